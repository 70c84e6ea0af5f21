"""The control loop: read the sample, decide, command the current, publish. Clocked by SYNC.

One loop for every policy (the MPC, an experiment's tracking law) with the same safety net
around it (`controller.safety`). In real time the loop sleeps to each period's deadline before
triggering the SYNC; in lock-step (the virtual drive) it runs as fast as the drive answers, and
time is the drive's. Requests from outside (a new reference, new weights) are queued and applied
at the start of a cycle, so the policy never sees a half-made change. Every sample and decision
goes to the subscribers as typed telemetry messages (`controller.messages`), in this thread: a
subscriber that does I/O hands the message to its own thread.
"""

import collections
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from controller import messages
from controller.messages import Subscriber
from controller.policy import Policy
from controller.safety import SafeCommand, SafetyNet
from driver import CommandRangeError, Drive, DriveError, Sample
from driver.clock import CycleClock, RingStats
from protocol import cia402

STALL_CYCLES = 10  # missed in a row: worth a message on the fault topic
# why a cycle missed its deadline: woken late by the host; the drive's sample late (the
# exchange, SYNC to the last TPDO or the frame's round trip); the decision (safety and MPC)
# over the period; the telemetry's hand-off and the loop's own messages
LATE_WAKE_UP, LATE_SAMPLE, DECISION, PUBLISH = ("late wake-up", "late sample",
                                                "decision over budget", "publish back-pressure")
MISSED_CAUSES = (LATE_WAKE_UP, LATE_SAMPLE, DECISION, PUBLISH)
HISTORY_KEYS = ("t", "position", "velocity", "reference", "current", "planned_current",
                "motor_current", "joint_torque")


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
    # missed cycles by what took the cycle's time: MISSED_CAUSES, counted in `run`
    missed_by_cause: dict[str, int] = field(
        default_factory=lambda: dict.fromkeys(MISSED_CAUSES, 0))
    # us per cycle the master spends besides the MPC's call: exchange with the drives,
    # decoding, safety, encoding (a figure of its own: what the service adds to the solver)
    master: RingStats = field(default_factory=RingStats)
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
                f"{self.solve.percentile(99):.1f} us, max {self.solve.max:.1f} us; master "
                f"(MPC excluded) median {self.master.percentile(50):.1f} us, p99 "
                f"{self.master.percentile(99):.1f} us; missed by cause: "
                + ", ".join(f"{cause} {n}" for cause, n in self.missed_by_cause.items())
                + f"; {self.reason}")

    def figures(self) -> dict:
        """The run's figures as plain data (what `actuatord --report` writes as JSON): times
        in us, missed cycles in total and by cause."""
        def stats(ring: RingStats) -> dict:
            return {"median_us": ring.percentile(50), "p99_us": ring.percentile(99),
                    "max_us": ring.max}

        return {"cycles": self.cycles, "missed": self.missed_cycles,
                "missed_by_cause": dict(self.missed_by_cause), "fallbacks": self.fallbacks,
                "cold_solve_us": self.cold_solve_us,
                "jitter": {"p99_us": self.jitter.percentile(99), "max_us": self.jitter.max},
                "mpc_tick": stats(self.solve), "master": stats(self.master),
                "exit_code": self.exit_code, "reason": self.reason}

    def count_missed(self, phases: dict[str, float], cycles: int) -> None:
        """`cycles` missed, put down to the phase that took longest of the cycle behind them
        (`phases`: s per cause), so a user can tell their machine from the service."""
        if cycles:
            cause = max(phases, key=phases.__getitem__)
            self.missed_by_cause[cause] += cycles


