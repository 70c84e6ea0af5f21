"""An EtherCAT line linked in one process: the master's side of pysoem's API (what
`driver.ethercat_master` calls of `pysoem.Master` and its slaves) served straight by a
`Segment` of virtual slaves, with no wire, no raw socket and no root.

What `--sim` runs for an EtherCAT robot: the master's own code (scan, identity check, PDO
assignment by CoE, the state machine's requests and refusals, the process data image, the
working counter) against the same slave controllers and firmware as on a veth, through their
physical interface: register writes (AL control, sync managers, watchdog) and sync manager
buffer accesses go through `Esc`'s rules, so a completed output buffer runs the drive's cycle
exactly as a frame's does. What it leaves out is the wire: frames, datagrams, the mailbox's
framing (CoE SDO requests reach the slave's object layer directly, with its abort codes) and
wall-clock watchdogs (master and slaves live and die together). Those are exercised over a
veth (`sim_bus.ethercat.netns`), against SOEM and KickCAT.

The cycle runs as a batch (`LinkedImage`): the whole output image decoded at once, every
slave in OP whose cycle is steady advanced in one compiled call (`sim_bus.line_physics`),
the input image encoded at once and every slave's SM2/SM3 buffers written in one compiled
call; a slave whose cycle has more to it (a state change, a fault, a slave not in OP) takes
the ESC's and firmware's own path, so the line behaves exactly as slave by slave
(tests/test_line_physics.py compares the two).
"""

import struct
import time
from collections.abc import Callable
from operator import attrgetter

import numpy as np
import pysoem
from numba.typed import List

from protocol import ethercat as ec
from protocol.dictionary import mappable_object
from protocol.pdo import PdoLayout
from sim_bus.ethercat.esc import Esc
from sim_bus.ethercat.firmware import SlaveFirmware
from sim_bus.ethercat.frame_batch import InputEncoder, batchable_keys, into_buffers
from sim_bus.ethercat.linked_dc import LineClock, LinkedClock
from sim_bus.ethercat.mailbox import SdoAbort
from sim_bus.ethercat.segment import Segment

_U16 = struct.Struct("<H")
_PRESENT = attrgetter("present")
FIRST_STATION_ADDRESS = 0x1001  # SOEM's: position 0 gets 0x1001
WORKING_COUNTER_PER_SLAVE = 3  # an output write counts 2, an input read 1 (LRW)
NO_FRAME = -1  # SOEM's EC_NOFRAME: receive_processdata's answer when no frame came back


