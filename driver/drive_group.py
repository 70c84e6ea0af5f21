"""Every joint of a robot in one cycle: one SYNC per CAN bus (one frame per EtherCAT segment),
every joint sampled in that cycle, every command sent before the next.

A `DriveGroup` owns the segments (a CAN bus, an EtherCAT line) and, through them, the joints'
`Cia402Drive`s. A cycle first triggers every segment (so the buses run side by side), then
collects every segment's samples as one array; commands go out segment by segment, each in
one pass over its joints, right after the controller has decided, which is before the next
cycle's trigger. A failure on one joint is raised as a
`JointFailure` naming it; the caller then stops every joint (`quick_stop_all`), because the
others were planned on the assumption that the whole arm moves together.
"""

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from operator import methodcaller
from typing import TypeVar

import can
import canopen
import numpy as np

from driver import process_image
from driver.cia402_drive import ENABLE_STEP_TIMEOUT, Cia402Drive
from driver.ethercat_dc import DcLine
from driver.ethercat_transport import EthercatTransport
from driver.interface import (
    SAMPLE_JOINT_TORQUE,
    SAMPLE_POSITION,
    SAMPLE_STATUSWORD,
    SAMPLE_VELOCITY,
    CommandRangeError,
    DriveError,
    DriveFault,
    DriveTimeout,
    EncoderGlitch,
    Sample,
    SampleLost,
)
from driver.process_image import FAULT_BITS, FAULT_MASK, decode, encode
from protocol import cia402, objects
from protocol.cia402 import State

SAMPLE_COLUMNS = Sample._fields
T = TypeVar("T")

log = logging.getLogger(__name__)

# walks of the state machine at most (`steer_together`): a fault reset and the three steps
# to operation enabled, with room for a drive that falls back once (as `Cia402Drive`'s own)
STEER_STEPS = 8


@dataclass(frozen=True)
class BringUp:
    """How long a group's start took (s on the host's performance counter): every drive
    configured (boot, start-up parameters, scaling, PDO mapping, the line to OP), then every
    drive enabled; the cold solve in between is the controller's (`LoopReport.cold_solve_us`).
    While the first drives are enabled and the last are not, the enabled ones hold no torque."""

    configure: float
    enable: float


class JointFailure(DriveError):
    """A joint's drive failed (or refused its command); `joint` names it, `cause` is the
    drive's own error."""

    def __init__(self, joint: str, cause: Exception):
        super().__init__(f"joint {joint}: {cause}")
        self.joint = joint
        self.cause = cause


class Segment:
    """Drives whose process data travels together. This base covers drives whose transports
    already share one frame a cycle, each `sync()`ed in turn (EtherCAT: the line sends the
    frame at the first `sync` of a cycle and the others read it), as a line whose slaves do
    not share one layout runs, and an EtherCAT joint alone (`single_joint`)."""

    def __init__(self, name: str, joints: Sequence[tuple[str, Cia402Drive]]):
        self.name = name
        self.joints = list(joints)

    def failed(self, joint: str, exc: DriveError) -> JointFailure:
        """`exc`, met while working on `joint`, as the failure of the joint it concerns."""
        return JointFailure(joint, exc)

    def enable(self) -> None:
        """Every drive's own CiA 402 walk to operation enabled, in joint order."""
        for joint, drive in self.joints:
            try:
                drive.enable()
            except DriveError as exc:
                raise self.failed(joint, exc) from exc

    def started(self) -> None:
        """Every drive of the group is up; cycles begin."""

    def trigger(self) -> None:
        """Start this segment's cycle (nothing to do where the first `sync` sends the frame)."""

    def collect(self) -> np.ndarray:
        """This cycle's samples, a row per joint (`driver.interface.SAMPLE_*` columns)."""
        samples = []
        for joint, drive in self.joints:
            try:
                samples.append(drive.sync())
            except SampleLost:
                raise  # the segment's, not the joint's: no joint failed
            except DriveError as exc:
                raise JointFailure(joint, exc) from exc
        return np.array(samples, dtype=float)

    def command(self, currents: np.ndarray) -> None:
        """One motor current (A) per joint of the segment, applied from the next cycle."""
        for (joint, drive), current in zip(self.joints, currents, strict=True):
            try:
                drive.command_current(float(current))
            except (CommandRangeError, DriveError) as exc:
                raise JointFailure(joint, exc) from exc

    def warnings(self) -> list[str]:
        """What the segment's drives reported since the last call, each naming its joint."""
        return [f"joint {joint}: {warning}" for joint, drive in self.joints
                for warning in drive.warnings()]

    def clock(self) -> DcLine | None:
        """The segment's distributed clocks, when it runs on them (an EtherCAT line in DC
        mode): what the cycle's clock follows."""
        return None

    def close(self) -> None:
        """Release what the segment owns beyond its drives (nothing here)."""