class CycleLoop:
    """The rhythm every control loop keeps, whatever it drives (one joint: `ControlLoop`; a
    robot: `controller.robot_loop.RobotLoop`): wait for the period's deadline (real time) or
    not (lock-step), report a stall, apply queued requests at the cycle start, run the cycle,
    time the decision (the first, cold one apart, after which the deadlines start), publish
    LoopStats every `stats_every` s of drive time, and end at the duration.

    A subclass's `_cycle()` samples, decides and commands; it returns the decision's wall time
    (s), or the report when the run ends there (`_finish`). `_published()` then sends the
    cycle's messages, with `report.cycles` already counting this cycle."""

    def __init__(self, options: LoopOptions, subscribers: Sequence[Subscriber] = (),
                 dropped: Callable[[], int] = lambda: 0, stop: threading.Event | None = None):
        """`dropped` counts the messages subscribers could not pass on (for LoopStats); `stop`,
        when given, is the caller's flag to end the run (a signal handler sets it)."""
        self.options = options
        self._subscribers = tuple(subscribers)
        self._dropped = dropped
        # appended by other threads, drained by the loop: deque's append and popleft are atomic
        self._requests: collections.deque[Callable[[], None]] = collections.deque()
        self._stop = stop if stop is not None else threading.Event()
        self.report = LoopReport()
        self._t: float | None = None  # drive time of the last sample (None before the first)
        self._mpc_time = 0.0  # s the last cycle spent in the policy's own call (set by _cycle)
        self._exchange_time = 0.0  # s the last cycle waited for its sample (set by _cycle)

    @property
    def time(self) -> float:
        """The drive time of the last sample (0 before the first)."""
        t = self._t
        return t if t is not None else 0.0

    def request(self, change: Callable[[], None]) -> None:
        """Run `change()` at the start of the next cycle (thread-safe)."""
        self._requests.append(change)

    def stop(self) -> None:
        self._stop.set()

    def publish(self, message) -> None:
        for subscriber in self._subscribers:
            subscriber(message)

    def fault(self, t: float, source: str, cause: str, action: str) -> None:
        self.publish(messages.fault(t, source, cause, action))

    def _clock_trim(self) -> float:
        """s to move the next deadline by (a loop whose drives keep a clock of their own)."""
        return 0.0

    def run(self) -> LoopReport:
        """Run until stopped, the duration is reached, the policy is done or a drive fails.
        The caller owns the drives' life cycle (start before, close after: close always
        disables them)."""
        options, report = self.options, self.report
        clock = report.clock = CycleClock(options.period, options.lockstep)
        next_stats = options.stats_every
        missed = 0
        behind: dict[str, float] = dict.fromkeys(MISSED_CAUSES, 0.0)  # the last cycle's phases
        while not self._stop.is_set():
            report.count_missed(behind, clock.wait(self._clock_trim()))
            if clock.missed_cycles - missed >= STALL_CYCLES and self._t is not None:
                self.fault(self._t, "controller",
                           f"loop stalled: {clock.missed_cycles - missed} cycles missed",
                           "continuing from the next sample")
            missed = clock.missed_cycles
            while self._requests:
                self._requests.popleft()()
            started = time.perf_counter()
            decide_time = self._cycle()
            if isinstance(decide_time, LoopReport):
                return decide_time
            master_time = time.perf_counter() - started - self._mpc_time
            if report.cycles == 0:
                # the cold solve runs once before the rhythm starts: timed on its own, and the
                # deadlines begin after it
                report.cold_solve_us = decide_time * 1e6
                clock.restart()
            phases = {LATE_WAKE_UP: clock.wake_lateness, LATE_SAMPLE: self._exchange_time,
                      DECISION: decide_time, PUBLISH: 0.0}
            if report.cycles:
                report.count_missed(phases, clock.check_overrun())
                report.solve.add(decide_time * 1e6)
                report.master.add(master_time * 1e6)
            report.cycles += 1
            published = time.perf_counter()
            self._published(decide_time)
            t = self._t
            if t >= next_stats:
                next_stats += options.stats_every
                self.publish(self._stats(t))
            phases[PUBLISH] = time.perf_counter() - published
            behind = phases
            if options.duration is not None and t >= options.duration - 1e-9:
                return self._finish(0, f"ran {options.duration} s", t=t)
            if self._done():
                return self._finish(0, "the policy finished", t=t)
        return self._finish(0, "stop requested", t=self.time)

    def _cycle(self) -> "float | LoopReport":
        raise NotImplementedError

    def _published(self, decide_time: float) -> None:
        raise NotImplementedError

    def _done(self) -> bool:
        return False

    def _stats(self, t: float):
        report = self.report
        return messages.loop_stats(
            t, report.cycles, report.missed_cycles, report.jitter.percentile(99),
            report.jitter.max, report.solve.percentile(50), report.solve.percentile(99),
            report.solve.max, self._dropped())

    def _finish(self, code: int, reason: str, source: str | None = None,
                action: str | None = None, t: float = 0.0) -> LoopReport:
        self.report.exit_code = code
        self.report.reason = reason
        if source is not None:
            self.fault(t, source, reason, action or "")
        self.publish(self._stats(t))
        return self.report


