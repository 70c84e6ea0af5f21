"""The CiA 402 layer, transport-neutral: a `Drive` on any `driver.transport.Transport`.

It owns what is the same on every fieldbus: which objects to use (`driver.profile`), their
units, steering the power state machine, turning process data into `Sample`s and currents into
targets, judging samples (`driver.sample_guard`, limits passed in) and drive faults from
emergencies. Transports own the bus: frames, timing, watchdogs.
"""

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from canopen.emcy import EmcyError

from driver.interface import (
    CommandRangeError,
    Drive,
    DriveError,
    DriveFault,
    DriveTimeout,
    EncoderGlitch,
    ProfileError,
    Sample,
    SampleLost,
    SdoRefused,
)
from driver.profile import Profile, Scaling, read_scaling, select_profile
from driver.sample_guard import SampleGuard
from driver.transport import Transport
from protocol import cia301, cia402, objects
from protocol.cia402 import State
from protocol.dictionary import StartupParameter, variable

log = logging.getLogger(__name__)

ENABLE_STEP_TIMEOUT = 0.5  # s for the drive to show each CiA 402 transition
BOOT_TIMEOUT = 5.0  # s for the drive to answer the reset at bring-up
_NUMBER = (int, float)  # a command's accepted types (`int | float` would build a union per call)


def _nothing() -> None:
    """The default `Cia402Drive.on_fault`: no segment is looking."""


@dataclass(frozen=True)
class Emergency:
    """An emergency as the drive sent it (CiA 301 codes on CANopen and EtherCAT alike)."""

    code: int
    register: int

    @property
    def description(self) -> str:
        return EmcyError(self.code, self.register, b"", 0.0).get_desc()


