"""Distributed-clock set-ups of masters nobody here wrote against the virtual line, datagram
by datagram, with what each master itself checks on the way (SOEM's ecx_configdc is in
tests/test_ethercat_dc.py).

IgH's EtherLab master (etherlab/ethercat 1.6: master/fsm_master.c, fsm_slave_scan.c, slave.c,
master.c, fsm_slave_config.c) differs from SOEM where a slave could trip on it:
- the delays come from a one-byte BWR of 0x0900 and 16-byte reads of ports 0-3, ports whose
  time did not change since the scan's first read counted as bypassed, and the loop states of
  the DL status (0x0110);
- the offset is worked out from one 28-byte read of 0x0910-0x092B (system time, the
  processing unit's receive time, offset, delay) against the application's time, and offset
  and delay go in one 12-byte write of 0x0920, then 0x0930 resets the control loop;
- the reference clock follows the master (a 32-bit FPWR of 0x0910 with the application's
  time, every other cycle in IgH's dc_user example) and the others follow it by a 32-bit FRMW;
- per slave, SYNC0's cycle (8 bytes at 0x09A0) goes before IgH waits for 0x092C to drop
  under 10 us, then the start time (the application's time + 100 ms, in phase with its first
  time), and only then the assignment and activation in one 16-bit write of 0x0980 (0x0300),
  all in PRE-OP, before SAFE-OP is asked for.

KickCAT (leducp/KickCAT: lib/master/src/Bus.cc resetSlaves, dc.cc Bus::enableDC, as its
marvin example calls it): its Python binding has no DC (no enableDC, no register access), so
its C++ sequence is replayed here: the reset of Bus::init (a BWR of zeros on 0x0910, 0x0981,
0x0980, then 0x0930 and the filter depths 0x0934), then in INIT the latch, each slave's
receive times and offset/delay, 15000 FRMWs of 0x0910 back to back (static drift
compensation), and SYNC0's cycle, start time and activation by broadcast writes, one start
time for all; PRE-OP, mapping, SAFE-OP and OP after, with an FRMW in every cycle.
"""

import struct

import numpy as np

from protocol import ethercat as ec
from sim_bus.ethercat import dc
from sim_bus.ethercat.segment import Segment
from tests.segment_frames import FrameMaster, enable_sequence, talos_devices

Cmd = ec.Command
AL = ec.AlState
PERIOD_NS = 1_000_000
SHIFT_NS = 400_000  # SYNC0 shift the application asks for (ecrt_slave_config_dc)
ASSIGN_ACTIVATE = 0x0300  # SYNC0 and cyclic operation, the unit assigned to EtherCAT
# the application's clock at host time 0: its low 32 bits, all a sync datagram carries, wrap
# at host time 20.2 s, while the test's line is on its way to OP
APP_EPOCH_NS = (800_000_000_000_000_000 >> 32 << 32) - 20_200_000_000
# IgH's own limits (fsm_master.c, fsm_slave_config.c)
EC_SYSTEM_TIME_TOLERANCE_NS = 1000
EC_DC_MAX_SYNC_DIFF_NS = 10_000
EC_DC_SYNC_WAIT_MS = 5000
EC_DC_START_OFFSET = 100_000_000
NEXT_PORT = (3, 2, 0, 1)  # IgH's port order (slave.c next_table)
PREVIOUS_PORT = (2, 3, 1, 0)


class Port:
    def __init__(self):
        self.receive_time = 0
        self.bypassed = self.loop_closed = False
        self.next_slave: IghSlave | None = None
        self.delay_to_next_dc = 0