class CanOpenBus(Segment):
    """The CANopen drives of one bus, cycled as the bus's process image: one SYNC a cycle for
    all of them (`driver.canopen_cycle.BusCycle`, the bus's since its first drive joined it),
    every TPDO's bytes copied into its drive's row of the input image as it arrives, then
    every joint decoded, scaled to SI, guarded and checked for faults in one compiled call,
    and every RPDO encoded in another (`driver.process_image`). The per-joint `Cia402Drive`s
    keep bring-up, acyclic access, the state machine, emergencies and their own words for a
    failure, which names its joint. With `owns_network` the bus disconnects the network on
    close (a robot's bus; a drive alone on its bus leaves that to its transport)."""

    def __init__(self, name: str, network: canopen.Network,
                 joints: Sequence[tuple[str, Cia402Drive]], *, owns_network: bool = True):
        super().__init__(name, joints)
        self.network = network
        self.owns_network = owns_network
        self._layout: np.ndarray | None = None  # made when the drives are up

    def started(self) -> None:
        drives = [drive for _, drive in self.joints]
        transports = [drive.transport for drive in drives]
        self._bus = bus = transports[0].bus_cycle
        rows = [transport.row for transport in transports]
        self._joint_of_row = dict(zip(rows, self.joints, strict=True))
        scaling = [drive.scaling for drive in drives]
        self._scale = np.array([[s.rad_per_increment, s.amps_per_feedback_unit,
                                 s.joint_torque_per_unit, drive.guard.max_position_step]
                                for s, drive in zip(scaling, drives, strict=True)])
        self._current_limit = np.array([drive.current_limit for drive in drives])
        self._target_per_amp = np.array([s.target_units_per_amp for s in scaling])
        self._out_layout, self._frames, size = bus.output_layout(rows)
        self._out = np.zeros(size, dtype=np.uint8)
        self._previous = np.full(len(drives), np.nan)
        self._period = drives[0].period
        self._cycle = drives[0].cycle
        self._warnings: list[str] = []
        self._controlword = cia402.Command.ENABLE_OPERATION.value
        self._warning_lists = [lst for drive in drives for lst in drive.warning_lists]
        for drive in drives:
            drive.on_fault = self._alarm
        self._shape = (len(drives), len(SAMPLE_COLUMNS))  # of a cycle's table
        self._layout = bus.input_layout(rows)
        bus.watch.restart_count()  # the other drives' bring-up is not load

    def _alarm(self) -> None:
        """A drive faulted: the bus's next look goes through its drives."""
        self._bus.alarm = True

    def _look_at_drives(self) -> None:
        """Something happened on the bus (an emergency, a drive failed): the first joint whose
        drive stops it is raised."""
        self._bus.alarm = False  # before looking: what comes during the look raises it again
        for joint, drive in self.joints:
            if drive.fault is not None:
                self._bus.alarm = True
                raise JointFailure(joint, drive.fault)

    def _blame(self, exc: DriveError) -> JointFailure:
        """The bus's failure as the failure of the joint whose row it concerns; a drive that
        faulted and then fell silent is named by its fault."""
        joint, drive = self._joint_of_row.get(self._bus.blamed, self.joints[0])
        if isinstance(exc, DriveTimeout) and drive._fault is not None:
            return JointFailure(joint, drive._fault)
        return JointFailure(joint, exc)

    def trigger(self) -> None:
        if self._layout is None:  # started drives given straight to a loop (`single_joint`)
            self.started()
        if self._bus.alarm:
            self._look_at_drives()
        try:
            self._bus.trigger()
        except DriveError as exc:
            raise self._blame(exc) from exc
        except (can.CanError, OSError) as exc:
            raise JointFailure(self.joints[0][0],
                               DriveError(f"cannot send SYNC on {self.name}: {exc}")) from exc

    def collect(self) -> np.ndarray:
        bus = self._bus
        try:
            bus.collect()
        except DriveError as exc:
            raise self._blame(exc) from exc
        self._cycle += 1
        table = np.empty(self._shape)
        glitch, faulted, saturated = decode(bus.image, self._layout, self._scale,
                                            self._cycle * self._period, self._previous, 1,
                                            table)
        if glitch >= 0 or faulted >= 0 or saturated >= 0:
            self._judge(table, glitch, faulted, saturated)
        return table

    def _judge(self, table: np.ndarray, glitch: int, faulted: int, saturated: int) -> None:
        """The rare outcomes of a cycle's decoding, in the drives' own words: an encoder
        glitch fails its joint now; a drive in fault is raised at the next command (its
        emergency names it); a saturated torque reading is a warning."""
        if saturated >= 0:
            for j in np.flatnonzero(np.isnan(table[:, SAMPLE_JOINT_TORQUE])):
                joint, drive = self.joints[j]
                if drive.profile.has_joint_torque:
                    reading = self._bus.inputs(drive.transport.row)[4]
                    self._warnings.append(f"joint {joint}: joint torque sensor reading "
                                          f"saturated ({reading} mN.m)")
        if faulted >= 0:
            statuswords = table[:, SAMPLE_STATUSWORD].astype(np.int64)
            for j in np.flatnonzero((statuswords & FAULT_MASK) == FAULT_BITS):
                self.joints[j][1].judge_statusword(int(statuswords[j]))
            self._bus.alarm = True
        if glitch >= 0:
            joint, drive = self.joints[glitch]
            try:  # its own words for it
                drive.guard.check_step(float(self._previous[glitch]),
                                       float(table[glitch, SAMPLE_POSITION]), drive.name)
            except EncoderGlitch as error:
                drive.fail(error)
                raise JointFailure(joint, error) from error

    def command(self, currents: np.ndarray) -> None:
        bad = encode(currents, self._current_limit, self._target_per_amp, self._controlword,
                     self._out_layout, self._out)
        if bad >= 0:
            joint, drive = self.joints[bad]
            try:
                drive.command_current(float(currents[bad]))  # its own words for the refusal
            except (CommandRangeError, DriveError) as exc:
                raise JointFailure(joint, exc) from exc
        if self._bus.alarm:
            self._look_at_drives()
        try:
            self._bus.send_frames(self._out.tobytes(), self._frames)
        except (can.CanError, OSError) as exc:
            raise JointFailure(self.joints[0][0],
                               DriveError(f"cannot send RPDOs on {self.name}: {exc}")) from exc

    def warnings(self) -> list[str]:
        """The bus's own (saturated sensors, found on the arrays), then any a drive kept
        (its transport's: late or doubled frames, an overloaded bus): one look at every
        drive's lists at once, a call per drive only when one has something."""
        out, self._warnings = self._warnings, []
        if any(self._warning_lists):
            for joint, drive in self.joints:
                if drive.has_warnings:
                    out += [f"joint {joint}: {warning}" for warning in drive.warnings()]
        return out

    def close(self) -> None:
        if self.owns_network:
            self.network.disconnect()


