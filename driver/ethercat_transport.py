"""The EtherCAT transport (pysoem): `driver.transport.Transport` for the CiA 402 drive in one
slave of an EtherCAT line (`driver.ethercat_master`).

Acyclic access is CoE SDO through the slave's mailbox; cyclic data is the slave's part of the
line's process image: RxPDO 0x1600 assigned to SM2 (0x1C12), TxPDO 0x1A00 to SM3 (0x1C13),
written by CoE in PRE-OP from the objects the CiA 402 layer asks for (over EtherCAT: those the
ESI's PDOs carry, i.e. cyclic synchronous torque). CoE emergencies are fetched from the
mailbox when the statusword shows a fault, and handed to `on_emergency` before the sample
that shows it.
"""

import logging
import struct
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import pysoem

from driver.clock import DriveClock, WallClock
from driver.ethercat_master import EthercatMaster, LineSilent
from driver.interface import DriveError, DriveLost, ProfileError, SdoRefused
from driver.transport import Transport
from protocol import cia301, cia402, objects
from protocol import eds_path as shipped_eds_path
from protocol import esi_path as shipped_esi_path
from protocol import ethercat as ec
from protocol.cia402 import State
from protocol.dictionary import has, load_dictionary, variable
from protocol.esi import EsiDevice, ethercat_dictionary, load_esi
from protocol.pdo import MappedObject, PdoLayout

log = logging.getLogger(__name__)

STATUSWORD_FAULT = 0x0008  # CiA 402 statusword bit 3
EMERGENCY_POLLS = 8  # cycles to look for the emergency behind a fault bit before giving up
MAILBOX_ATTEMPTS = 3
_U8 = struct.Struct("<B")
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")


