"""How fast an EtherCAT line runs from this master: lock-step cycles per second (the next frame
sent as soon as the last came back), the frame round trip at a real-time period (send to
receive of the one frame per cycle, median and p99), and the read of every slave's AL status
the line makes every STATE_CHECK_FRAMES cycles (median and p99). Measured against whatever
line is on the interface (`sim_bus.ethercat.netns` makes a virtual one); `bus-bench` prints
the figures."""

import os
import time

import numpy as np

from driver.clock import CycleClock, DriveClock, WallClock, prefer_real_time
from driver.ethercat_master import STATE_CHECK_FRAMES
from driver.ethercat_transport import EthercatTransport, open_ethercat_transports
from driver.interface import SampleLost
from protocol import objects
from protocol.dictionary import mapped_object, variable

ENABLE_OPERATION = 0x0F


def _bring_up(transports: list[EthercatTransport], period: float) -> None:
    """The ESI's own cyclic objects on every slave, the line in OP."""
    esi = transports[0].line.esi
    for transport in transports:
        dictionary = transport.dictionary
        outputs = [mapped_object(variable(dictionary, e.index, e.subindex))
                   for e in esi.rxpdos[0].entries]
        inputs = [mapped_object(variable(dictionary, e.index, e.subindex))
                  for e in esi.txpdos[0].entries]
        transport.boot(5.0)
        transport.write(objects.MODES_OF_OPERATION, 0, objects.MODE_CYCLIC_SYNC_TORQUE)
        transport.map_process_data(outputs, inputs)
        transport.start(period)


def _cycle(transports: list[EthercatTransport], outputs: tuple[int, ...]) -> None:
    for transport in transports:
        transport.send(outputs)
    try:
        for transport in transports:
            transport.exchange()
    except SampleLost:
        pass  # a frame the line rode through: counted by the line (`lost_frames`)


def measure_line(interface: str, slaves: int, cycles: int = 5000,
                 period: float = 1e-3, sync: str = "free_run") -> dict:
    """{'slaves', 'drive_time_cycles_per_s', 'round_trip_median_us', 'round_trip_p99_us',
    'missed_cycles', 'lost_frames', 'state_check_median_us', 'state_check_p99_us'} for the
    first `slaves` slaves on `interface` (the line must be there).
    `sync` "dc": the line on distributed clocks, the real-time cycles following the reference
    clock, with the propagation delays measured and the master-to-reference-clock offset
    ('dc_delays_ns', 'dc_offset' median/p99/max in us after settling); no lock-step figure
    then: slaves on SYNC0 want a frame every period of wall time, which lock-step does not
    promise; and the measurement runs at real-time priority, as the control loop does
    (`driver.clock.prefer_real_time`; given back after)."""
    dc = sync == "dc"
    refused = prefer_real_time() if dc else "free run"
    # free run: the master on drive time (the slaves' watchdog off) for the lock-step rate
    transports = open_ethercat_transports(interface, range(slaves),
                                          clock=WallClock() if dc else DriveClock(), sync=sync)
    try:
        _bring_up(transports, period)
        outputs = (0, 0)  # controlword 0: the drives stay disabled, the frames are real
        for _ in range(100):
            _cycle(transports, outputs)
        rate = None
        if not dc:
            start = time.perf_counter()
            for _ in range(cycles):
                _cycle(transports, outputs)
            rate = round(cycles / (time.perf_counter() - start))
        line = transports[0].line
        clock = CycleClock(period, WallClock())
        round_trips = np.empty(cycles)
        for k in range(cycles):
            clock.wait(line.clock_trim())
            t0 = time.perf_counter()
            _cycle(transports, outputs)
            round_trips[k] = time.perf_counter() - t0
            clock.check_overrun()
        figures = {} if line.dc is None else {
            "dc_delays_ns": line.dc.delays_ns,
            "dc_offset": {"median_us": round(line.dc.offsets_ns.percentile(50) / 1e3, 1),
                          "p99_us": round(line.dc.offsets_ns.percentile(99) / 1e3, 1),
                          "max_us": round(line.dc.offsets_ns.max / 1e3, 1),
                          "cycles": line.dc.offsets_ns.count}}
        checks = np.empty(cycles // STATE_CHECK_FRAMES)
        for k in range(len(checks)):
            if dc:  # slaves on SYNC0 want their frame every period meanwhile
                clock.wait(line.clock_trim())
                _cycle(transports, outputs)
            t0 = time.perf_counter()
            line.check_states()
            checks[k] = time.perf_counter() - t0
        return {
            **figures,
            "slaves": slaves,
            "frames": line.frames,
            "drive_time_cycles_per_s": rate,
            "round_trip_median_us": round(float(np.median(round_trips)) * 1e6, 1),
            "round_trip_p99_us": round(float(np.percentile(round_trips, 99)) * 1e6, 1),
            "period_us": round(period * 1e6),
            "missed_cycles": clock.missed_cycles,
            "lost_frames": line.lost_frames,
            "state_check_median_us": round(float(np.median(checks)) * 1e6, 1),
            "state_check_p99_us": round(float(np.percentile(checks, 99)) * 1e6, 1),
        }
    finally:
        if refused is None:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        for transport in transports:
            transport.stop()
            transport.close()
