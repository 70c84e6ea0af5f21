"""How fast an EtherCAT line runs from this master: lock-step cycles per second (the next frame
sent as soon as the last came back), the frame round trip at a real-time period (send to
receive of the one frame per cycle, median and p99), and the read of every slave's AL status
the line makes every STATE_CHECK_FRAMES cycles (median and p99). Measured against whatever
line is on the interface (`sim_bus.ethercat.netns` makes a virtual one); `bus-bench` prints
the figures."""

import time

import numpy as np

from driver.clock import CycleClock
from driver.ethercat_master import STATE_CHECK_FRAMES
from driver.ethercat_transport import EthercatTransport, open_ethercat_transports
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
    for transport in transports:
        transport.exchange()


def measure_line(interface: str, slaves: int, cycles: int = 5000,
                 period: float = 1e-3) -> dict:
    """{'slaves', 'lockstep_cycles_per_s', 'round_trip_median_us', 'round_trip_p99_us',
    'missed_cycles', 'state_check_median_us', 'state_check_p99_us'} for the first `slaves`
    slaves on `interface` (the line must be there)."""
    transports = open_ethercat_transports(interface, range(slaves), lockstep=True)
    try:
        _bring_up(transports, period)
        outputs = (0, 0)  # controlword 0: the drives stay disabled, the frames are real
        for _ in range(100):
            _cycle(transports, outputs)
        start = time.perf_counter()
        for _ in range(cycles):
            _cycle(transports, outputs)
        rate = cycles / (time.perf_counter() - start)
        line = transports[0].line
        clock = CycleClock(period, lockstep=False)
        round_trips = np.empty(cycles)
        for k in range(cycles):
            clock.wait()
            t0 = time.perf_counter()
            _cycle(transports, outputs)
            round_trips[k] = time.perf_counter() - t0
            clock.check_overrun()
        checks = np.empty(cycles // STATE_CHECK_FRAMES)
        for k in range(len(checks)):
            t0 = time.perf_counter()
            line.check_states()
            checks[k] = time.perf_counter() - t0
        return {
            "slaves": slaves,
            "frames": line.frames,
            "lockstep_cycles_per_s": round(rate),
            "round_trip_median_us": round(float(np.median(round_trips)) * 1e6, 1),
            "round_trip_p99_us": round(float(np.percentile(round_trips, 99)) * 1e6, 1),
            "period_us": round(period * 1e6),
            "missed_cycles": clock.missed_cycles,
            "state_check_median_us": round(float(np.median(checks)) * 1e6, 1),
            "state_check_p99_us": round(float(np.percentile(checks, 99)) * 1e6, 1),
        }
    finally:
        for transport in transports:
            transport.stop()
            transport.close()