class IghSlave:
    """What IgH keeps of a slave for its DC calculations (ec_slave_t's ports and delays)."""

    def __init__(self, position: int):
        self.position = position
        self.ports = [Port() for _ in range(4)]
        self.upstream_port = 0
        self.transmission_delay = 0

    # slave.c, for slaves that all support DC
    def next_port(self, index: int) -> int:
        while True:
            index = NEXT_PORT[index]
            if self.ports[index].next_slave is not None:
                return index
            if index == self.upstream_port:
                return self.upstream_port

    def previous_normal_port(self, index: int) -> int:
        while True:
            index = PREVIOUS_PORT[index]
            port = self.ports[index]
            if not port.bypassed and port.next_slave is not None:
                return index
            if index == self.upstream_port:
                return self.upstream_port

    def calc_upstream_port(self) -> None:
        self.upstream_port = 0
        replace = self.ports[0].loop_closed or self.ports[0].bypassed
        for i in range(1, 4):
            port = self.ports[i]
            if not port.loop_closed and not port.bypassed:
                diff = _s32(port.receive_time - self.ports[self.upstream_port].receive_time)
                if diff < 0 or replace:
                    self.upstream_port, replace = i, False

    def rtt_sum(self) -> int:
        total, index = 0, self.next_port(self.upstream_port)
        while index != self.upstream_port:
            previous = self.previous_normal_port(index)
            if not self.ports[index].bypassed:
                total += (self.ports[index].receive_time
                          - self.ports[previous].receive_time) & 0xFFFFFFFF
            index = self.next_port(index)
        return total & 0xFFFFFFFF

    def calc_port_delays(self) -> None:
        index = self.next_port(self.upstream_port)
        while index != self.upstream_port:
            following = self.ports[index].next_slave
            previous = self.previous_normal_port(index)
            rtt = 0 if self.ports[index].bypassed else (
                self.ports[index].receive_time - self.ports[previous].receive_time) & 0xFFFFFFFF
            delay = ((rtt - following.rtt_sum()) & 0xFFFFFFFF) // 2
            self.ports[index].delay_to_next_dc = delay
            following.ports[following.upstream_port].delay_to_next_dc = delay
            index = self.next_port(index)

    def calc_transmission_delays(self, delay: list[int]) -> None:
        self.transmission_delay = delay[0]
        index = self.next_port(self.upstream_port)
        while index != self.upstream_port:
            delay[0] += self.ports[index].delay_to_next_dc
            self.ports[index].next_slave.calc_transmission_delays(delay)
            index = self.next_port(index)
        delay[0] += self.ports[self.upstream_port].delay_to_next_dc


def _topology(slaves: list[IghSlave]) -> None:
    """master.c ec_master_calc_topology_rec over the scanned slaves."""
    position = [0]

    def walk(slave: IghSlave, upstream: IghSlave | None) -> None:
        slave.ports[slave.upstream_port].next_slave = upstream
        index = NEXT_PORT[slave.upstream_port]
        while index != slave.upstream_port:
            if not slave.ports[index].loop_closed:
                position[0] += 1
                assert position[0] < len(slaves), "IgH: Failed to calculate bus topology"
                slave.ports[index].next_slave = slaves[position[0]]
                walk(slaves[position[0]], slave)
            index = NEXT_PORT[index]

    walk(slaves[0], None)


def _s32(value: int) -> int:
    value &= 0xFFFFFFFF
    return value - (1 << 32) if value >= 1 << 31 else value


def _s64(value: int) -> int:
    value &= (1 << 64) - 1
    return value - (1 << 64) if value >= 1 << 63 else value