class EthercatLine(Segment):
    """The drives of one EtherCAT line, cycled as one process image: one frame a cycle, every
    slave's inputs decoded, scaled, guarded and checked for faults in one compiled call over
    the line's input bytes, and every command encoded in another (`driver.process_image`, as
    a CAN bus's; as some fifteen numpy operations it cost 17 us a cycle for one joint). The
    per-joint `Cia402Drive`s keep bring-up, acyclic access, emergencies and naming the joint
    that failed; a line whose slaves do not share one PDO layout (different drives on one
    line) runs each drive's own path instead."""

    def failed(self, joint: str, exc: DriveError) -> JointFailure:
        """The line's own failure (`driver.ethercat_master.LineFailure`) names the joint of
        the first slave it blames (a slave that refused a state or left OP, one that did not
        answer), not whichever joint's call met it."""
        positions = getattr(exc, "positions", ())
        if positions:
            joint = next((name for name, drive in self.joints
                          if drive.transport.position == positions[0]), joint)
        return JointFailure(joint, exc)

    def enable(self) -> None:
        """Every drive of the line to operation enabled together, through the process data
        (`steer_together`) where the frames carry their controlwords and statuswords; else
        each drive's own walk."""
        transports = [drive.transport for _, drive in self.joints]
        if not all(transport.steers_through_image() for transport in transports):
            super().enable()
            return
        try:
            stuck = steer_together(transports, State.OPERATION_ENABLED)
        except DriveError as exc:  # the line's failure: `failed` names the slave it blames
            raise self.failed(self.joints[0][0], exc) from exc
        if stuck is not None:
            joint, drive = self.joints[stuck]
            raise JointFailure(joint, DriveFault(
                f"{drive.name}: cannot reach 'operation enabled' (stuck in "
                f"'{drive.transport.image_state().value}')"))
        for _, drive in self.joints:
            drive.mark_enabled()

    def started(self) -> None:
        drives = [drive for _, drive in self.joints]
        transports = [drive.transport for drive in drives]
        self._drives, self._transports = drives, transports
        self._line = transports[0].line
        self._line.settle()
        self._slaves = [transport.slave for transport in transports]
        inputs = {transport._in_codec.dtype for transport in transports}
        outputs = {transport._out_codec.dtype for transport in transports}
        self._image = len(inputs) == 1 and len(outputs) == 1 and all(
            drive.profile.inputs == drives[0].profile.inputs for drive in drives)
        if not self._image:
            return
        self._in_dtype, self._out_dtype = inputs.pop(), outputs.pop()
        self._out_size = self._out_dtype.itemsize
        scaling = [drive.scaling for drive in drives]
        self._scale = np.array([[s.rad_per_increment, s.amps_per_feedback_unit,
                                 s.joint_torque_per_unit, drive.guard.max_position_step]
                                for s, drive in zip(scaling, drives, strict=True)])
        self._target_per_amp = np.array([s.target_units_per_amp for s in scaling])
        self._current_limit = np.array([drive.current_limit for drive in drives])
        # the line's images as the bus's are (`driver.process_image`): every slave's inputs
        # (outputs) one after the other, each PDO entry at its offset with its size and sign
        self._in_layout = _image_layout(self._in_dtype, len(drives), process_image.INPUTS)
        self._out_layout = _image_layout(self._out_dtype, len(drives), process_image.OUTPUTS)
        self._out = np.zeros(len(drives) * self._out_size, dtype=np.uint8)
        self._controlword = cia402.Command.ENABLE_OPERATION.value
        self._period = drives[0].period
        self._cycle = drives[0].cycle
        self._previous = np.full(len(drives), np.nan)  # NaN: no step to judge yet
        self._periods_since_sample = 1  # more after cycles whose frame was lost
        self._warnings: list[str] = []
        self._warning_lists = [lst for drive in drives for lst in drive.warning_lists]
        # a drive faulted since the line last looked (or the first cycle): one look a cycle
        # at this flag and the line's failure, not a call per drive, twice a cycle
        self._alarmed = True
        for drive in drives:
            drive.on_fault = self._alarm

    def _alarm(self) -> None:
        """A drive faulted: the line's next look goes through its drives."""
        self._alarmed = True

    def _look_at_drives(self) -> None:
        """The first joint whose drive is stopped (by its fault or the line's failure) is
        raised, a slave that left OP named first."""
        self._alarmed = False  # before looking: what comes during the look raises it again
        for joint, drive in self.joints:
            if drive.fault is not None:
                self._alarmed = True
                self._check_line(joint)
                raise JointFailure(joint, drive.fault)

    def clock(self) -> DcLine | None:
        return self.joints[0][1].transport.line.dc

    def warnings(self) -> list[str]:
        """The line's own (saturated sensors, found on the arrays), then any a drive kept
        (from its bring-up and acyclic path): one attribute look per drive, not a call."""
        if not self._image:
            return super().warnings()
        out, self._warnings = self._warnings, []
        if any(self._warning_lists):
            for joint, drive in self.joints:
                if drive.has_warnings:
                    out += [f"joint {joint}: {warning}" for warning in drive.warnings()]
        return out

    def _check_line(self, joint: str) -> None:
        """A drive reported a fault: a slave that left OP is the cause to name first (its
        drive's fault is the reaction to it, EMCY 0xA000)."""
        try:
            self._line.check_states()
        except DriveError as exc:
            raise self.failed(joint, exc) from exc

    def collect(self) -> np.ndarray:
        if not self._image:
            try:
                return super().collect()
            except JointFailure as failure:
                if isinstance(failure.cause, (DriveFault, EncoderGlitch)):
                    self._check_line(failure.joint)
                raise self.failed(failure.joint, failure.cause) from failure.cause
        if self._alarmed or self._line.failure is not None:
            self._look_at_drives()
        try:
            self._transports[0].exchange()  # this cycle's frame, for every slave on the line
        except SampleLost:
            self._cycle += 1  # its period passed without a sample
            self._periods_since_sample += 1
            raise
        except DriveError as exc:
            raise self.failed(self.joints[0][0], exc) from exc
        with self._line.lock:  # the line's keeper may be sending a frame
            data = b"".join([slave.input for slave in self._slaves])
        self._cycle += 1
        # on distributed clocks the drives move on at SYNC0 while the master is late (or its
        # frames were lost); free-running, a lost frame may have run them (lost on its way
        # back), so each counts as a period
        cycles = (self._periods_since_sample if self._line.dc is None
                  else self._line.dc.elapsed_periods)
        self._periods_since_sample = 1
        table = np.empty((len(self._drives), len(SAMPLE_COLUMNS)))
        glitch, faulted, saturated = decode(np.frombuffer(data, np.uint8), self._in_layout,
                                            self._scale, self._cycle * self._period,
                                            self._previous, cycles, table)
        if glitch >= 0 or faulted >= 0 or saturated >= 0:
            self._judge(data, table, cycles, glitch, faulted, saturated)
        return table

    def _judge(self, data: bytes, table: np.ndarray, cycles: int, glitch: int, faulted: int,
               saturated: int) -> None:
        """The rare outcomes of a cycle's decoding, in the drives' own words: a saturated
        torque reading is a warning; an encoder glitch fails its joint; a drive in fault
        names the emergency behind it (its own path reads it)."""
        raw = np.frombuffer(data, self._in_dtype)
        if saturated >= 0:
            for j in np.flatnonzero(np.isnan(table[:, SAMPLE_JOINT_TORQUE])):
                if self._drives[j].profile.has_joint_torque:
                    self._warnings.append(f"joint {self.joints[j][0]}: joint torque sensor "
                                          f"reading saturated ({int(raw['f4'][j])} mN.m)")
        if glitch >= 0:
            drive = self._drives[glitch]
            # a slave that lost its sync jumps too: its AL status, read now, is the cause to
            # name, not the jump (the periodic state check may be cycles away)
            self._check_line(self.joints[glitch][0])
            try:
                drive.guard.check_step(float(self._previous[glitch]),
                                       float(table[glitch, SAMPLE_POSITION]), drive.name, cycles)
            except EncoderGlitch as error:
                drive.fail(error)
                raise JointFailure(self.joints[glitch][0], error) from error
        if faulted >= 0:
            joint, drive = self.joints[faulted]
            self._check_line(joint)
            try:
                drive.take(lambda: tuple(int(v) for v in raw[faulted]))
            except DriveError as exc:
                raise JointFailure(joint, exc) from exc

    def command(self, currents: np.ndarray) -> None:
        """This cycle's motor currents (A), one per joint of the line, out in the next frame."""
        if not self._image:
            try:
                return super().command(currents)
            except JointFailure as failure:
                if isinstance(failure.cause, DriveFault):
                    self._check_line(failure.joint)
                raise
        bad = encode(currents, self._current_limit, self._target_per_amp, self._controlword,
                     self._out_layout, self._out)
        if bad >= 0:
            joint, drive = self.joints[bad]
            try:
                drive.command_current(float(currents[bad]))  # its own words for the refusal
            except (CommandRangeError, DriveError) as exc:
                raise JointFailure(joint, exc) from exc
        if self._alarmed or self._line.failure is not None:
            self._look_at_drives()
        data, size = self._out.tobytes(), self._out_size
        with self._line.lock:
            for k, slave in enumerate(self._slaves):
                slave.output = data[k * size:(k + 1) * size]


