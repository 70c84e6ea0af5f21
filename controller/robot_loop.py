"""The control loop for a robot: every joint in one cycle.

Each period: one group sync (one SYNC per bus, every joint sampled in the same cycle), each
joint screened by its own safety net, the batched MPC over the joints that passed (one
compiled call), each decision checked by its net, one command per joint sent before the next
sync, and one `JointStates` message with every joint. A failure of any joint's drive ends the
run: the caller quick-stops every drive (`driver.drive_group.DriveGroup.quick_stop_all`), since
the other joints' plans assumed that one would move as planned.
"""

import math
import threading
import time
from collections.abc import Callable, Sequence
from typing import Protocol

import numpy as np

from controller import messages
from controller.loop import CycleLoop, LoopOptions, LoopReport
from controller.messages import Subscriber
from controller.mpc import BatchMpc
from controller.policy import Decision, PlanSnapshot
from controller.reference import reference_at
from controller.safety import SafeCommand, SafetyNet
from driver import DriveError, Sample
from protocol import cia402

QUICK_STOPPED = "every joint quick-stopped, then disabled"  # what the caller does on failure


class Joints(Protocol):
    """What the loop needs of the drives (`driver.drive_group.DriveGroup`)."""

    names: list[str]

    def sync(self) -> list[Sample]: ...

    def command_currents(self, currents: Sequence[float]) -> None: ...

    def warnings(self) -> list[str]: ...


class _JointPolicy:
    """One joint of the batch as its safety net sees it: the net asks for the reference and
    tells the joint to start afresh; the batch itself is ticked by the loop, once."""

    def __init__(self, batch: BatchMpc, index: int):
        self._batch, self._index = batch, index
        joint = batch.joints[index]
        self.parameters = joint.parameters
        self.limits = joint.limits

    def tick(self, sample: Sample) -> Decision:
        raise TypeError("a batched joint is ticked by RobotLoop with the others")

    def reference_at(self, t: float) -> tuple[float, float]:
        q, qd = reference_at(self._batch.joints[self._index].reference_packed, t)
        return float(q), float(qd)

    def reset(self) -> None:
        self._batch.skip(self._batch.joints[self._index])

    def plan(self, t: float) -> PlanSnapshot:
        return self._batch.plan(self._batch.joints[self._index], t)


class RobotLoop(CycleLoop):
    def __init__(self, joints: Joints, batch: BatchMpc, options: LoopOptions,
                 subscribers: Sequence[Subscriber] = (),
                 dropped: Callable[[], int] = lambda: 0, stop: threading.Event | None = None,
                 settle: float = 0.0):
        """`settle` (s of drive time): tracking errors count from then on (the approach from
        where a joint rests to its reference is not tracking)."""
        if len(batch) != len(joints.names):
            raise ValueError(f"{len(joints.names)} joints, {len(batch)} problems")
        super().__init__(options, subscribers, dropped, stop)
        self._joints = joints
        self.batch = batch
        self.names = list(joints.names)
        self._nets = [SafetyNet(_JointPolicy(batch, j)) for j in range(len(batch))]
        self.failed_joint: str | None = None  # the joint whose failure ended the run
        # per joint: sum of squared tracking errors and their count (for tracking_rms)
        self._squared_error = np.zeros(len(batch))
        self._tracked = 0
        self._settle = settle
        self.latest: list[Sample] | None = None
        self._drive_states: list[str] = []
        self._commands: list[SafeCommand] = []

    def tracking_rms(self) -> list[float]:
        """rad, each joint's RMS of position minus reference over the run (after `settle`)."""
        if not self._tracked:
            return [math.nan] * len(self.names)
        return [float(v) for v in np.sqrt(self._squared_error / self._tracked)]

    def _cycle(self) -> "float | LoopReport":
        joints, batch, count = self._joints, self.batch, len(self.names)
        try:
            samples = joints.sync()
        except DriveError as exc:
            return self._fail(exc, self.time + self.options.period)
        self.latest = samples
        t = self._t = samples[0].t
        for warning in joints.warnings():
            self.fault(t, "drive", warning, "continuing: the command does not use it")
        drive_states = self._drive_states = [
            cia402.state_from_statusword(s.statusword).value for s in samples]
        for name, state in zip(self.names, drive_states, strict=True):
            if state != cia402.State.OPERATION_ENABLED.value:
                self.failed_joint = name
                return self._finish(1, f"joint {name}: drive left operation enabled: {state}",
                                    "drive", QUICK_STOPPED, t)
        start = time.perf_counter()
        commands: list[SafeCommand | None] = [None] * count
        ticked = []
        for j in range(count):
            screened = self._nets[j].screen(samples[j])
            if screened is None:
                sample = samples[j]
                batch.prepare(batch.joints[j], sample.position, sample.velocity)
                ticked.append(j)
            else:
                commands[j] = screened
        batch.run(t)
        for j in ticked:
            commands[j] = self._nets[j].check(samples[j], batch.decision(batch.joints[j]))
        decide_time = time.perf_counter() - start
        self._commands = commands
        try:
            joints.command_currents([c.current for c in commands])
        except DriveError as exc:
            return self._fail(exc, t)
        return decide_time

    def _published(self, decide_time: float) -> None:
        t, samples, commands = self._t, self.latest, self._commands
        self.publish(messages.joint_states(t, self.names, samples, self._drive_states,
                                           commands, decide_time))
        for name, command in zip(self.names, commands, strict=True):
            if command.fault is not None:
                self.report.fallbacks += 1
                self.fault(t, "controller", f"joint {name}: {command.fault}",
                           f"commanded {command.current:.3f} A (safe command)")
        if t >= self._settle:
            for j, (sample, command) in enumerate(zip(samples, commands, strict=True)):
                error = sample.position - command.decision.reference_position
                self._squared_error[j] += error * error
            self._tracked += 1

    def _fail(self, exc: DriveError, t: float) -> LoopReport:
        self.failed_joint = getattr(exc, "joint", None)
        return self._finish(1, f"drive failed: {exc}", "drive", QUICK_STOPPED, t)
