"""The control loop: read the sample, solve, command the current, publish. Clocked by SYNC.

In real time the loop sleeps to each period's deadline before triggering the SYNC; in
lock-step (the virtual drive) it runs as fast as the drive answers, and time is the drive's.
Requests from outside (a new reference, new weights) are queued and applied at the start of a
cycle, so the solver never sees a half-made change.
"""

import math
import queue
import threading
from collections.abc import Callable
from dataclasses import dataclass, field

from controller.mpc import Mpc, TickResult
from driver import CommandRangeError, Drive, DriveError, Sample
from driver.clock import CycleClock, RingStats
from protocol import cia402

STALL_CYCLES = 10  # missed in a row: worth a message on the fault topic


@dataclass
class LoopOptions:
    period: float = 1e-3  # s
    lockstep: bool = False
    duration: float | None = None  # s of drive time; None runs until stopped
    plan_every: int = 10  # cycles between Plan messages
    stats_every: float = 1.0  # s of drive time between LoopStats messages
    keep_history: bool = False  # for --plot


@dataclass
class LoopReport:
    cycles: int = 0
    fallbacks: int = 0
    cold_solve_us: float = math.nan
    exit_code: int = 0
    reason: str = "stopped"
    clock: CycleClock | None = None
    solve: RingStats = field(default_factory=RingStats)
    history: dict = field(default_factory=dict)

    @property
    def missed_cycles(self) -> int:
        return self.clock.missed_cycles if self.clock else 0

    @property
    def jitter(self) -> RingStats:
        return self.clock.jitter_us if self.clock else RingStats(1)

    def summary(self) -> str:
        return (f"{self.cycles} cycles, {self.missed_cycles} missed, {self.fallbacks} safety "
                f"fallbacks; cold solve {self.cold_solve_us:.0f} us; period jitter p99 "
                f"{self.jitter.percentile(99):.1f} us, max {self.jitter.max:.1f} us; MPC tick "
                f"median {self.solve.percentile(50):.1f} us, p99 "
                f"{self.solve.percentile(99):.1f} us, max {self.solve.max:.1f} us; "
                f"{self.reason}")


