"""Distributed clocks on the linked line (`sim_bus.ethercat.linked`): what SOEM does on the wire
for `config_dc`, `dc_sync` and the cyclic frame's reference clock datagram, done with the same
register reads and writes on the slave controllers in this process, so their DC units
(`sim_bus.ethercat.dc`) see exactly what a veth line's see.

Time: the clock the line is given (`driver.clock`). On drive time (lock-step) the line's clocks
run on its frames' count x the SYNC0 cycle, with no drift (the drive time is the only time
there is, so a run is the same every time); on the wall clock, the host's monotonic clock, each
slave drifting its stated amount, and the SYNC0 events due run before each frame.
"""

import struct
import time
from collections.abc import Sequence
from typing import Protocol

from protocol import ethercat as ec
from sim_bus.ethercat import dc
from sim_bus.ethercat.esc import Esc

SYNC_DELAY_NS = 100_000_000  # SOEM's SyncDelay: the first SYNC0 this far after dc_sync
EPOCH_2000_NS = 946_684_800 * 1_000_000_000  # EtherCAT time counts from 2000-01-01
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")


class LineClock(Protocol):
    """What the line needs of the clock it is given (`driver.clock.WallClock` or
    `DriveClock`, made by the master's side with `clock_for`)."""

    runs_alone: bool

    def now(self) -> float: ...

    def advance(self, seconds: float) -> None: ...


class LinkedClock:
    """The linked line's time and its reference clock datagram."""

    def __init__(self, escs: Sequence[Esc], clock: LineClock):
        self.escs = list(escs)
        self.clock = clock
        self.configured = False  # config_dc ran: the cyclic frame carries the time datagram
        if not clock.runs_alone:
            for esc in self.escs:
                esc.dc.drift = 0.0

    def now(self) -> float:
        return self.clock.now()

    def _at(self, t: float) -> None:
        for esc in self.escs:
            esc.now = t + esc.dc.hop

    def config_dc(self) -> bool:
        """SOEM's ecx_configdc: a broadcast write to 0x0900 latches every receive time, the
        master's time goes into each offset (0x0920, against the latched 0x0918), and each
        propagation delay (0x0928) from the port times of the slave and its parent."""
        t = self.now()
        self._at(t)
        if self.clock.runs_alone:
            master_time = time.time_ns() - EPOCH_2000_NS
        else:
            master_time = int(round(t * 1e9))  # drive time
        slaves = [esc for esc in self.escs if esc.present
                  and _u16(esc, ec.REG_FEATURES) & dc.FEATURE_DC]
        for esc in slaves:
            esc._write(dc.REG_RECEIVE_TIME_PORT0, memoryview(bytes(4)))
        parent_span = delay = 0
        for k, esc in enumerate(slaves):
            port0, port1 = _read(esc, dc.REG_RECEIVE_TIME_PORT0, 8, "<II")
            (latched,) = _read(esc, dc.REG_RECEIVE_TIME_UNIT, 8, "<Q")
            esc._write(dc.REG_SYSTEM_TIME_OFFSET,
                       memoryview(_U64.pack((master_time - latched) & (2**64 - 1))))
            span = (port1 - port0) & 0xFFFFFFFF if not esc.dc.last_in_line else 0
            if k:  # the reference clock keeps delay 0
                delay += (parent_span - span) // 2
                esc._write(dc.REG_SYSTEM_TIME_DELAY, memoryview(_U32.pack(delay)))
            parent_span = span
        self.configured = bool(slaves)
        return self.configured

    def dc_sync(self, esc: Esc, active: bool, cycle_ns: int, shift_ns: int) -> None:
        """SOEM's ecx_dcsync0: cyclic operation off, the first SYNC0 a whole number of cycles
        past the slave's time plus SyncDelay, plus the shift; then SYNC0 on."""
        self._at(self.now())
        esc._write(dc.REG_SYNC_ACTIVATION, memoryview(b"\x00"))
        esc._write(dc.REG_CYCLIC_UNIT_CONTROL, memoryview(b"\x00"))
        (now,) = _read(esc, dc.REG_SYSTEM_TIME, 8, "<Q")
        start = ((now + SYNC_DELAY_NS) // cycle_ns) * cycle_ns + cycle_ns + shift_ns
        esc._write(dc.REG_START_TIME, memoryview(_U64.pack(start)))
        esc._write(dc.REG_SYNC0_CYCLE_TIME, memoryview(_U32.pack(cycle_ns)))
        activation = dc.ACTIVATION_CYCLIC | dc.ACTIVATION_SYNC0 if active else 0
        esc._write(dc.REG_SYNC_ACTIVATION, memoryview(bytes([activation])))

    def before_frame(self) -> int | None:
        """Real time: the SYNC0 events that came before this frame. Then the reference clock
        datagram (FRMW 0x0910: the first DC slave's system time read, written to the others
        as their compare value). The reference clock's time, or None before config_dc."""
        if not self.configured:
            return None
        t = self.now()
        if self.clock.runs_alone:
            self.run_sync0(t)
        self._at(t)
        present = [esc for esc in self.escs if esc.present]
        if not present:
            return None
        reference, *others = present
        (system_time,) = _read(reference, dc.REG_SYSTEM_TIME, 8, "<Q")
        data = memoryview(_U64.pack(system_time))
        for esc in others:
            esc._write(dc.REG_SYSTEM_TIME, data)
        return system_time

    def after_frame(self) -> None:
        """Drive time: a SYNC0 cycle of it passes, with the SYNC0 that takes this frame's
        outputs and samples the inputs the next frame reads."""
        if self.clock.runs_alone or not self.configured:
            return
        cycle = next((esc.dc.cycle_time for esc in self.escs if esc.dc.sync0_active), 0)
        if cycle:
            self.clock.advance(cycle * 1e-9)
            self.run_sync0(self.clock.now() - 1e-9)

    def run_sync0(self, until: float) -> None:
        """Each slave's SYNC0 pulses due by `until` taken, and its application run once, at
        the last of them: pulses that came while the line was late are one event, as on a
        segment (`sim_bus.ethercat.dc`); on drive time one pulse is due a frame."""
        for esc in self.escs:
            taken = False
            while esc.present:
                t = esc.dc.next_sync0_host_time(until)
                if t is None or t > until or not esc.take_sync0(t):
                    break
                taken = True
            if taken:
                esc.firmware.sync0(esc)


def _u16(esc: Esc, address: int) -> int:
    return esc.memory[address] | esc.memory[address + 1] << 8


def _read(esc: Esc, address: int, length: int, layout: str) -> tuple:
    out = bytearray(length)
    esc._read(address, length, memoryview(out), 0)
    return struct.unpack(layout, out)