class EthercatTransport(Transport):
    """Slave `position` (0-based, in line order) of `line`; its dictionary is the drive's EDS
    seen through the line's ESI (`protocol.esi.ethercat_dictionary`)."""

    def __init__(self, line: EthercatMaster, position: int, *,
                 eds: str | Path | None = None):
        if position < 0:
            raise ValueError(f"slave position {position}: positions count from 0")
        self.line = line
        self.position = position
        self.name = line.label(position)  # 'slave 3 (arm_left_4_joint)' in every report
        self.dictionary = ethercat_dictionary(
            load_dictionary(eds if eds is not None else shipped_eds_path()), line.esi)
        self._outputs: tuple[MappedObject, ...] = ()
        self._inputs: tuple[MappedObject, ...] = ()
        self._out_codec: PdoLayout | None = None
        self._in_codec: PdoLayout | None = None
        self._staged: list[int] = []
        self._seen = 0  # the line's frame whose inputs this transport returned last
        self._statusword_at: int | None = None  # input position of 0x6041
        self._emergency_polls = 0
        self._mapped = False
        self._closed = False
        self._listening = None  # the pysoem slave our emergency callback is on
        line.claim(position, lambda: self._mapped, self._take_image)

    @property
    def slave(self):
        return self.line.slave(self.position)

    # --- acyclic -----------------------------------------------------------------------------

    def boot(self, timeout: float) -> None:
        """The line from INIT to PRE-OP (once for all its slaves; again after a failure).
        There is no other master to find: a line has one master port."""
        if self.line.master is None or self.line.failure is not None:
            self.line.scan(timeout)
        slave = self.slave
        if slave is not self._listening:  # a new scan made new slave objects
            slave.add_emergency_callback(self._on_emergency)
            self._listening = slave
        self._disable_what_was_left()

    def _disable_what_was_left(self) -> None:
        """A drive an earlier master left powered (killed in lock-step, where no watchdog
        watched it, or mid-way through its own start) is switched off before anything is
        configured: a master never inherits an enabled drive or its last target."""
        state = cia402.state_from_statusword(self.read(objects.STATUSWORD))
        if state in (State.SWITCH_ON_DISABLED, State.NOT_READY_TO_SWITCH_ON, State.FAULT):
            return
        log.warning("%s: drive found in '%s', left by an earlier master: disabling it",
                    self.name, state.value)
        self.write(objects.CONTROLWORD, 0, cia402.Command.DISABLE_VOLTAGE.value)

    def _through_image(self) -> bool:
        """From OP on, while the line answers: objects the process data carries are read and
        written through it (`EthercatMaster.pass_image`), not by CoE, as a cyclic master
        steers CiA 402. A drive may refuse an SDO write to an object its RxPDO maps (the
        process data owns it from SAFE-OP on: SOEM's maintainers say so of drives in the
        field, and `sim_bus.ethercat.objects` refuses it), and where it accepts one the next
        frame's value overwrites it. A CoE access is also three frames or more and holds the
        line for its round trip: on distributed clocks the enable sequence's dozens of them
        (32 drives) left SYNC0 windows without outputs until the slaves dropped out with
        0x001A, and in free run they were most of the configuration's burst of frames.
        After the line failed, reads go by CoE and writes by a last frame
        (`EthercatMaster.last_frame`)."""
        line = self.line
        return line.operational and self._mapped

    def read(self, index: int, subindex: int = 0) -> int:
        var = self._variable(index, subindex)
        at = _position(self._inputs, index, subindex)
        if at is not None and self._through_image() and self.line.failure is None:
            self.line.pass_image()  # inputs the slave made after the last write
            return self._input_at(at)
        try:
            data = self._mailbox(self.slave.sdo_read, index, subindex)
        except pysoem.SdoError as exc:
            raise SdoRefused(f"{self.name}: CoE read 0x{index:04X}:{subindex:02X} aborted: "
                             f"{cia301.sdo_abort_name(exc.abort_code)}",
                             exc.abort_code) from None
        return var.decode_raw(data)

    def write(self, index: int, subindex: int, value: int) -> None:
        var = self._variable(index, subindex)
        # an object the outputs carry is staged first: a frame that goes while the CoE write
        # waits for its answer (the line's keeper) must not take the old value back to it
        carried = self.stage_output(index, subindex, value)
        if carried and self._through_image():
            # a frame takes it to the slave; after the line failed, a last one to the slaves
            # still in OP (a quick stop, the disable on close), else CoE as the last resort
            if self.line.failure is None:
                self.line.pass_image()
                return
            if self.line.last_frame():
                return
        try:
            self._mailbox(self.slave.sdo_write, index, subindex, var.encode_raw(value))
        except pysoem.SdoError as exc:
            raise SdoRefused(f"{self.name}: CoE write 0x{index:04X}:{subindex:02X} = {value} "
                             f"aborted: {cia301.sdo_abort_name(exc.abort_code)}",
                             exc.abort_code) from None

    # --- through the process data (the line's frames carry it) --------------------------------

    def steers_through_image(self) -> bool:
        """Whether the line's frames carry this drive's controlword and statusword now (OP,
        the line answering): its segment can walk CiA 402 with the others'
        (`driver.drive_group.EthercatLine.enable`)."""
        return (self._through_image() and self.line.failure is None
                and self._statusword_at is not None
                and _position(self._outputs, objects.CONTROLWORD, 0) is not None)

    def image_state(self) -> State:
        """The drive's CiA 402 state as the last frame's statusword shows it."""
        return cia402.state_from_statusword(self._input_at(self._statusword_at))

    def _input_at(self, k: int) -> int:
        """Input `k` as the last frame brought it (no frame sent)."""
        with self.line.lock:
            return self._in_codec.struct.unpack(self.slave.input)[k]

    def stage_output(self, index: int, subindex: int, value: int) -> bool:
        """Put `value` in this slave's outputs for the next frame, when they carry the
        object; whether they do."""
        k = _position(self._outputs, index, subindex)
        if k is None:
            return False
        if self.line.mapped and self._mapped:
            # what the image carries now (the line may have written it as a whole,
            # `driver.drive_group.EthercatLine`), with this object changed
            with self.line.lock:
                self._staged[:] = self._out_codec.struct.unpack(self.slave.output)
        self._staged[k] = value  # the next frame carries it
        self._stage()
        return True

    def _mailbox(self, access, index: int, subindex: int, *data: bytes):
        """One CoE SDO access, tried again when the mailbox exchange itself got no answer (a
        register access SOEM gave up on after its few ms): an SDO abort is the drive's
        answer and is not retried. On a line where nothing answers any more (`LineSilent`)
        it fails at once."""
        if isinstance(self.line.failure, LineSilent):
            raise DriveError(f"{self.name}: CoE access 0x{index:04X}:{subindex:02X} not tried: "
                             "nothing on the line answers") from self.line.failure
        for attempt in range(MAILBOX_ATTEMPTS):
            try:
                with self.line.acyclic():  # its frames waited for asleep
                    self.line.keep_alive()
                    return access(index, subindex, *data)
            except (pysoem.WkcError, pysoem.MailboxError, pysoem.PacketError) as exc:
                if attempt == MAILBOX_ATTEMPTS - 1:
                    raise DriveError(f"{self.name}: CoE access 0x{index:04X}:{subindex:02X} "
                                     f"failed {MAILBOX_ATTEMPTS} times: {exc!r}") from None

    def _variable(self, index: int, subindex: int):
        var = variable(self.dictionary, index, subindex)
        if var is None:
            raise DriveError(f"{self.name}: 0x{index:04X}:{subindex:02X} is not in the "
                             "drive's dictionary")
        return var

    # --- process data ------------------------------------------------------------------------

    def map_process_data(self, outputs: Sequence[MappedObject],
                         inputs: Sequence[MappedObject]) -> None:
        esi = self.line.esi
        for objs, kind, pdos in ((outputs, "output", esi.rxpdos), (inputs, "input", esi.txpdos)):
            missing = [str(o) for o in objs if not _mappable(self.dictionary, o)]
            if missing:
                raise ProfileError(f"{self.name}: the ESI's PDOs cannot carry {kind}s "
                                   f"{', '.join(missing)}")
            if objs and not pdos:
                raise ProfileError(f"{self.name}: the ESI has no {kind} PDO")
        self._write_pdo(ec.RXPDO_ASSIGN, esi.rxpdos[0].index if outputs else 0, outputs)
        self._write_pdo(ec.TXPDO_ASSIGN, esi.txpdos[0].index if inputs else 0, inputs)
        self._outputs, self._inputs = tuple(outputs), tuple(inputs)
        self._out_codec = PdoLayout(0, self._outputs)
        self._in_codec = PdoLayout(0, self._inputs)
        self._staged = [0] * len(self._outputs)
        self._statusword_at = next((k for k, o in enumerate(self._inputs)
                                    if o.index == objects.STATUSWORD), None)
        self._mapped = True

    def _write_pdo(self, assign: int, pdo: int, mapped: Sequence[MappedObject]) -> None:
        """Assignment off, mapping rewritten, assignment back on (ETG.1000.6 order), then
        read back: a slave that kept something else is refused."""
        self._sdo_write(assign, 0, _U8.pack(0))
        if not pdo:
            return
        self._sdo_write(pdo, 0, _U8.pack(0))
        for k, obj in enumerate(mapped, start=1):
            self._sdo_write(pdo, k, _U32.pack(obj.mapping_entry))
        self._sdo_write(pdo, 0, _U8.pack(len(mapped)))
        self._sdo_write(assign, 1, _U16.pack(pdo))
        self._sdo_write(assign, 0, _U8.pack(1))
        entries = [self.read(pdo, k) for k in range(1, self.read(pdo, 0) + 1)]
        (assigned,) = _U16.unpack(self._mailbox(self.slave.sdo_read, assign, 1))
        if entries != [o.mapping_entry for o in mapped] or assigned != pdo:
            raise ProfileError(f"{self.name}: PDO 0x{pdo:04X} reads back as "
                               f"{[f'0x{e:08X}' for e in entries]} after the mapping was "
                               "written")

    def _sdo_write(self, index: int, subindex: int, data: bytes) -> None:
        try:
            self._mailbox(self.slave.sdo_write, index, subindex, data)
        except pysoem.SdoError as exc:
            raise ProfileError(f"{self.name}: PDO configuration 0x{index:04X}:{subindex:02X} "
                               f"refused: {cia301.sdo_abort_name(exc.abort_code)}") from None

    def start(self, period: float) -> None:
        """The drive's cycle period (0x1006, the physics step of an SM-synchronous drive),
        then the line to OP once every slave in use has its process data mapped (the last
        transport to start takes the line there; the first exchange at the latest)."""
        if has(self.dictionary, objects.CYCLE_PERIOD_US):
            self.write(objects.CYCLE_PERIOD_US, 0, int(round(period * 1e6)))
        self.line.period = period  # DC: the SYNC0 cycle
        if self.line.all_ready():
            self.line.go_operational()

    def send(self, outputs: Sequence[int]) -> None:
        self._staged[:] = outputs
        self._stage()

    def _take_image(self) -> None:
        """The line's process image exists (SOEM's config_map): this slave's part of it
        checked against the PDOs this transport mapped, then its outputs staged. SOEM sizes
        the image from SDO reads of its own, which a lost or late mailbox answer corrupts
        (talos_32 beside two busy loops: 1 start in 5 got 2 output bytes for 4): a clear
        refusal, not a process image the cycle cannot decode."""
        slave = self.slave
        sizes = (len(slave.output), len(slave.input))
        if sizes != (self._out_codec.size, self._in_codec.size):
            self._mapped = False  # the image does not hold what was mapped: nothing staged
            raise DriveError(f"{self.name}: SOEM mapped {sizes[0]} output and {sizes[1]} "
                             f"input bytes where the PDOs written carry "
                             f"{self._out_codec.size} and {self._in_codec.size} (its reads of "
                             "the PDO assignment got a lost or late mailbox answer): start "
                             "again")
        self._stage()

    def _stage(self) -> None:
        if self.line.mapped and self._mapped:
            with self.line.lock:
                self.slave.output = self._out_codec.struct.pack(*self._staged)

    def exchange(self) -> tuple[int, ...]:
        line = self.line
        if not line.operational:
            if not line.all_ready():
                raise DriveError(f"{self.name}: the line is not operational: a slave in use "
                                 "has no process data mapped yet")
            line.go_operational()
        if self._seen == line.frames:
            try:
                line.cycle()  # this cycle's frame, for every slave on the line
            finally:
                self._seen = line.frames  # lost or not, the next exchange sends the next
        elif line.failure is not None:
            raise line.failure
        else:
            self._seen = line.frames
            if line.last_loss is not None and line.last_loss_at == line.frames:
                raise line.last_loss  # this cycle's frame, sent for another joint, was lost
        values = self._in_codec.struct.unpack(self.slave.input)
        at = self._statusword_at
        if at is not None and values[at] & STATUSWORD_FAULT:
            if self._emergency_polls < EMERGENCY_POLLS:
                self._emergency_polls += 1
                self._poll_mailbox()
        else:
            self._emergency_polls = 0
        return values

    def _poll_mailbox(self) -> None:
        try:
            self.slave.mbx_receive()
        except (pysoem.WkcError, pysoem.MailboxError, pysoem.PacketError) as exc:
            self.line.failure = self.line.failure or DriveLost(
                f"{self.name}: mailbox unreadable: {exc!r}")

    def _on_emergency(self, emergency) -> None:
        self._emergency_polls = EMERGENCY_POLLS  # found it
        self.on_emergency(emergency.error_code, emergency.error_reg)

    @property
    def failure(self) -> DriveError | None:
        return self.line.failure

    def stop(self) -> None:
        try:
            self.line.release(self.position)
        except (pysoem.WkcError, OSError):
            pass

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.line.unclaim(self.position)