class Cia402Drive(Drive):
    """A CiA 402 torque drive for one joint, through `transport`.

    `velocity_limit` (rad/s) is the joint's, for the sample guard; `drive_gain` (N.m/A) is
    the model's, needed when the drive is commanded in torque (0x6071); `current_max` (A) is
    the most the controller will command: a drive that accepts less is refused at start,
    before it is enabled (ProfileError). `startup` are the robot file's objects for this drive,
    written right after boot (PRE-OP / PRE-OPERATIONAL) and read back. The profile is chosen
    from the transport's dictionary here, before any traffic: ProfileError if the drive lacks
    what the loop needs.
    """

    def __init__(self, transport: Transport, *, velocity_limit: float, period: float = 1e-3,
                 drive_gain: float | None = None, current_max: float | None = None,
                 startup: Sequence[StartupParameter] = ()):
        if not 50e-6 <= period <= 1.0:
            raise ValueError(f"period {period} s outside 50 us .. 1 s")
        self.transport = transport
        self.name = transport.name
        self.period = period
        self.drive_gain = drive_gain
        self.current_max = current_max
        self.startup = tuple(startup)
        self.profile: Profile = select_profile(transport.dictionary, drive_gain)
        self.guard = SampleGuard(velocity_limit, period)
        self.scaling: Scaling | None = None
        self.current_limit = 0.0
        self.cycle = 0
        self.last_emergency: Emergency | None = None
        self._fault: DriveError | None = None
        # called (in whichever thread saw it) each time this drive faults: a segment then
        # looks at its drives once, instead of asking every drive every cycle
        self.on_fault: Callable[[], None] = _nothing
        self._latest: Sample | None = None
        self._periods_since_latest = 1  # more after cycles whose sample was lost
        self._warnings: list[str] = []
        self._lock = threading.Lock()  # emergencies arrive in the transport's receive thread
        self._closed = False
        self._booted = False
        transport.on_emergency = self._on_emergency

    # --- bring-up ---------------------------------------------------------------------------

    def configure(self) -> None:
        """Everything before the power stage: boot, scaling, the current check, the mode and
        the process data, cyclic exchange running. Split from `enable` so that a group can
        refuse any of its drives before it enables one."""
        t = self.transport
        t.boot(BOOT_TIMEOUT)
        self._booted = True  # from here on the drive is ours to leave disabled
        self._write_startup()
        self.scaling = read_scaling(self.profile, t.read, t.dictionary, self.drive_gain)
        self.current_limit = self.scaling.current_limit
        if self.current_max is not None and self.current_max > self.current_limit * (1 + 1e-9):
            # refused before the power stage is on: the controller would plan with currents
            # the drive refuses, and the first such command would end the run enabled
            raise ProfileError(
                f"{self.name}: the model's current_max {self.current_max:g} A is more than the "
                f"drive accepts, {self.current_limit:g} A (its max current); lower current_max "
                "in the model file or raise the drive's limit")
        t.write(objects.MODES_OF_OPERATION, 0, self.profile.mode)
        t.map_process_data(self.profile.outputs, self.profile.inputs)
        t.start(self.period)

    def _write_startup(self) -> None:
        """The start-up parameters, in order, each read back: before the scaling is read, so
        a changed limit (0x6073, 0x6072) is the one the master plans with. A drive that
        refuses one, or keeps another value, stops the start in one line naming the object
        and the abort code in words (the robot file was checked against the EDS already, so
        this is the drive's own answer)."""
        t = self.transport
        for index, subindex, value in self.startup:
            var = variable(t.dictionary, index, subindex)
            what = f"start-up parameter 0x{index:04X}:{subindex:02X}" + (
                f" ({var.name})" if var is not None else "")
            try:
                t.write(index, subindex, value)
                if var is not None and var.access_type == "wo":
                    continue  # nothing to read back
                kept = t.read(index, subindex)
            except SdoRefused as exc:
                raise SdoRefused(f"{self.name}: {what} = {value} refused by the drive: "
                                 f"{cia301.sdo_abort_name(exc.abort_code)}",
                                 exc.abort_code) from exc
            expected = var.decode_raw(var.encode_raw(value)) if var is not None else value
            if kept != expected:
                raise DriveError(f"{self.name}: {what} = {value} written, the drive reads back "
                                 f"{kept}")

    def start(self) -> None:
        self.configure()
        self.enable()

    # --- CiA 402 ----------------------------------------------------------------------------

    def state(self) -> State:
        return cia402.state_from_statusword(self.transport.read(objects.STATUSWORD))

    def enable(self) -> None:
        self._steer(State.OPERATION_ENABLED)
        self.mark_enabled()

    def mark_enabled(self) -> None:
        """Operation enabled, by `enable` or by its segment with the others
        (`driver.drive_group.EthercatLine.enable`): a fault met on the way is behind it."""
        with self._lock:
            self._fault = None

    def disable(self) -> None:
        self._send(cia402.Command.DISABLE_VOLTAGE.value, 0.0)
        self._steer(State.SWITCH_ON_DISABLED)

    def fault_reset(self) -> None:
        self.transport.write(objects.CONTROLWORD, 0, 0)
        self._steer(State.SWITCH_ON_DISABLED)
        with self._lock:
            self.last_emergency = None
            self._fault = None

    def _steer(self, goal: State) -> None:
        """Walk the CiA 402 graph by acyclic controlword writes until the statusword shows
        goal (acyclic: it works before cyclic exchange runs and on every transport)."""
        for _ in range(8):
            state = self.state()
            controlword = cia402.controlword_toward(state, goal)
            if controlword is None:
                return
            if controlword == cia402.Command.FAULT_RESET.value:
                self.transport.write(objects.CONTROLWORD, 0, 0)  # bit 7 acts on its rising edge
            self.transport.write(objects.CONTROLWORD, 0, controlword)
            deadline = time.monotonic() + ENABLE_STEP_TIMEOUT
            while self.state() is state and time.monotonic() < deadline:
                time.sleep(0.001)
        raise DriveFault(f"{self.name}: cannot reach '{goal.value}' "
                         f"(stuck in '{self.state().value}')")

    # --- cyclic -----------------------------------------------------------------------------

    @property
    def fault(self) -> DriveError | None:
        """What stops this drive: a drive fault, a glitch, or the transport's failure."""
        return self._fault or self.transport.failure

    def sync(self) -> Sample:
        self.check_healthy()
        return self.take(self.transport.exchange)

    def check_healthy(self) -> None:
        """Raise what stops this drive, if anything (before a cycle is triggered)."""
        fault = self.fault
        if fault is not None:
            raise fault

    def take(self, inputs: Callable[[], tuple[int, ...]]) -> Sample:
        """This cycle's sample from `inputs()`: the transport's `exchange`, or, where several
        drives share one SYNC or frame (`driver.drive_group`), the half that collects this
        drive's process data after it."""
        try:
            values = inputs()
        except SampleLost:
            self.cycle += 1  # its period passed without a sample
            self._periods_since_latest += 1
            raise
        except DriveTimeout:
            if self._fault is not None:
                raise self._fault from None  # the drive faulted and stopped answering
            raise
        self.cycle += 1
        scaling = self.scaling
        joint_torque = math.nan
        if self.profile.has_joint_torque:
            reading = values[4]
            if self.guard.saturated(reading):
                self._warnings.append(f"joint torque sensor reading saturated ({reading} mN.m)")
            else:
                joint_torque = reading * scaling.joint_torque_per_unit
        # positional: t, position, velocity, motor_current, joint_torque, statusword
        sample = Sample(self.cycle * self.period, values[1] * scaling.rad_per_increment,
                        values[2] * scaling.rad_per_increment,
                        values[3] * scaling.amps_per_feedback_unit, joint_torque, values[0])
        previous, self._latest = self._latest, sample
        periods, self._periods_since_latest = self._periods_since_latest, 1
        if previous is not None:
            try:
                self.guard.check_step(previous.position, sample.position, self.name, periods)
            except EncoderGlitch as error:
                self.fail(error)
                raise
        self.judge_statusword(sample.statusword)
        return sample

    def fail(self, error: DriveError) -> None:
        """This drive is stopped by `error` (a glitch its segment found on the arrays, say):
        raised by `check_healthy` until it is enabled or reset again."""
        with self._lock:
            self._fault = error
        self.on_fault()

    def judge_statusword(self, statusword: int) -> None:
        """A statusword in the fault state makes this drive faulted (named by its emergency
        when one came): from its own sample, or from a segment's arrays."""
        if cia402.state_from_statusword(statusword) is State.FAULT:
            with self._lock:
                if self._fault is None:
                    self._fault = DriveFault(self._fault_text(), self._emergency_code())
            self.on_fault()

    def read(self) -> Sample | None:
        return self._latest

    def measured_state(self) -> tuple[float, float]:
        """Position (rad) and velocity (rad/s) read acyclically once configured: where the
        joint is before it is enabled, for a controller to make its first plan from while
        no cycle waits for it."""
        read, per_increment = self.transport.read, self.scaling.rad_per_increment
        return (read(objects.POSITION_ACTUAL) * per_increment,
                read(objects.VELOCITY_ACTUAL) * per_increment)

    def warnings(self) -> list[str]:
        out = self._warnings[:]
        del self._warnings[:len(out)]  # in place: the list stays the one `warning_lists` gave
        return out + self.transport.warnings()

    @property
    def has_warnings(self) -> bool:
        """Whether `warnings()` has anything to say (a cheap look, for a line's cycle)."""
        return bool(self._warnings) or self.transport.has_warnings

    @property
    def warning_lists(self) -> tuple[list[str], ...]:
        """The lists `warnings()` drains (the drive's own, its transport's): a segment looks
        at them all at once each cycle, no call per drive."""
        return (self._warnings, *self.transport.warning_lists)

    def command_current(self, current: float) -> None:
        if not isinstance(current, _NUMBER) or not math.isfinite(current):
            raise CommandRangeError(f"motor current command {current!r} is not a finite number")
        if abs(current) > self.current_limit:
            raise CommandRangeError(f"motor current command {current:.3f} A outside the drive's "
                                    f"limit of +/-{self.current_limit:.3f} A")
        self.check_healthy()
        self._send(cia402.Command.ENABLE_OPERATION.value, current)

    def _send(self, controlword: int, current: float) -> None:
        target = int(round(current * self.scaling.target_units_per_amp))
        self.transport.send((controlword, target))

    # --- health -----------------------------------------------------------------------------

    def _on_emergency(self, code: int, register: int) -> None:
        if code == cia301.EMCY_NO_ERROR:
            return
        with self._lock:
            self.last_emergency = Emergency(code, register)
            log.error("%s: EMCY 0x%04X %s", self.name, code, self.last_emergency.description)
            self._fault = DriveFault(self._fault_text(), code)
        self.on_fault()

    def _fault_text(self) -> str:
        if self.last_emergency is None:
            return f"{self.name}: drive in fault state"
        return (f"{self.name}: drive fault, EMCY 0x{self.last_emergency.code:04X} "
                f"({self.last_emergency.description})")

    def _emergency_code(self) -> int:
        return self.last_emergency.code if self.last_emergency is not None else 0

    @property
    def booted(self) -> bool:
        """This master booted the drive (it is ours to stop and leave disabled)."""
        return self._booted

    def quick_stop(self) -> None:
        """CiA 402 quick stop, now: the controlword by process data (the fastest way in) and
        again by the transport's own write (SDO; on an EtherCAT line its frame, or its last
        frame after a failure: `driver.ethercat_transport`). A torque drive then
        applies no torque and engages its brake (quick stop option 0x605A). Best effort:
        never raises, so one dead drive does not keep the others running. A drive never
        booted (refused: another master drives it) is left alone, as `close` leaves it: a
        refused second master used to quick-stop the first master's running joint."""
        self.stage_quick_stop()
        self.write_quick_stop()

    def stage_quick_stop(self) -> None:
        """The quick stop's process data half: the controlword and a zero target in the
        outputs (on EtherCAT the line's next frame carries them; on CANopen the RPDO goes),
        best effort. A group stages every drive's before any drive's `write_quick_stop`, so
        the first frame that goes stops them all."""
        if not self._booted or self.scaling is None:
            return
        try:
            self._send(cia402.Command.QUICK_STOP.value, 0.0)
        except DriveError as exc:
            log.warning("%s: quick stop by process data failed: %s", self.name, exc)

    def write_quick_stop(self) -> None:
        """The quick stop's other half: the controlword by the transport's own write, best
        effort."""
        if not self._booted:
            return
        try:
            self.transport.write(objects.CONTROLWORD, 0, cia402.Command.QUICK_STOP.value)
        except DriveError as exc:
            log.warning("%s: quick stop by acyclic write failed: %s", self.name, exc)

    # --- shutdown ---------------------------------------------------------------------------

    def close(self) -> None:
        """Leave the drive disabled: zero current and disable voltage cyclically, disable
        voltage acyclically, leave cyclic operation. Each step best effort, so a dead drive
        does not stop the rest. A drive never booted (refused, or another master's) is left
        alone. Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            if self._booted:
                if self.scaling is not None:
                    self._send(cia402.Command.DISABLE_VOLTAGE.value, 0.0)
                self.transport.write(objects.CONTROLWORD, 0,
                                     cia402.Command.DISABLE_VOLTAGE.value)
        except DriveError as exc:
            log.warning("%s: could not confirm disable on close: %s", self.name, exc)
        finally:
            if self._booted:
                self.transport.stop()
            self.transport.close()
