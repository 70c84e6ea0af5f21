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
from controller.loop import STALL_CYCLES, LoopOptions, LoopReport
from controller.messages import Subscriber
from controller.mpc import BatchMpc
from controller.policy import Decision, PlanSnapshot
from controller.reference import reference_at
from controller.safety import SafeCommand, SafetyNet
from driver import DriveError, Sample
from driver.clock import CycleClock
from protocol import cia402


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


class RobotLoop:
    def __init__(self, joints: Joints, batch: BatchMpc, options: LoopOptions,
                 subscribers: Sequence[Subscriber] = (),
                 dropped: Callable[[], int] = lambda: 0, stop: threading.Event | None = None,
                 settle: float = 0.0):
        """`settle` (s of drive time): tracking errors count from then on (the approach from
        where a joint rests to its reference is not tracking)."""
        if len(batch) != len(joints.names):
            raise ValueError(f"{len(joints.names)} joints, {len(batch)} problems")
        self._joints = joints
        self.batch = batch
        self.options = options
        self.names = list(joints.names)
        self._nets = [SafetyNet(_JointPolicy(batch, j)) for j in range(len(batch))]
        self._subscribers = tuple(subscribers)
        self._dropped = dropped
        self._stop = stop if stop is not None else threading.Event()
        self.report = LoopReport()
        self.failed_joint: str | None = None  # the joint whose failure ended the run
        # per joint: sum of squared tracking errors and their count (for tracking_rms)
        self._squared_error = np.zeros(len(batch))
        self._tracked = 0
        self._settle = settle
        self.latest: list[Sample] | None = None

    def stop(self) -> None:
        self._stop.set()

    def publish(self, message) -> None:
        for subscriber in self._subscribers:
            subscriber(message)

    def tracking_rms(self) -> list[float]:
        """rad, each joint's RMS of position minus reference over the run (after `settle`)."""
        if not self._tracked:
            return [math.nan] * len(self.names)
        return [float(v) for v in np.sqrt(self._squared_error / self._tracked)]

    def run(self) -> LoopReport:
        """Run until stopped, the duration is reached or a joint fails. The caller owns the
        drives (start before; on failure quick-stop all; close after)."""
        options, report, joints, batch = self.options, self.report, self._joints, self.batch
        clock = report.clock = CycleClock(options.period, options.lockstep)
        next_stats = options.stats_every
        missed = 0
        t = 0.0
        perf_counter = time.perf_counter
        count = len(self.names)
        while not self._stop.is_set():
            clock.wait()
            if clock.missed_cycles - missed >= STALL_CYCLES:
                self._fault(t, "controller",
                            f"loop stalled: {clock.missed_cycles - missed} cycles missed",
                            "continuing from the next sample")
            missed = clock.missed_cycles
            try:
                samples = joints.sync()
            except DriveError as exc:
                return self._fail(exc, t + options.period)
            self.latest = samples
            t = samples[0].t
            for warning in joints.warnings():
                self._fault(t, "drive", warning, "continuing: the command does not use it")
            drive_states = [cia402.state_from_statusword(s.statusword).value for s in samples]
            for name, state in zip(self.names, drive_states, strict=True):
                if state != cia402.State.OPERATION_ENABLED.value:
                    self.failed_joint = name
                    return self._finish(1, f"joint {name}: drive left operation enabled: "
                                           f"{state}", "drive", t)
            start = perf_counter()
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
            decide_time = perf_counter() - start
            try:
                joints.command_currents([c.current for c in commands])
            except DriveError as exc:
                return self._fail(exc, t)
            if report.cycles == 0:
                # the cold solves run once before the rhythm starts: timed on their own, and
                # the deadlines begin after them
                report.cold_solve_us = decide_time * 1e6
                clock.restart()
            else:
                clock.check_overrun()
                report.solve.add(decide_time * 1e6)
            report.cycles += 1
            self.publish(messages.joint_states(t, self.names, samples, drive_states, commands,
                                               decide_time))
            for name, command in zip(self.names, commands, strict=True):
                if command.fault is not None:
                    report.fallbacks += 1
                    self._fault(t, "controller", f"joint {name}: {command.fault}",
                                f"commanded {command.current:.3f} A (safe command)")
            if t >= self._settle:
                for j, (sample, command) in enumerate(zip(samples, commands, strict=True)):
                    error = sample.position - command.decision.reference_position
                    self._squared_error[j] += error * error
                self._tracked += 1
            if t >= next_stats:
                next_stats += options.stats_every
                self.publish(self._stats(t))
            if options.duration is not None and t >= options.duration - 1e-9:
                return self._finish(0, f"ran {options.duration} s", t=t)
        return self._finish(0, "stop requested", t=t)

    def _fail(self, exc: DriveError, t: float) -> LoopReport:
        self.failed_joint = getattr(exc, "joint", None)
        return self._finish(1, f"drive failed: {exc}", "drive", t)

    def _fault(self, t: float, source: str, cause: str, action: str) -> None:
        self.publish(messages.fault(t, source, cause, action))

    def _stats(self, t: float):
        report = self.report
        return messages.loop_stats(
            t, report.cycles, report.missed_cycles, report.jitter.percentile(99),
            report.jitter.max, report.solve.percentile(50), report.solve.percentile(99),
            report.solve.max, self._dropped())

    def _finish(self, code: int, reason: str, source: str | None = None,
                t: float = 0.0) -> LoopReport:
        self.report.exit_code = code
        self.report.reason = reason
        if source is not None:
            self._fault(t, source, reason, "every joint quick-stopped, then disabled")
        self.publish(self._stats(t))
        return self.report