class IghMaster:
    """IgH's datagrams over a `FrameMaster`'s line: the application's cycle (its time, the
    reference clock's sync, the domain's LRW) with at most one datagram of the master's state
    machines in each frame, as IgH injects them into the application's sends."""

    def __init__(self, segment: Segment):
        self.frames = FrameMaster(segment)
        self.segment = segment
        self.count = self.frames.count
        self.slaves = [IghSlave(k) for k in range(self.count)]
        self.app_time = 0
        self.dc_ref_time = 0
        self.dc_offset_valid = False
        self.cycles = 0
        self.controlwords = np.zeros(self.count, dtype=np.int64)
        self.lrw_wkc = 0

    def station(self, k: int, register: int) -> int:
        return (0x1001 + k) | register << 16

    def exchange(self, *datagrams) -> list[tuple[bytes, int]]:
        """(command, address, data) datagrams in one frame at the frames' time now."""
        frame = self.frames.send([(c, k, a, d) for k, (c, a, d) in enumerate(datagrams)])
        return [ec.datagram_result(frame, span) for span in ec.datagram_spans(frame)]

    def cycle(self, *fsm) -> list[tuple[bytes, int]]:
        """One application cycle a period on (the SYNC0 events due by then run first, as the
        line does): ecrt_master_application_time; the reference clock synced to it every
        other cycle (ecrt_master_sync_reference_clock: a 32-bit FPWR of 0x0910) and the
        others to the reference (ecrt_master_sync_slave_clocks: a 32-bit FRMW), both only
        once the offsets are written; the domain's LRW once mapped; then `fsm`'s datagrams.
        Their results (data, working counter), `fsm`'s last."""
        frames = self.frames
        frames.now += PERIOD_NS * 1e-9
        _wake_through(self.segment, frames.now)
        self.app_time = APP_EPOCH_NS + round(frames.now * 1e9)
        if not self.dc_ref_time:
            self.dc_ref_time = self.app_time
        datagrams = []
        if self.dc_offset_valid:
            if self.cycles % 2 == 0:
                datagrams.append((Cmd.FPWR, self.station(0, dc.REG_SYSTEM_TIME),
                                  struct.pack("<I", self.app_time & 0xFFFFFFFF)))
            datagrams.append((Cmd.FRMW, self.station(0, dc.REG_SYSTEM_TIME), bytes(4)))
        mapped = hasattr(frames, "layouts")
        if mapped:
            datagrams.append((Cmd.LRW, 0, frames.image(self.controlwords,
                                                       np.zeros(self.count, np.int64))))
        self.cycles += 1
        results = self.exchange(*datagrams, *fsm)
        if mapped:
            self.lrw_wkc = results[len(datagrams) - 1][1]
        return results[len(datagrams):]

    # --- the scan: fsm_master.c, fsm_slave_scan.c ---------------------------------------

    def scan(self) -> None:
        for k, slave in enumerate(self.slaves):  # old receive times, before any latch
            [(times, wkc)] = self.cycle((Cmd.APRD, (-k & 0xFFFF) | dc.REG_RECEIVE_TIME_PORT0
                                        << 16, bytes(16)))
            assert wkc == 1
            for i, port in enumerate(slave.ports):
                port.receive_time = struct.unpack_from("<I", times, 4 * i)[0]
        [(_, wkc)] = self.cycle((Cmd.BWR, ec.REG_STATION_ADDRESS << 16, bytes(2)))
        assert wkc == self.count
        [(_, wkc)] = self.cycle((Cmd.BWR, dc.REG_RECEIVE_TIME_PORT0 << 16, bytes(1)))
        assert wkc == self.count  # the latch: every port's receive time
        for k in range(self.count):
            [(_, wkc)] = self.cycle((Cmd.APWR, (-k & 0xFFFF) | ec.REG_STATION_ADDRESS << 16,
                                     struct.pack("<H", 0x1001 + k)))
            assert wkc == 1
        for k, slave in enumerate(self.slaves):
            [(features, _)] = self.cycle((Cmd.FPRD, self.station(k, ec.REG_FEATURES),
                                          bytes(2)))
            octet = features[0]
            assert octet >> 2 & 1 and octet >> 3 & 1  # DC, 64-bit range
            [(_, wkc)] = self.cycle((Cmd.FPRD, self.station(k, dc.REG_SYSTEM_TIME), bytes(8)))
            assert wkc == 1  # has_dc_system_time
            [(times, wkc)] = self.cycle((Cmd.FPRD, self.station(k, dc.REG_RECEIVE_TIME_PORT0),
                                         bytes(16)))
            assert wkc == 1
            for i, port in enumerate(slave.ports):
                new = struct.unpack_from("<I", times, 4 * i)[0]
                port.bypassed = new == port.receive_time
                port.receive_time = new
            [(status, _)] = self.cycle((Cmd.FPRD, self.station(k, ec.REG_DL_STATUS),
                                        bytes(2)))
            (status,) = struct.unpack("<H", status)
            for i, port in enumerate(slave.ports):
                port.loop_closed = bool(status & 1 << (8 + 2 * i))
        # ec_master_calc_dc: the first DC slave is the reference clock
        for slave in self.slaves:
            slave.calc_upstream_port()
        _topology(self.slaves)
        for slave in self.slaves:
            slave.calc_port_delays()
        self.slaves[0].calc_transmission_delays([0])

    def write_system_times(self) -> None:
        """fsm_master.c: each slave's offset onto the application's time, with its delay."""
        for k, slave in enumerate(self.slaves):
            [(times, wkc)] = self.cycle((Cmd.FPRD, self.station(k, dc.REG_SYSTEM_TIME),
                                         bytes(28)))
            assert wkc == 1
            app_time_sent = self.app_time
            system_time, _, old_offset, old_delay = struct.unpack("<QQQI", times)
            time_diff = _s64(app_time_sent - system_time)
            new_offset = old_offset
            if abs(time_diff) > EC_SYSTEM_TIME_TOLERANCE_NS:
                new_offset = (time_diff + old_offset) & ((1 << 64) - 1)
            if new_offset == old_offset and slave.transmission_delay == old_delay:
                continue
            [(_, wkc)] = self.cycle((Cmd.FPWR, self.station(k, dc.REG_SYSTEM_TIME_OFFSET),
                                     struct.pack("<QI", new_offset, slave.transmission_delay)))
            assert wkc == 1
            [(_, wkc)] = self.cycle((Cmd.FPWR, self.station(k, dc.REG_SPEED_COUNTER_START),
                                     struct.pack("<H", 0x1000)))
            assert wkc == 1
        self.dc_offset_valid = True

    def configure_dc(self, k: int) -> tuple[int, int, list[int]]:
        """fsm_slave_config.c for slave k, from its DC cycle on: SYNC0's cycle, the wait for
        its system time difference, the start time, the assignment and activation. (IgH's
        start time, the system time read as it went, the differences read on the way)."""
        [(_, wkc)] = self.cycle((Cmd.FPWR, self.station(k, dc.REG_SYNC0_CYCLE_TIME),
                                 struct.pack("<II", PERIOD_NS, 0)))
        assert wkc == 1
        started = self.cycles
        differences = []
        while True:
            [(difference, wkc)] = self.cycle((Cmd.FPRD, self.station(
                k, dc.REG_SYSTEM_TIME_DIFFERENCE), bytes(4)))
            assert wkc == 1
            differences.append(struct.unpack("<I", difference)[0] & 0x7FFFFFFF)
            if differences[-1] <= EC_DC_MAX_SYNC_DIFF_NS:
                break
            assert (self.cycles - started) * PERIOD_NS < EC_DC_SYNC_WAIT_MS * 1_000_000, (
                f"IgH: slave {k} did not sync after {EC_DC_SYNC_WAIT_MS} ms: {differences[-5:]}")
        start_time = self.app_time + EC_DC_START_OFFSET
        remainder = (start_time - self.dc_ref_time) % PERIOD_NS
        start = start_time + PERIOD_NS - remainder + SHIFT_NS
        [(_, wkc), (now, _)] = self.cycle(
            (Cmd.FPWR, self.station(k, dc.REG_START_TIME), struct.pack("<Q", start)),
            (Cmd.FPRD, self.station(k, dc.REG_SYSTEM_TIME), bytes(8)))
        assert wkc == 1
        [(_, wkc)] = self.cycle((Cmd.FPWR, self.station(k, dc.REG_CYCLIC_UNIT_CONTROL),
                                 struct.pack("<H", ASSIGN_ACTIVATE)))
        assert wkc == 1
        return start, struct.unpack("<Q", now)[0], differences

    def request(self, k: int, state: int) -> None:
        """fsm_change.c's first step: AL control written."""
        [(_, wkc)] = self.cycle((Cmd.FPWR, self.station(k, ec.REG_AL_CONTROL),
                                 struct.pack("<H", state)))
        assert wkc == 1

    def al_status(self, k: int) -> int:
        [(status, _)] = self.cycle((Cmd.FPRD, self.station(k, ec.REG_AL_STATUS), bytes(2)))
        return struct.unpack("<H", status)[0]

    def change_state(self, k: int, state: int, cycles: int = 300) -> int:
        """fsm_change.c: AL control written, then AL status polled until it shows `state`
        (or the error bit); the state read last."""
        self.request(k, state)
        for _ in range(cycles):
            status = self.al_status(k)
            if status & 0x0F == state or status & ec.AL_ERROR:
                return status
        return status