def _image_layout(dtype: np.dtype, slaves: int, entries: int) -> np.ndarray:
    """A `driver.process_image` layout of `slaves` images of `dtype` one after the other (a
    line's input or output image): per slave and entry (f0, f1, ... in PDO order), its offset
    in the line's image and its code (0 where the slave's PDO has fewer entries)."""
    layout = np.zeros((slaves, 2 * entries), dtype=np.int64)
    for k, name in enumerate(dtype.names[:entries]):
        entry, offset = dtype.fields[name][:2]
        layout[:, 2 * k] = np.arange(slaves) * dtype.itemsize + offset
        layout[:, 2 * k + 1] = process_image.code(entry.itemsize, entry.kind == "i")
    return layout


class DriveGroup:
    """The robot's joints, in `names` order, on `segments` (each joint on exactly one)."""

    def __init__(self, names: Sequence[str], segments: Sequence[Segment]):
        self.names = list(names)
        self.segments = list(segments)
        placed = [joint for segment in segments for joint, _ in segment.joints]
        if sorted(placed) != sorted(self.names):
            raise ValueError(f"joints {self.names} placed on the segments as {placed}")
        drives = {joint: drive for segment in segments for joint, drive in segment.joints}
        self.drives = [drives[name] for name in self.names]
        # samples come segment by segment; this puts them back in joint order
        self._order = np.array([placed.index(name) for name in self.names])
        self._in_order = bool((self._order == np.arange(len(self.names))).all())
        # each segment's joints' places in joint order (for their commands)
        self._rows = [np.array([self.names.index(joint) for joint, _ in segment.joints],
                               dtype=np.intp) for segment in segments]
        # one segment with its joints in order (a robot of one, a single line): the samples
        # and commands need no reordering, a cycle no indexing
        self._whole = len(self.segments) == 1 and self._in_order
        self.period = self.drives[0].period
        self.clocks: list[DcLine] = []
        self.bring_up: BringUp | None = None  # once started
        self._closed = False

    def __len__(self) -> int:
        return len(self.names)

    def start(self, configured: Callable[[np.ndarray], None] | None = None) -> None:
        """Configure every drive, in joint order, then enable every one, segment by segment
        (an EtherCAT line's together): a drive that does not fit its joint is refused before
        any is enabled. In between, `configured` is given
        every joint's measured state (a row per joint, `driver.interface.SAMPLE_*` columns,
        position and velocity read acyclically): a controller's cold solve runs there,
        before any drive is enabled, not in the first cycle. A failure names the joint (the
        caller closes the group, which disables those already enabled)."""
        began = time.perf_counter()
        self._each(methodcaller("configure"))
        configured_at = time.perf_counter()
        if configured is not None:
            table = np.zeros((len(self.names), len(SAMPLE_COLUMNS)))
            table[:, [SAMPLE_POSITION, SAMPLE_VELOCITY]] = self._each(
                methodcaller("measured_state"))
            configured(table)
        enabling = time.perf_counter()
        for segment in self.segments:
            segment.enable()
        self.bring_up = BringUp(configured_at - began, time.perf_counter() - enabling)
        for segment in self.segments:
            segment.started()
        # the distributed clocks of the lines that run on them (made as the lines went to OP)
        self.clocks = [clock for segment in self.segments
                       if (clock := segment.clock()) is not None]

    def _each(self, step: Callable[[Cia402Drive], T]) -> list[T]:
        """`step` of every drive in joint order, a failure naming its joint."""
        out = []
        for name, drive in zip(self.names, self.drives, strict=True):
            try:
                out.append(step(drive))
            except DriveError as exc:
                segment = next(s for s in self.segments if any(j == name for j, _ in s.joints))
                raise segment.failed(name, exc) from exc
        return out

    def sync(self) -> np.ndarray:
        """One cycle: trigger every segment, then every joint's sample, a row per joint in
        joint order (`driver.interface.SAMPLE_*` columns)."""
        if self._whole:
            segment = self.segments[0]
            segment.trigger()
            return segment.collect()
        for segment in self.segments:
            segment.trigger()
        tables, lost = [], None
        for segment in self.segments:  # every segment's cycle is collected, lost or not
            try:
                tables.append(segment.collect())
            except SampleLost as exc:
                lost = lost or exc
        if lost is not None:
            raise lost
        placed = tables[0] if len(tables) == 1 else np.concatenate(tables)
        return placed if self._in_order else placed[self._order]

    def command_currents(self, currents: Sequence[float]) -> None:
        """One motor current (A) per joint, in joint order, applied from the next cycle."""
        currents = np.asarray(currents, dtype=float)
        if self._whole:
            self.segments[0].command(currents)
            return
        for segment, rows in zip(self.segments, self._rows, strict=True):
            segment.command(currents[rows])

    def warnings(self) -> list[str]:
        if self._whole:
            return self.segments[0].warnings()
        return [warning for segment in self.segments for warning in segment.warnings()]

    def clock_trim(self) -> float:
        """s to add to the next period of the cycle's clock: the first DC line's reference
        clock leads (two lines' clocks cannot both), 0 without one."""
        return self.clocks[0].take_trim() if self.clocks else 0.0

    def quick_stop_all(self) -> list[tuple[str, str]]:
        """Quick-stop every drive (best effort each: a dead one does not spare the others),
        then read back each state: (joint, CiA 402 state name, or why it could not be read).
        A drive this master never booted (refused) is not ours: left alone, said so."""
        for drive in self.drives:  # every drive's in the outputs before any frame goes
            drive.stage_quick_stop()
        for drive in self.drives:
            drive.write_quick_stop()
        states = []
        for name, drive in zip(self.names, self.drives, strict=True):
            if not drive.booted:
                states.append((name, "left alone (not started by this master)"))
                continue
            try:
                states.append((name, drive.state().value))
            except DriveError as exc:
                states.append((name, f"unreachable ({exc})"))
        return states

    def close(self) -> None:
        """Disable every drive (best effort each), then release the buses. Idempotent."""
        if self._closed:
            return
        self._closed = True
        for name, drive in zip(self.names, self.drives, strict=True):
            try:
                drive.close()
            except Exception as exc:  # one drive's trouble must not keep the others enabled
                log.warning("joint %s: close failed: %s", name, exc)
        for segment in self.segments:
            segment.close()