class LinkedSlave:
    """One slave as pysoem shows it to a master: identity, state, process data bytes, CoE."""

    def __init__(self, position: int, esc: Esc, firmware: SlaveFirmware, changes: list[int],
                 clock: LinkedClock):
        self.position = position
        self._clock = clock
        self._esc, self._firmware = esc, firmware
        self._changes = changes  # the line's count of accesses other than process data
        esi = firmware.esi
        self.man, self.id, self.rev = esi.identity
        self.name = esi.name
        self.state = 0
        self.al_status = 0
        self.output = b""
        self.input = b""
        self._outputs: tuple[int, int] | None = None  # (SM2 start, length) once mapped
        self._inputs: tuple[int, int] | None = None
        self._input_buffer = bytearray()
        self.layouts: tuple[PdoLayout, PdoLayout] | None = None  # (outputs, inputs) mapped

    # --- registers, as FPWR/FPRD would reach them -------------------------------------------

    def _write(self, address: int, data: bytes) -> bool:
        self._changes[0] += 1
        return self._esc._write(address, memoryview(data))

    def _fprd(self, address: int, size: int, timeout_us: int = 0) -> bytes:
        """A register read, as pysoem's `_fprd` (FPRD) gives it."""
        out = bytearray(size)
        self._esc.now = self._clock.now() + self._esc.dc.hop
        if not self._esc.present or not self._esc._read(address, size, memoryview(out), 0):
            raise pysoem.WkcError(f"FPRD 0x{address:04X} refused")
        return bytes(out)

    def dc_sync(self, act: bool, sync0_cycle_time: int, sync0_shift_time: int = 0) -> None:
        """SYNC0 on (or off) with this cycle time and shift, ns (SOEM's ecx_dcsync0)."""
        self._changes[0] += 1  # a register write: the line's batch looks at its slaves again
        self._clock.dc_sync(self._esc, act, sync0_cycle_time, sync0_shift_time)

    def _read_state(self) -> None:
        """As SOEM's ecx_readstate leaves it: a slave that is gone reads as state 0."""
        memory = self._esc.memory
        present = self._esc.present
        self.state = _U16.unpack_from(memory, ec.REG_AL_STATUS)[0] if present else 0
        self.al_status = _U16.unpack_from(memory, ec.REG_AL_STATUS_CODE)[0] if present else 0

    def write_state(self) -> None:
        """Request `state` (with the error acknowledge, as SOEM's state requests carry it)."""
        self._write(ec.REG_AL_CONTROL, _U16.pack(self.state | ec.AL_ERROR))

    def set_watchdog(self, name: str, milliseconds: float) -> None:
        """The process data watchdog (`name` 'processdata'), 0: off."""
        if name != "processdata":
            raise ValueError(f"no watchdog {name!r} here")
        self._write(ec.REG_WATCHDOG_DIVIDER, _U16.pack(ec.WATCHDOG_DIVIDER_DEFAULT))
        self._write(ec.REG_WATCHDOG_TIME_PROCESS_DATA,
                    _U16.pack(int(round(milliseconds * 10))))  # 100 us ticks

    def _sync_manager(self, kind: str, length: int) -> tuple[int, int]:
        sm = self._firmware.esi.sync_manager(kind)
        number = self._firmware.esi.sm_number(kind)
        self._write(ec.REG_SM0 + number * ec.SM_SIZE,
                    ec.SYNC_MANAGER.pack(sm.start, length, sm.control, 0,
                                         ec.SM_ACTIVATE_ENABLE if length else 0, 0))
        return sm.start, length

    # --- CoE (the slave's object layer: SDO semantics and abort codes) -----------------------

    def _coe(self, index: int, subindex: int, access: Callable):
        if self._esc.al_status & ec.AL_STATE_MASK == ec.AlState.INIT:
            raise pysoem.MailboxError(self.position + 1, 0, "mailbox not running in INIT")
        self._changes[0] += 1
        try:
            return access()
        except SdoAbort as exc:
            raise pysoem.SdoError(self.position + 1, index, subindex, exc.code,
                                  f"SDO abort 0x{exc.code:08X}") from None

    def sdo_read(self, index: int, subindex: int) -> bytes:
        return self._coe(index, subindex,
                         lambda: bytes(self._firmware.objects.upload(index, subindex)))

    def sdo_write(self, index: int, subindex: int, data: bytes) -> None:
        self._coe(index, subindex,
                  lambda: self._firmware.objects.download(index, subindex, bytes(data)))

    def add_emergency_callback(self, callback: Callable) -> None:
        """CoE emergencies of the drive, as pysoem hands them over (error_code, error_reg);
        delivered when the drive raises them (no mailbox in between)."""
        self._firmware.device.add_emergency_handler(
            lambda code, register: callback(_Emergency(code, register)))

    def mbx_receive(self) -> int:
        return 0  # emergencies arrive through the callback as they happen

    # --- process data -------------------------------------------------------------------------

    def _map(self) -> int:
        """SM2/SM3 sized for the PDOs assigned by CoE (SOEM's config_map); bytes mapped."""
        objects = self._firmware.objects
        layouts = tuple(PdoLayout(0, tuple(
            mappable_object(self._firmware.device.dictionary, e)
            for e in objects.assigned_entries(assign)))
            for assign in (ec.RXPDO_ASSIGN, ec.TXPDO_ASSIGN))
        self.layouts = layouts
        sizes = [layout.size for layout in layouts]
        self._outputs = self._sync_manager("Outputs", sizes[0])
        self._inputs = self._sync_manager("Inputs", sizes[1])
        self.output = bytes(sizes[0])
        self._input_buffer = bytearray(sizes[1])
        self.input = bytes(sizes[1])
        return sizes[0] + sizes[1]

    def _exchange(self) -> int:
        """Write the outputs (a completed SM2 buffer runs the drive's cycle), read the inputs;
        this slave's share of the working counter."""
        if not self._esc.present:
            return 0  # powered off: the frame passes it untouched
        count = 0
        if self._outputs is not None and self._outputs[1]:
            if self._write(self._outputs[0], self.output):
                count += 2
        if self._inputs is not None and self._inputs[1]:
            start, length = self._inputs
            if self._esc._read(start, length, memoryview(self._input_buffer), 0):
                self.input = bytes(self._input_buffer)
                count += 1
        return count


class _Emergency:
    __slots__ = ("error_code", "error_reg")

    def __init__(self, code: int, register: int):
        self.error_code, self.error_reg = code, register