def _wake_through(segment: Segment, until: float) -> None:
    while (at := segment.next_sync0(until)) is not None and at <= until:
        segment.run_sync0(at)


def test_igh_dc_set_up_runs_the_line_on_its_sync0():
    """IgH's scan, offsets, per-slave DC configuration and state changes against four of
    talos' drives: the delays it works out are the line's, every slave's system time
    difference drops under IgH's 10 us before activation, each start time lies in the future
    and in phase with the application's first time (+ the shift), SYNC0 fires there every
    period on every slave, every slave reaches OP and its drive follows the controlwords, and
    IgH's sync monitor (a BRD of 0x092C) stays under a microsecond."""
    segment = Segment(talos_devices(4))
    igh = IghMaster(segment)
    igh.frames.now = 20.0
    igh.scan()
    hop = dc.HOP_DELAY * 1e9
    delays = [slave.transmission_delay for slave in igh.slaves]
    assert [abs(d - k * hop) <= k * hop * 1e-4 + 2 for k, d in enumerate(delays)] == [True] * 4
    assert [slave.upstream_port for slave in igh.slaves] == [0] * 4
    for k in range(igh.count):  # clear SMs and the DC assignment (INIT), then the mapping
        [(_, wkc)] = igh.cycle((Cmd.FPWR, igh.station(k, ec.REG_SM0), bytes(4 * ec.SM_SIZE)))
        assert wkc == 1
        [(_, wkc)] = igh.cycle((Cmd.FPWR, igh.station(k, dc.REG_CYCLIC_UNIT_CONTROL),
                                bytes(2)))
        assert wkc == 1
    igh.write_system_times()
    igh.frames.map_process_data()
    starts = []
    for k in range(igh.count):
        start, now, differences = igh.configure_dc(k)
        assert differences[-1] <= EC_DC_MAX_SYNC_DIFF_NS
        assert 0.09e9 < start - now < 0.11e9  # in the future, by IgH's 100 ms
        assert (start - igh.dc_ref_time) % PERIOD_NS == SHIFT_NS
        assert segment.escs[k].dc.sync0_active
        starts.append(start)
    # SYNC0 at IgH's start time: the first pulse of each slave at its own start, all on one
    # phase of the application's clock
    firsts = [esc.dc.next_sync0 for esc in segment.escs]
    assert firsts == starts
    for k in range(igh.count):
        assert igh.change_state(k, AL.SAFE_OP) == AL.SAFE_OP
    for k in range(igh.count):  # OP, entered at a SYNC0 with the domain's outputs
        igh.request(k, AL.OP)
    for _ in range(300):  # polled as fsm_change polls: OP comes with the first SYNC0
        states = [igh.al_status(k) for k in range(igh.count)]
        if states == [AL.OP] * igh.count or any(s & ec.AL_ERROR for s in states):
            break
    assert states == [AL.OP] * igh.count
    for n in range(200):  # the drives enabled by the domain's controlwords
        igh.controlwords[:] = enable_sequence(n, igh.count)
        igh.cycle()
    assert igh.lrw_wkc == 3 * igh.count
    assert all(device.state.name == "OPERATION_ENABLED" for device in segment.drives.devices)
    # every pulse fired, from each slave's start on, a period apart
    assert min(esc.dc.sync0_count for esc in segment.escs) > 200
    assert [(esc.dc.next_sync0 - start) - esc.dc.sync0_count * PERIOD_NS
            for esc, start in zip(segment.escs, starts, strict=True)] == [0] * igh.count
    # the reference clock follows the application's time (IgH's 32-bit writes, across the
    # wrap of their low 32 bits), the others follow the reference
    assert (igh.app_time - APP_EPOCH_NS) * 1e-9 > 20.2
    assert [abs(esc.dc.system_time(igh.frames.now) - igh.app_time) < 1000
            for esc in segment.escs] == [True] * igh.count
    # ecrt_master_sync_monitor_queue / _process: the largest difference on the line
    [(difference, wkc)] = igh.cycle((Cmd.BRD, dc.REG_SYSTEM_TIME_DIFFERENCE << 16, bytes(4)))
    assert wkc == igh.count
    assert struct.unpack("<I", difference)[0] & 0x7FFFFFFF < 1000