def steer_together(transports: Sequence[EthercatTransport], goal: State) -> int | None:
    """Walk the CiA 402 state machines of one line's drives to `goal` together, by the
    controlwords and statuswords its frames carry (`EthercatMaster.pass_image`): a frame
    shows every state, every drive not there gets its next controlword
    (`protocol.cia402.controlword_toward`) in the next, and frames follow, a period apart,
    until each of those drives has left the state it was in (ENABLE_STEP_TIMEOUT on the
    line's clock, drive time in lock-step). One drive after the other, each read and write
    a frame of its own, 32 drives took some 400 frames, the enabled joints held at zero
    torque all the while; together, a few frames whatever their number. Returns None, or
    the index of the first drive that did not get there."""
    line = transports[0].line
    clock = line.clock

    def states() -> list[State]:
        return [t.image_state() for t in transports]

    line.pass_image()
    for _ in range(STEER_STEPS):
        before = states()
        words = [cia402.controlword_toward(state, goal) for state in before]
        moving = [k for k, word in enumerate(words) if word is not None]
        if not moving:
            return None
        resets = [k for k in moving if words[k] == cia402.Command.FAULT_RESET.value]
        for k in resets:  # a fault reset acts on its bit's rising edge
            transports[k].stage_output(objects.CONTROLWORD, 0, 0)
        if resets:
            line.pass_image()
        for k in moving:
            transports[k].stage_output(objects.CONTROLWORD, 0, words[k])
        deadline = clock.now() + ENABLE_STEP_TIMEOUT
        line.pass_image()  # takes them to the drives
        while True:
            line.pass_image()  # shows what the drives made of them
            after = states()
            if all(after[k] is not before[k] for k in moving) or clock.now() >= deadline:
                break
            if clock.runs_alone:
                clock.sleep_until(clock.now() + line.period)  # a drive's own pace
    return next((k for k, state in enumerate(states()) if state is not goal), None)


def single_joint(drive: Cia402Drive, name: str = "joint") -> DriveGroup:
    """One drive as a robot of one joint named `name`: on CANopen its bus's segment, as a
    robot's bus is (the transport keeps the network); on EtherCAT alone on its segment, its
    own `sync` each cycle (its transport sends the line's frame)."""
    from driver.canopen_transport import CanOpenTransport

    if isinstance(drive.transport, CanOpenTransport):
        segment: Segment = CanOpenBus(name, drive.transport.network, [(name, drive)],
                                      owns_network=False)
    else:
        segment = Segment(name, [(name, drive)])
    return DriveGroup([name], [segment])
