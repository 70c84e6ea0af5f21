"""Every joint of a robot in one cycle: one SYNC per CAN bus (one frame per EtherCAT segment),
every joint sampled in that cycle, every command sent before the next.

A `DriveGroup` owns the segments (a CAN bus, an EtherCAT line) and, through them, the joints'
`Cia402Drive`s. A cycle first triggers every segment (so the buses run side by side), then
collects every joint's sample; commands go out joint by joint right after the controller has
decided, which is before the next cycle's trigger. A failure on one joint is raised as a
`JointFailure` naming it; the caller then stops every joint (`quick_stop_all`), because the
others were planned on the assumption that the whole arm moves together.
"""

import logging
from collections.abc import Sequence

import can
import canopen

from driver.cia402_drive import Cia402Drive
from driver.interface import CommandRangeError, DriveError, Sample
from protocol import cia301

log = logging.getLogger(__name__)


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
    frame at the first `sync` of a cycle and the others read it; `open_ethercat_drives` on
    branch `ethercat`), and a drive alone on its CAN bus (its `sync` is the single-joint
    path exactly)."""

    def __init__(self, name: str, joints: Sequence[tuple[str, Cia402Drive]]):
        self.name = name
        self.joints = list(joints)

    def started(self) -> None:
        """Every drive of the group is up; cycles begin."""

    def trigger(self) -> None:
        """Start this segment's cycle (nothing to do where the first `sync` sends the frame)."""

    def collect(self) -> list[Sample]:
        samples = []
        for joint, drive in self.joints:
            try:
                samples.append(drive.sync())
            except DriveError as exc:
                raise JointFailure(joint, exc) from exc
        return samples

    def close(self) -> None:
        """Release what the segment owns beyond its drives (nothing here)."""


class CanOpenBus(Segment):
    """Several CANopen drives on one network: one SYNC for all of them per cycle. The bus owns
    the network (its drives' transports are built with `owns_network=False`)."""

    def __init__(self, name: str, network: canopen.Network,
                 joints: Sequence[tuple[str, Cia402Drive]]):
        super().__init__(name, joints)
        self.network = network

    def started(self) -> None:
        cyclic = 1 + sum(drive.transport.sync_cycle.frames_per_cycle for _, drive in self.joints)
        for _, drive in self.joints:
            drive.transport.health.expect_cyclic_frames(cyclic)
            drive.transport.health.restart_count()

    def trigger(self) -> None:
        sync_data = b""
        for joint, drive in self.joints:
            try:
                drive.check_healthy()
                expected = drive.transport.arm()
            except DriveError as exc:
                raise JointFailure(joint, exc) from exc
            # every drive arms once a cycle from the same start, so counters agree; a drive
            # that does not count SYNCs takes any data (CiA 301 ignores the counter then)
            if expected and sync_data and expected != sync_data:
                raise JointFailure(joint, DriveError(
                    f"expects SYNC counter {expected[0]}, the bus is at {sync_data[0]}"))
            sync_data = expected or sync_data
        try:
            self.network.send_message(cia301.SYNC_COB_ID, sync_data)
        except (can.CanError, OSError) as exc:
            raise JointFailure(self.joints[0][0],
                               DriveError(f"cannot send SYNC on {self.name}: {exc}")) from exc

    def collect(self) -> list[Sample]:
        samples = []
        for joint, drive in self.joints:
            try:
                samples.append(drive.take(drive.transport.collect))
            except DriveError as exc:
                raise JointFailure(joint, exc) from exc
        return samples

    def close(self) -> None:
        self.network.disconnect()


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
        self._order = [placed.index(name) for name in self.names]
        self.period = self.drives[0].period
        self._closed = False

    def __len__(self) -> int:
        return len(self.names)

    def start(self) -> None:
        """Configure every drive, then enable every one, in joint order: a drive that does not
        fit its joint is refused before any is enabled. A failure names the joint (the caller
        closes the group, which disables those already enabled)."""
        for step in ("configure", "enable"):
            for name, drive in zip(self.names, self.drives, strict=True):
                try:
                    getattr(drive, step)()
                except DriveError as exc:
                    raise JointFailure(name, exc) from exc
        for segment in self.segments:
            segment.started()

    def sync(self) -> list[Sample]:
        """One cycle: trigger every segment, then every joint's sample, in joint order."""
        for segment in self.segments:
            segment.trigger()
        placed = [sample for segment in self.segments for sample in segment.collect()]
        return [placed[i] for i in self._order]

    def command_currents(self, currents: Sequence[float]) -> None:
        """One motor current (A) per joint, in joint order, applied from the next cycle."""
        for name, drive, current in zip(self.names, self.drives, currents, strict=True):
            try:
                drive.command_current(current)
            except (CommandRangeError, DriveError) as exc:
                raise JointFailure(name, exc) from exc

    def warnings(self) -> list[str]:
        return [f"joint {name}: {warning}" for name, drive in zip(self.names, self.drives,
                                                                   strict=True)
                for warning in drive.warnings()]

    def quick_stop_all(self) -> list[tuple[str, str]]:
        """Quick-stop every drive (best effort each: a dead one does not spare the others),
        then read back each state: (joint, CiA 402 state name, or why it could not be read)."""
        for drive in self.drives:
            drive.quick_stop()
        states = []
        for name, drive in zip(self.names, self.drives, strict=True):
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