class ControlLoop(CycleLoop):
    """One joint: its sample, its policy behind the safety net, its command."""

    def __init__(self, drive: Drive, policy: Policy, options: LoopOptions,
                 subscribers: Sequence[Subscriber] = (),
                 dropped: Callable[[], int] = lambda: 0, stop: threading.Event | None = None):
        super().__init__(options, subscribers, dropped, stop)
        self._drive = drive
        self.policy = policy
        self._net = SafetyNet(policy)
        self.latest: Sample | None = None  # the last sample the loop took
        self._statusword: int | None = None
        self._state: cia402.State | None = None
        self._safe: SafeCommand | None = None
        self._history = {key: [] for key in HISTORY_KEYS}
        if options.keep_history:
            self.report.history = self._history

    def _cycle(self) -> "float | LoopReport":
        drive, period = self._drive, self.options.period
        exchange = time.perf_counter()
        try:
            sample = drive.sync()
            self._exchange_time = time.perf_counter() - exchange
        except DriveError as exc:
            return self._finish(1, f"drive failed: {exc}", "drive",
                                "stopped commanding; drive disabled on exit",
                                self.time + period if self.latest else 0.0)
        self.latest, self._t = sample, sample.t
        for warning in drive.warnings():
            self.fault(sample.t, "drive", warning, "continuing: the command does not use it")
        if sample.statusword != self._statusword:
            self._statusword = sample.statusword
            self._state = cia402.state_from_statusword(sample.statusword)
        if self._state is not cia402.State.OPERATION_ENABLED:
            return self._finish(1, f"drive left operation enabled: {self._state.value}",
                                "drive", "stopped commanding; drive disabled on exit", sample.t)
        start = time.perf_counter()
        safe = self._safe = self._net.decide(sample)
        decide_time = self._mpc_time = time.perf_counter() - start
        try:
            drive.command_current(safe.current)
        except (CommandRangeError, DriveError) as exc:
            source = "controller" if isinstance(exc, CommandRangeError) else "drive"
            return self._finish(1, f"command refused: {exc}", source,
                                "stopped commanding; drive disabled on exit", sample.t)
        return decide_time

    def _published(self, decide_time: float) -> None:
        sample, safe = self.latest, self._safe
        t = sample.t
        publish = self.publish
        publish(messages.state(sample, self._state.value))
        publish(messages.command(t, safe, self._net.limits))
        publish(messages.solver_stats(t, safe, decide_time))
        if safe.fault is not None:
            self.report.fallbacks += 1
            self.fault(t, "controller", safe.fault,
                       f"commanded {safe.current:.3f} A (safe command)")
        if self.report.cycles % self.options.plan_every == 0:
            snapshot = self.policy.plan(t)
            if snapshot is not None:
                publish(messages.plan(snapshot))
        if self.options.keep_history:
            for key, value in zip(HISTORY_KEYS, (
                    t, sample.position, sample.velocity, safe.decision.reference_position,
                    safe.current, safe.decision.planned_current, sample.motor_current,
                    sample.joint_torque), strict=True):
                self._history[key].append(value)

    def _done(self) -> bool:
        return self._safe.decision.finished