# KickCAT's since_ecat_epoch at host time 0 (any epoch: it is the master's time)
ECAT_EPOCH_NS = APP_EPOCH_NS
KICKCAT_SHIFT_NS = 500_000  # enableDC(1ms, 500us, 100ms), as its marvin example
KICKCAT_START_DELAY_NS = 100_000_000
KICKCAT_SYNC_THRESHOLD_NS = 10_000  # isDCSynchronized(10us), as marvin
DRIFT_COMPENSATION_FRAMES = 15_000
DRIFT_COMPENSATION_SPACING = 50e-6  # s between them: as fast as a frame comes back


def _exchange(frames: FrameMaster, *datagrams) -> list[tuple[bytes, int]]:
    frame = frames.send([(c, k, a, d) for k, (c, a, d) in enumerate(datagrams)])
    return [ec.datagram_result(frame, span) for span in ec.datagram_spans(frame)]


def test_kickcat_enable_dc_runs_the_line_on_its_sync0():
    """KickCAT's reset and Bus::enableDC against four of talos' drives, in INIT: the delays it
    works out (its computePropagationDelay on a line) are the line's, after its burst of
    FRMWs every slave's system time difference is under its 10 us, one start time broadcast
    to all is in every slave's future and SYNC0 fires there every period on all of them; the
    line then comes to OP on SYNC0 with an FRMW in every cycle and the drives follow."""
    segment = Segment(talos_devices(4))
    frames = FrameMaster(segment)  # station addresses, as Bus::init sets them
    count = frames.count
    frames.now = 20.0

    def bwr(register: int, data: bytes) -> None:
        [(_, wkc)] = _exchange(frames, (Cmd.BWR, register << 16, data))
        assert wkc == count

    def master_time() -> int:
        return ECAT_EPOCH_NS + round(frames.now * 1e9)

    bwr(dc.REG_SYSTEM_TIME, bytes(8))  # Bus::resetSlaves, its DC part
    bwr(dc.REG_SYNC_ACTIVATION, bytes(1))
    bwr(dc.REG_CYCLIC_UNIT_CONTROL, bytes(2))
    bwr(dc.REG_SPEED_COUNTER_START, struct.pack("<H", 0x1000))
    bwr(0x0934, struct.pack("<H", 0x0C00))  # filter depths
    frames.now += 0.01
    now = master_time()  # sampled before the latch
    bwr(dc.REG_RECEIVE_TIME_PORT0, bytes(1))
    ports, latched = [], []
    for k in range(count):
        [(times, wkc), (unit, unit_wkc)] = _exchange(
            frames, (Cmd.FPRD, (0x1001 + k) | dc.REG_RECEIVE_TIME_PORT0 << 16, bytes(16)),
            (Cmd.FPRD, (0x1001 + k) | dc.REG_RECEIVE_TIME_UNIT << 16, bytes(8)))
        assert wkc == unit_wkc == 1
        ports.append(struct.unpack("<4I", times))
        latched.append(struct.unpack("<Q", unit)[0])
    # on a line: port 0 the entry, port 1 to the next (open on all but the last)
    deltas = [(p[1] - p[0]) & 0xFFFFFFFF if k < count - 1 else 0 for k, p in enumerate(ports)]
    delays = [0]
    for k in range(1, count):
        delays.append(delays[-1] + (deltas[k - 1] - deltas[k]) // 2)
    hop = dc.HOP_DELAY * 1e9
    assert [abs(d - k * hop) <= k * hop * 1e-4 + 2 for k, d in enumerate(delays)] == [True] * 4
    for k in range(count):  # applyMasterTime
        for register, data in ((dc.REG_SYSTEM_TIME_DELAY, struct.pack("<I", delays[k])),
                               (dc.REG_SYSTEM_TIME_OFFSET,
                                struct.pack("<Q", (now - latched[k]) % 2**64))):
            [(_, wkc)] = _exchange(frames, (Cmd.FPWR, (0x1001 + k) | register << 16, data))
            assert wkc == 1
    bwr(0x0934, struct.pack("<H", 0x0C00))
    bwr(dc.REG_SPEED_COUNTER_START, struct.pack("<H", 0x1000))
    for _ in range(DRIFT_COMPENSATION_FRAMES):  # static drift compensation
        frames.now += DRIFT_COMPENSATION_SPACING
        [(_, wkc)] = _exchange(frames, (Cmd.FRMW, 0x1001 | dc.REG_SYSTEM_TIME << 16,
                                        struct.pack("<Q", master_time())))
        assert wkc == count
    differences = []
    for k in range(1, count):  # isDCSynchronized
        [(difference, wkc)] = _exchange(
            frames, (Cmd.FPRD, (0x1001 + k) | dc.REG_SYSTEM_TIME_DIFFERENCE << 16, bytes(4)))
        differences.append(struct.unpack("<I", difference)[0] & 0x7FFFFFFF)
    assert max(differences) <= KICKCAT_SYNC_THRESHOLD_NS
    bwr(dc.REG_SYNC0_CYCLE_TIME, struct.pack("<I", PERIOD_NS))
    [(network_time, wkc)] = _exchange(frames, (Cmd.FPRD, 0x1001 | dc.REG_SYSTEM_TIME << 16,
                                               bytes(8)))
    assert wkc == 1
    (network_time,) = struct.unpack("<Q", network_time)
    start = (network_time // PERIOD_NS * PERIOD_NS + PERIOD_NS + KICKCAT_SHIFT_NS
             + KICKCAT_START_DELAY_NS)
    bwr(dc.REG_START_TIME, struct.pack("<Q", start))
    bwr(dc.REG_SYNC_ACTIVATION, b"\x03")
    assert [esc.dc.next_sync0 for esc in segment.escs] == [start] * count  # in every future
    host_starts = [esc.dc.next_sync0_host_time(frames.now) for esc in segment.escs]
    assert max(host_starts) - min(host_starts) < 50e-9  # the same instant on every slave

    def cycle() -> list[tuple[bytes, int]]:
        frames.now += PERIOD_NS * 1e-9
        _wake_through(segment, frames.now)
        datagrams = []
        if hasattr(frames, "layouts"):
            datagrams.append((Cmd.LRW, 0, frames.image(controlwords, np.zeros(count,
                                                                              np.int64))))
        datagrams.append((Cmd.FRMW, 0x1001 | dc.REG_SYSTEM_TIME << 16,
                          struct.pack("<Q", master_time())))
        return _exchange(frames, *datagrams)

    controlwords = np.zeros(count, dtype=np.int64)
    frames.map_process_data()  # PRE-OP, the mapping
    for state in (AL.SAFE_OP, AL.OP):  # requestState, then the cycle until the line is there
        bwr(ec.REG_AL_CONTROL, struct.pack("<H", state))
        for _ in range(300):
            cycle()
            if frames.states() == [state] * count:
                break
        assert frames.states() == [state] * count
    for n in range(200):
        controlwords[:] = enable_sequence(n, count)
        [(_, lrw_wkc), (_, frmw_wkc)] = cycle()
    assert lrw_wkc == 3 * count and frmw_wkc == count
    assert all(device.state.name == "OPERATION_ENABLED" for device in segment.drives.devices)
    assert min(esc.dc.sync0_count for esc in segment.escs) > 200
    assert [esc.dc.next_sync0 - start - esc.dc.sync0_count * PERIOD_NS
            for esc in segment.escs] == [0] * count
    differences = [struct.unpack("<I", _exchange(frames, (
        Cmd.FPRD, (0x1001 + k) | dc.REG_SYSTEM_TIME_DIFFERENCE << 16, bytes(4)))[0][0])[0]
        & 0x7FFFFFFF for k in range(1, count)]
    assert max(differences) <= KICKCAT_SYNC_THRESHOLD_NS