class LinkedMaster:
    """`pysoem.Master`'s calls, served by `segment` in this process (`open` takes no
    interface: the segment is the line)."""

    def __init__(self, segment: Segment, clock: LineClock):
        self._segment = segment
        # the line's time for its distributed clocks (on drive time its frames x the SYNC0
        # cycle)
        self._clock = LinkedClock(segment.escs, clock)
        self.dc_time = 0  # ns, the reference clock's time the last frame read
        self.slaves: list[LinkedSlave] = []
        self.state = 0
        self.expected_wkc = 0
        # s each process data exchange spent in the slaves (their firmware and physics), in
        # order: what a benchmark of the master takes out of its figures
        self.slave_seconds: list[float] = []
        self._image: LinkedImage | None = None  # the batch, once mapped with one layout
        self._changes = [0]  # register writes and CoE accesses: the slaves may have changed

    def open(self, interface: str) -> None:
        """Nothing to open: the line is in this process."""

    def close(self) -> None:
        self.slaves = []
        self._image = None

    def config_init(self) -> int:
        """INIT (errors acknowledged), station addresses, the mailbox sync managers as the
        SII gives them, PRE-OP requested: SOEM's config_init. The number of slaves."""
        segment = self._segment
        with segment.lock:
            self.slaves = [LinkedSlave(k, esc, firmware, self._changes, self._clock)
                           for k, (esc, firmware)
                           in enumerate(zip(segment.escs, segment.firmwares, strict=True))]
            for slave in self.slaves:
                slave.state = ec.AlState.INIT
                slave.write_state()
                slave._write(ec.REG_STATION_ADDRESS, _U16.pack(FIRST_STATION_ADDRESS
                                                               + slave.position))
                for kind in ("MBoxOut", "MBoxIn"):
                    slave._sync_manager(kind, slave._firmware.esi.sync_manager(
                        kind).default_size)
                slave.state = ec.AlState.PRE_OP
                slave.write_state()
                slave._read_state()
        return len(self.slaves)

    def config_map(self) -> int:
        """The process data sync managers from each slave's PDO assignment, then SAFE-OP
        requested (as SOEM's config_map does). The image's size in bytes."""
        with self._segment.lock:
            size = sum(slave._map() for slave in self.slaves)
            self.expected_wkc = WORKING_COUNTER_PER_SLAVE * len(self.slaves)
            self._image = LinkedImage.of(self.slaves, self._segment, self._changes)
            for slave in self.slaves:
                slave.state = ec.AlState.SAFE_OP
                slave.write_state()
        return size

    def config_dc(self) -> bool:
        """Propagation delays and offsets of every slave with DC (SOEM's config_dc); True
        when there is one."""
        with self._segment.lock:
            return self._clock.config_dc()

    def write_state(self) -> None:
        with self._segment.lock:
            for slave in self.slaves:
                slave.state = self.state
                slave.write_state()

    def read_state(self) -> int:
        """Every slave's AL status and code; the lowest state."""
        with self._segment.lock:
            for slave in self.slaves:
                slave._read_state()
        return min((slave.state & ec.AL_STATE_MASK for slave in self.slaves), default=0)

    def state_check(self, expected: int, timeout_us: int = 0) -> int:
        """The slaves answer a request at once here: `expected` when every slave is in it,
        else the lowest state."""
        lowest = self.read_state()
        return expected if all(slave.state == expected for slave in self.slaves) else lowest

    def send_processdata(self) -> None:
        """One cycle of the image: every slave's outputs in (its drive cycles), its inputs
        out; the working counter is kept for `receive_processdata`."""
        start = time.perf_counter()
        with self._segment.lock:
            dc_time = self._clock.before_frame()
            if dc_time is not None:
                self.dc_time = dc_time
            image = self._image
            self._wkc = (image.exchange() if image is not None
                         else sum(slave._exchange() for slave in self.slaves))
            if self._segment.frame_lost():
                # SOEM's answer for a frame that did not come back; what the slaves wrote
                # stands in `input`, which a master reads only for a frame that came back
                self._wkc = NO_FRAME
            self._segment.frames += 1
            self._clock.after_frame()
            self._segment.drives.renew_draws()  # a few a cycle, not all in one
        self.slave_seconds.append(time.perf_counter() - start)

    def receive_processdata(self, timeout_us: int = 0) -> int:
        return self._wkc


