"""What a controller needs from an actuator drive, whatever the fieldbus.

CANopen (this package) implements it today; an EtherCAT CoE backend maps the same CiA 402
objects onto process data and can implement it without touching the controller.
"""

from abc import ABC, abstractmethod
from typing import NamedTuple


class Sample(NamedTuple):
    """One synchronous sample of the drive, in SI units. Immutable; a named tuple rather than
    a frozen dataclass because one is made per joint per cycle (a third of the cost).

    `joint_torque` is the torque sensor's reading on its nominal scale; the model's
    `torque_sensor_gain` (K_j) maps it to the true joint torque.
    """

    t: float  # s, cycle count x period (the drive's time base)
    position: float  # rad
    velocity: float  # rad/s
    motor_current: float  # A
    joint_torque: float  # N.m
    statusword: int


# the column of each field where a cycle's samples are stacked into one array (rows: joints),
# as the robot's cycle works on them
(SAMPLE_T, SAMPLE_POSITION, SAMPLE_VELOCITY, SAMPLE_MOTOR_CURRENT, SAMPLE_JOINT_TORQUE,
 SAMPLE_STATUSWORD) = range(len(Sample._fields))


class DriveError(RuntimeError):
    """Base of everything a drive reports as going wrong."""


class DriveFault(DriveError):
    """The drive is in its CiA 402 fault state (EMCY received); needs an explicit reset."""

    def __init__(self, message: str, error_code: int = 0):
        super().__init__(message)
        self.error_code = error_code


class DriveLost(DriveError):
    """The drive stopped talking (heartbeat missing, or it rebooted under us)."""


class SdoRefused(DriveError):
    """The drive answered an SDO access with an abort (`abort_code`, CiA 301): its answer,
    not a lost message."""

    def __init__(self, message: str, abort_code: int):
        super().__init__(message)
        self.abort_code = abort_code


class DriveTimeout(DriveError):
    """A SYNC went unanswered: the sample did not arrive in time."""


class SampleLost(DriveError):
    """This cycle's frame did not come back (an EtherCAT frame lost on the line), and the
    line rides through it: no sample this cycle, the drives hold the outputs they had. A loop
    skips the cycle and counts it missed; the line fails with an error of its own once
    frames stay lost past what the drives forgive (`driver.ethercat_master`'s
    LOST_FRAMES_IN_A_ROW). A caller that knows nothing of it meets a DriveError, as for any
    other failure."""


class EncoderGlitch(DriveError):
    """The position jumped further in one cycle than the joint can move."""


class ProfileError(DriveError):
    """The drive lacks what the loop needs (a mode, an object, a mapping); found before
    anything was enabled, so it is bad input rather than a run-time failure."""


class ForeignMaster(DriveError):
    """Another master is driving the drive (its SYNC or RPDO traffic, or the drive already
    enabled): taking it over would fight that master."""


class CommandRangeError(ValueError):
    """A command outside what the drive accepts; nothing was sent."""


class Drive(ABC):
    """A torque-controlled joint behind a drive: enable, sample, command current, disable.

    `sync()` is the clock: it makes the drive sample (and, in lock-step simulation, advance)
    and returns the new sample; a command given after it is applied from the next cycle on.
    """

    period: float  # s
    current_limit: float  # A, the largest |current| the drive accepts

    @abstractmethod
    def start(self) -> None:
        """Bring the drive up (boot, configure) and enable it for current commands."""

    @abstractmethod
    def sync(self) -> Sample:
        """Trigger one cycle and return its sample; raises DriveError subclasses."""

    @abstractmethod
    def read(self) -> Sample | None:
        """The latest sample without triggering a cycle (None before the first)."""

    @abstractmethod
    def command_current(self, current: float) -> None:
        """Command motor current (A); CommandRangeError if |current| > current_limit or NaN."""

    @abstractmethod
    def enable(self) -> None:
        """Run the CiA 402 sequence to operation enabled (resets a fault first)."""

    @abstractmethod
    def disable(self) -> None:
        """Zero current and leave the power stage off (switch on disabled)."""

    @abstractmethod
    def fault_reset(self) -> None:
        """Clear a drive fault (CiA 402 fault reset); the drive is left disabled."""

    def warnings(self) -> list[str]:
        """Problems seen since the last call that did not stop the drive (a duplicate frame,
        an implausible sensor reading, an overloaded bus): for the fault topic."""
        return []

    @abstractmethod
    def close(self) -> None:
        """Disable the drive (best effort if it is unreachable) and release the bus."""

    def __enter__(self) -> "Drive":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