def _position(mapped: Sequence[MappedObject], index: int, subindex: int) -> int | None:
    """Where the object sits among a PDO's `mapped` objects (None: not there)."""
    return next((k for k, obj in enumerate(mapped)
                 if (obj.index, obj.subindex) == (index, subindex)), None)


def _mappable(dictionary, obj: MappedObject) -> bool:
    var = variable(dictionary, obj.index, obj.subindex)
    return var is not None and var.pdo_mappable


def open_ethercat_transports(interface: str, positions: Sequence[int], *,
                             clock: WallClock | DriveClock | None = None,
                             esi: str | Path | EsiDevice | None = None,
                             eds: str | Path | Sequence[str | Path | None] | None = None,
                             response_timeout: float | None = None,
                             watchdog: float | None = None,
                             open_master: Callable[[], Any] = pysoem.Master,
                             names: Sequence[str | None] | None = None,
                             sync: str = "free_run") -> list[EthercatTransport]:
    """One transport per slave position on the line at `interface`, sharing its master (one
    frame per cycle for all of them). `esi` defaults to the shipped elbow drive ESI; `eds` is
    every slave's EDS, or a list with one per position (drives of different joints differ);
    `names` the joint of each position, named with its slave in every report.
    `clock`, `open_master`, `sync`: see `driver.ethercat_master.EthercatMaster`."""
    if not isinstance(esi, EsiDevice):
        esi = load_esi(esi if esi is not None else shipped_esi_path())
    if eds is None or isinstance(eds, str | Path):
        eds = [eds] * len(positions)
    line = EthercatMaster(interface, esi, clock=clock, response_timeout=response_timeout,
                          watchdog=watchdog, open_master=open_master, sync=sync)
    for position, name in zip(positions, names or (), strict=False):
        if name:
            line.names[position] = name
    return [EthercatTransport(line, position, eds=path)
            for position, path in zip(positions, eds, strict=True)]