class LinkedImage:
    """The line's process data cycle as a batch over its slaves, for a line whose slaves all
    map the same layout: the controlword and targets out, inputs among the drive's live
    objects (`sim_bus.device.LINE_KEYS`). Built by `of`, which says None for any other."""

    def __init__(self, slaves: list[LinkedSlave], segment: Segment, changes: list[int]):
        self.slaves = slaves
        self.line = segment.drives
        # which slaves' cycles are steady for the ESC and the firmware, as of `_seen`
        # changes on the line: kept while the line only exchanges process data in steady
        # cycles (nothing else changes a slave's state or sync managers)
        self._changes, self._seen = changes, -1
        self._steady = np.zeros(len(slaves), dtype=bool)
        outputs, inputs = slaves[0].layouts
        self.keys = (tuple((o.index, o.subindex) for o in outputs.objects),
                     tuple((o.index, o.subindex) for o in inputs.objects))
        self._out_dtype = outputs.dtype
        self._out_size, self._in_size = outputs.size, inputs.size
        self._inputs = InputEncoder(inputs, len(slaves))
        self._rows = np.arange(len(slaves))
        # per slave: its sync managers as last checked, whether their buffers are plain
        # (enabled for the PDI, exactly the mapped areas, nothing else over them) and
        # whether the output buffer retriggers the watchdog
        self._checked: list = [None] * len(slaves)
        self._plain = [False] * len(slaves)
        self._watchdog = [False] * len(slaves)
        # per slave, where a batched cycle writes: the ESC's memory (a view), the SM2 and
        # SM3 buffers' starts; the ESCs whose watchdog the outputs retrigger
        self._memories = List([np.frombuffer(slave._esc.memory, np.uint8) for slave in slaves])
        self._starts = np.zeros((len(slaves), 2), dtype=np.int64)
        self._watchdogs: list[int] = []
        self._firmwares = [slave._firmware for slave in slaves]
        self._escs = [slave._esc for slave in slaves]

    @classmethod
    def of(cls, slaves: list[LinkedSlave], segment: Segment,
           changes: list[int]) -> "LinkedImage | None":
        if not slaves or len(segment.drives) != len(slaves):
            return None
        layouts = {(slave.layouts[0].objects, slave.layouts[1].objects) for slave in slaves}
        if len(layouts) != 1:
            return None
        outputs, inputs = layouts.pop()
        if not batchable_keys([(o.index, o.subindex) for o in outputs],
                              [(o.index, o.subindex) for o in inputs]):
            return None
        return cls(slaves, segment, changes)

    def _check(self, k: int) -> bool:
        """Whether slave k's SM2/SM3 take the whole buffers as the ESC's rules would (the
        sync managers change only with a register write: checked again after one)."""
        slave = self.slaves[k]
        esc = slave._esc
        self._checked[k] = sms = esc._sms
        plain, watchdog = True, False
        for (start, length), writes in ((slave._outputs, True), (slave._inputs, False)):
            over = [sm for sm in sms if sm[1] < start + length and start < sm[2]]
            if (len(over) != 1 or over[0][0] < 0 or over[0][1:3] != (start, start + length)
                    or over[0][3] or over[0][4] != writes):
                plain = False
            elif writes:
                watchdog = over[0][5]
        self._plain[k], self._watchdog[k] = plain, watchdog
        return plain

    def exchange(self) -> int:
        """One frame's process data for every slave; the working counter."""
        slaves, line = self.slaves, self.line
        if line.refresh() or self._changes[0] != self._seen:
            keys, checked, plain = self.keys, self._checked, self._plain
            self._steady[:] = [
                slave._firmware.steady_keys() == keys
                and (plain[k] if checked[k] is slave._esc._sms else self._check(k))
                for k, slave in enumerate(slaves)]
            self._starts[:] = [(slave._outputs[0], slave._inputs[0]) for slave in slaves]
            self._watchdogs = [k for k, slave in enumerate(slaves)
                               if self._watchdog[k] and slave._esc._watchdog_period]
            self._seen = self._changes[0]
        steady = self._steady
        if not all(map(_PRESENT, self._escs)):  # a slave powered off: not in the batch
            steady = steady & np.fromiter(map(_PRESENT, self._escs), dtype=bool,
                                          count=len(slaves))
        data = b"".join([slave.output for slave in slaves])
        if len(data) != self._out_size * len(slaves):  # not the mapped image: slave by slave
            return sum(slave._exchange() for slave in slaves)
        outputs = np.frombuffer(data, self._out_dtype)
        rows = self._rows[steady]
        out_keys = self.keys[0]
        done = line.cycle(rows, outputs["f0"].astype(np.int64), out_keys,
                          [outputs[f"f{k}"].astype(np.int64) for k in range(1, len(out_keys))],
                          refresh=False)
        batched = rows[done]
        every = len(batched) == len(slaves)
        inputs = self._inputs
        inputs.encode(line.values, None if every else batched)
        image = inputs.image.tobytes()
        into_buffers(batched, self._memories, self._starts,
                     np.frombuffer(data, np.uint8).reshape(len(slaves), self._out_size),
                     inputs.bytes)
        if self._watchdogs:
            ran = set(batched.tolist())
            for k in self._watchdogs:
                if k in ran:
                    slaves[k]._esc._trigger_watchdog()
        in_size, firmwares = self._in_size, self._firmwares
        for k in batched.tolist():
            slaves[k].input = image[k * in_size:(k + 1) * in_size]
            firmwares[k].cycles += 1
        count = WORKING_COUNTER_PER_SLAVE * len(batched)
        if not every:  # slave by slave, which may change them: look again
            left = np.ones(len(slaves), dtype=bool)
            left[batched] = False
            count += sum(slaves[k]._exchange() for k in np.flatnonzero(left).tolist())
            self._seen = -1
        return count