class ControlLoop:
    def __init__(self, drive: Drive, mpc: Mpc, options: LoopOptions,
                 publish: Callable[[str, dict], None] | None = None,
                 dropped: Callable[[], int] = lambda: 0):
        self.drive = drive
        self.mpc = mpc
        self.options = options
        self.publish = publish or (lambda topic, fields: None)
        self.dropped = dropped
        self._requests: queue.Queue = queue.Queue()
        self._stop = threading.Event()
        self.report = LoopReport()

    def request(self, change: Callable[[Mpc], None]) -> None:
        """Apply `change(mpc)` at the start of the next cycle (thread-safe)."""
        self._requests.put(change)

    def stop(self) -> None:
        self._stop.set()

    def fault(self, t: float, source: str, cause: str, action: str) -> None:
        self.publish("fault", {"t": t, "source": source, "cause": cause, "action": action})

    def run(self) -> LoopReport:
        """Run until stopped, the duration is reached or the drive fails. The caller owns the
        drive's life cycle (start before, close after: close always disables it)."""
        options, report = self.options, self.report
        history = {k: [] for k in ("t", "position", "velocity", "reference", "current",
                                   "planned_current", "motor_current", "joint_torque")}
        if options.keep_history:
            report.history = history
        clock = report.clock = CycleClock(options.period, options.lockstep)
        next_stats = options.stats_every
        missed = 0
        while not self._stop.is_set():
            clock.wait()
            if clock.missed_cycles - missed >= STALL_CYCLES and self.drive.read() is not None:
                self.fault(self.drive.read().t, "controller",
                           f"loop stalled: {clock.missed_cycles - missed} cycles missed",
                           "continuing from the next sample")
            missed = clock.missed_cycles
            self._apply_requests()
            try:
                sample = self.drive.sync()
            except DriveError as exc:
                last = self.drive.read()
                return self._finish(1, f"drive failed: {exc}", "drive",
                                    "stopped commanding; drive disabled on exit",
                                    last.t + options.period if last is not None else 0.0)
            for warning in self.drive.warnings():
                self.fault(sample.t, "drive", warning, "continuing: the command does not use it")
            state = cia402.state_from_statusword(sample.statusword)
            if state is not cia402.State.OPERATION_ENABLED:
                return self._finish(1, f"drive left operation enabled: {state.value}", "drive",
                                    "stopped commanding; drive disabled on exit", sample.t)
            result = self.mpc.tick(sample.position, sample.velocity, sample.t)
            try:
                self.drive.command_current(result.current)
            except (CommandRangeError, DriveError) as exc:
                source = "controller" if isinstance(exc, CommandRangeError) else "drive"
                return self._finish(1, f"command refused: {exc}", source,
                                    "stopped commanding; drive disabled on exit", sample.t)
            if report.cycles == 0:
                # the cold solve runs once before the rhythm starts: timed on its own, and the
                # deadlines begin after it
                report.cold_solve_us = result.solve_time * 1e6
                clock.restart()
            else:
                clock.check_overrun()
                report.solve.add(result.solve_time * 1e6)
            report.cycles += 1
            self._publish_cycle(sample, state, result)
            if options.keep_history:
                for key, value in (("t", sample.t), ("position", sample.position),
                                   ("velocity", sample.velocity),
                                   ("reference", result.reference_position),
                                   ("current", result.current),
                                   ("planned_current", result.planned_current),
                                   ("motor_current", sample.motor_current),
                                   ("joint_torque", sample.joint_torque)):
                    history[key].append(value)
            if sample.t >= next_stats:
                next_stats += options.stats_every
                self.publish("loop_stats", self._stats_fields(sample.t))
            if options.duration is not None and sample.t >= options.duration - 1e-9:
                return self._finish(0, f"ran {options.duration} s", t=sample.t)
        return self._finish(0, "stop requested", t=self.drive.read().t if self.drive.read()
                            else 0.0)

    def _apply_requests(self) -> None:
        while True:
            try:
                change = self._requests.get_nowait()
            except queue.Empty:
                return
            change(self.mpc)

    def _publish_cycle(self, sample: Sample, state: cia402.State, result: TickResult) -> None:
        limits = self.mpc.limits
        self.publish("state", {
            "t": sample.t, "position": sample.position, "velocity": sample.velocity,
            "motor_current": sample.motor_current, "joint_torque": sample.joint_torque,
            "statusword": sample.statusword, "drive_state": state.value})
        self.publish("command", {
            "t": sample.t, "current": result.current,
            "planned_current": result.planned_current,
            "reference_position": result.reference_position,
            "reference_velocity": result.reference_velocity,
            "current_limit": limits.current_max, "position_min": limits.position_min,
            "position_max": limits.position_max, "saturated": result.saturated,
            "fallback": result.fault is not None})
        self.publish("solver", {
            "t": sample.t, "solve_time_us": result.solve_time * 1e6,
            "iterations": result.solve.iterations, "rollouts": result.solve.rollouts,
            "status": result.solve.status_name, "cost": result.solve.cost})
        if result.fault is not None:
            self.report.fallbacks += 1
            self.fault(sample.t, "controller", result.fault,
                       f"commanded {result.current:.3f} A (safe command)")
        if self.report.cycles % self.options.plan_every == 0:
            solver = self.mpc.solver
            self.publish("plan", {
                "t": sample.t, "dt": self.mpc.settings.dt,
                "position": solver.X[:, 0].tolist(), "velocity": solver.X[:, 1].tolist(),
                "current": solver.U.tolist(),
                "reference_position": solver.reference_position.tolist()})

    def _stats_fields(self, t: float) -> dict:
        report = self.report
        return {"t": t, "cycles": report.cycles, "missed_cycles": report.missed_cycles,
                "period_jitter_p99_us": report.jitter.percentile(99),
                "period_jitter_max_us": report.jitter.max,
                "solve_median_us": report.solve.percentile(50),
                "solve_p99_us": report.solve.percentile(99), "solve_max_us": report.solve.max,
                "dropped_messages": self.dropped()}

    def _finish(self, code: int, reason: str, source: str | None = None,
                action: str | None = None, t: float = 0.0) -> LoopReport:
        self.report.exit_code = code
        self.report.reason = reason
        if source is not None:
            self.fault(t, source, reason, action or "")
        self.publish("loop_stats", self._stats_fields(t))
        return self.report
