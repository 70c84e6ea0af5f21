"""The control loop: every joint of a robot in one cycle, one joint being a robot of one.

Each period: one group sync (one SYNC per CAN bus, one frame per EtherCAT line, every joint
sampled in the same cycle), the samples stacked into one table, the batch safety screen, one
call of the policy for every joint that passed (the batched MPC: one compiled call), the
batch check of each decision, one command per joint sent before the next sync, and the
cycle's telemetry. In real time the loop sleeps to each period's deadline before the sync; in
lock-step (virtual drives) it runs as fast as the drives answer, and time is the drives'.
Requests from outside (a new reference, new weights) are queued and applied at the start of a
cycle, so the policy never sees a half-made change. Every message goes to the subscribers as a
typed telemetry message (`controller.messages`), in this thread: a subscriber that does I/O
hands the message to its own thread. A subscriber that only sends bytes (a Zenoh publisher)
gets a one-joint cycle's messages and its plans as their wire bytes, without the messages.

A failure of any joint's drive ends the run: the caller quick-stops every drive
(`driver.drive_group.DriveGroup.quick_stop_all`), since the other joints' plans assumed that
one would move as planned.
"""

import collections
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple, Protocol

import numba
import numpy as np

from controller import messages
from controller import workspace as ws
from controller.ilqr import CONVERGED, MAX_ITERATIONS, STATUS_NAMES
from controller.messages import Subscriber, WireSubscriber
from controller.mpc import COLD, BatchMpc, Mpc
from controller.policy import PlanSnapshot, Policy
from controller.reference import reference_at
from controller.safety import NOT_FINITE, BatchSafety, SafetyNet
from driver import DriveError, Sample
from driver.clock import CycleClock, DriveClock, RingStats, WallClock
from driver.interface import (
    SAMPLE_POSITION,
    SAMPLE_STATUSWORD,
    SAMPLE_T,
    SAMPLE_VELOCITY,
    SampleLost,
)
from model.parameters import ActuatorParameters, Limits
from protocol import cia402

STALL_CYCLES = 10  # missed in a row: worth a message on the fault topic
MISSES_KEPT = 20_000  # times cycles were missed, kept for the report
# why a cycle missed its deadline: woken late by the host; the drive's sample late (the
# exchange, SYNC to the last TPDO or the frame's round trip) or lost (a frame that did not
# come back); the decision (safety and MPC) over the period; the telemetry's hand-off and the
# loop's own messages
LATE_WAKE_UP, LATE_SAMPLE, DECISION, PUBLISH = ("late wake-up", "late sample",
                                                "decision over budget", "publish back-pressure")
MISSED_CAUSES = (LATE_WAKE_UP, LATE_SAMPLE, DECISION, PUBLISH)
HISTORY_KEYS = ("t", "position", "velocity", "reference", "current", "planned_current",
                "motor_current", "joint_torque")
QUICK_STOPPED = "every joint quick-stopped, then disabled"  # what the caller does on failure
# by the solver's status code: its name, and whether its decision may go out
_STATUS_NAMES = np.array(STATUS_NAMES, dtype=object)
_USABLE = np.array([code in (CONVERGED, MAX_ITERATIONS) for code in range(len(STATUS_NAMES))])


@dataclass
class LoopOptions:
    period: float = 1e-3  # s
    # the wall clock in real time, drive time in lock-step (`driver.clock.clock_for`)
    clock: WallClock | DriveClock = field(default_factory=WallClock)
    duration: float | None = None  # s of drive time; None runs until stopped
    plan_every: int = 10  # cycles between Plan messages
    stats_every: float = 1.0  # s of drive time between LoopStats messages
    keep_history: bool = False  # for --plot


@dataclass
class LoopReport:
    cycles: int = 0
    fallbacks: int = 0
    cold_solve_us: float = math.nan
    # the drives' start around it (`driver.drive_group.BringUp`): configured, then enabled
    configure_us: float = math.nan
    enable_us: float = math.nan
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
    # s on the loop's clock (real time: `time.perf_counter`, the host's monotonic clock,
    # which other processes read too): the rhythm's first deadline and the run's end, the
    # span a host's stalls beside the run are counted over (`driver.host_floor`)
    cycles_from: float = math.nan
    cycles_to: float = math.nan
    # s on the host's performance counter over the same span, whatever the loop's clock: on
    # drive time (lock-step) what a cycle costs as a whole, drives, MPC, master and telemetry
    # together (`wall_per_cycle_us`), beside the MPC tick measured in the same run
    wall_from: float = math.nan
    wall_to: float = math.nan
    # (s on the loop's clock, cycles): each time cycles were found missed, the first
    # MISSES_KEPT times
    missed_at: list[tuple[float, int]] = field(default_factory=list)
    # cycles without a sample (a frame lost on the line, ridden through): among the missed,
    # as late samples
    lost_samples: int = 0

    @property
    def missed_cycles(self) -> int:
        return self.clock.missed_cycles if self.clock else 0

    @property
    def jitter(self) -> RingStats:
        return self.clock.jitter_us if self.clock else RingStats(1)

    @property
    def wall_per_cycle_us(self) -> float:
        """The wall time of a cycle after the first (NaN before a second cycle ran): on drive
        time the whole cycle's cost, on the wall clock the period kept."""
        if self.cycles < 2 or math.isnan(self.wall_to):
            return math.nan
        return (self.wall_to - self.wall_from) / (self.cycles - 1) * 1e6

    def summary(self) -> str:
        return (f"{self.cycles} cycles, {self.missed_cycles} missed, {self.fallbacks} safety "
                f"fallbacks; cold solve {self.cold_solve_us:.0f} us; period jitter p99 "
                f"{self.jitter.percentile(99):.1f} us, max {self.jitter.max:.1f} us; MPC tick "
                f"median {self.solve.percentile(50):.1f} us, p99 "
                f"{self.solve.percentile(99):.1f} us, max {self.solve.max:.1f} us; master "
                f"(MPC excluded) median {self.master.percentile(50):.1f} us, p99 "
                f"{self.master.percentile(99):.1f} us; wall time a cycle "
                f"{self.wall_per_cycle_us:.1f} us; missed by cause: "
                + ", ".join(f"{cause} {n}" for cause, n in self.missed_by_cause.items())
                + f" ({self.lost_samples} samples lost); {self.reason}")

    def figures(self) -> dict:
        """The run's figures as plain data (what `actuatord --report` writes as JSON): times
        in us, missed cycles in total and by cause."""
        def stats(ring: RingStats) -> dict:
            return {"median_us": ring.percentile(50), "p99_us": ring.percentile(99),
                    "max_us": ring.max}

        return {"cycles": self.cycles, "missed": self.missed_cycles,
                "missed_by_cause": dict(self.missed_by_cause),
                "lost_samples": self.lost_samples, "fallbacks": self.fallbacks,
                "cold_solve_us": self.cold_solve_us,
                # None: the group did not start (JSON has no NaN)
                "configure_us": None if math.isnan(self.configure_us) else self.configure_us,
                "enable_us": None if math.isnan(self.enable_us) else self.enable_us,
                "jitter": {"p99_us": self.jitter.percentile(99), "max_us": self.jitter.max},
                "mpc_tick": stats(self.solve), "master": stats(self.master),
                "wall_per_cycle_us": None if math.isnan(wall := self.wall_per_cycle_us)
                else wall,
                # None: the run ended before its rhythm began (JSON has no NaN)
                "cycles_from_s": None if math.isnan(self.cycles_from) else self.cycles_from,
                "cycles_to_s": None if math.isnan(self.cycles_to) else self.cycles_to,
                "missed_at_s": self.missed_at,
                "exit_code": self.exit_code, "reason": self.reason}

    def count_missed(self, phases: Sequence[float], cycles: int, at: float) -> None:
        """`cycles` missed, seen at `at` (s on the loop's clock), put down to the phase that
        took longest of the cycle behind them (`phases`: s per cause, in MISSED_CAUSES order),
        so a user can tell their machine from the service; when, so a bench can hold them
        against the host's own stalls (`driver.host_floor`)."""
        if cycles:
            longest = max(range(len(MISSED_CAUSES)), key=phases.__getitem__)
            self._count(MISSED_CAUSES[longest], cycles, at)

    def count_lost(self, at: float) -> None:
        """A cycle whose sample never came (seen at `at`, s on the loop's clock): missed, a
        late sample's."""
        self.lost_samples += 1
        self._count(LATE_SAMPLE, 1, at)

    def _count(self, cause: str, cycles: int, at: float) -> None:
        self.missed_by_cause[cause] += cycles
        if len(self.missed_at) < MISSES_KEPT:
            self.missed_at.append((at, cycles))


# The cycle's array work in two compiled calls whatever the number of joints: as numpy
# operations it took some 25 calls a cycle, each ~1 us of interpreter overhead on arrays of a
# few elements (a one-joint lock-step cycle went from 84 to 136 us of CPU against the scalar
# loop it replaced; see the commit).
@numba.njit(**ws.JIT)
def _screen(table, limits, believed):  # pragma: no cover - compiled
    """Per joint: is its drive in operation enabled, and is its state believable (written
    into `believed`; `BatchSafety.believed`'s rule on `limits`, its `screen_limits`; a NaN
    never is)? Returns the first joint whose drive is not enabled (-1: none) and whether
    every joint is believed."""
    everyone = True
    for j in range(table.shape[0]):
        statusword = np.int64(table[j, SAMPLE_STATUSWORD])
        if statusword & cia402.OPERATION_ENABLED_MASK != cia402.OPERATION_ENABLED_BITS:
            return j, everyone
        q, qd = table[j, SAMPLE_POSITION], table[j, SAMPLE_VELOCITY]
        ok = limits[0, j] <= q <= limits[1, j] and abs(qd) <= limits[2, j]
        believed[j] = ok
        everyone = everyone and ok
    return -1, everyone


@numba.njit(**ws.JIT)
def _check(header, ok, current_max, currents):  # pragma: no cover - compiled
    """Every joint's planned current clipped to its limit into `currents`; False when a
    joint's decision may not go out (failed, or not finite): the slow path then decides."""
    usable = True
    for j in range(header.shape[0]):
        planned = header[j, ws.PLANNED_CURRENT]
        if not (ok[j] and math.isfinite(planned)):
            usable = False
        limit = current_max[j]
        currents[j] = min(max(planned, -limit), limit)
    return usable


@numba.njit(**ws.JIT)
def _prepare(rows, table, believed):  # pragma: no cover - compiled
    """Each believed joint's measured state into its MPC row; True when one starts cold."""
    cold = False
    for j in range(rows.shape[0]):
        if believed[j]:
            rows[j, ws.POSITION] = table[j, SAMPLE_POSITION]
            rows[j, ws.VELOCITY] = table[j, SAMPLE_VELOCITY]
            cold = cold or rows[j, ws.MODE] == COLD
    return cold


@numba.njit(**ws.JIT)
def _decisions(rows, header, ok, current_max, currents):  # pragma: no cover - compiled
    """The rows' headers copied out (the next tick overwrites the rows) and, per joint,
    whether the solver's status lets its decision go out (`_USABLE`, a constant here); then
    `_check` on them, in the same call (a compiled call's dispatch costs ~0.4 us, as much as
    the work of both for one joint): True when every decision may go out."""
    header[:] = rows[:, :header.shape[1]]
    for j in range(rows.shape[0]):
        ok[j] = _USABLE[np.int64(rows[j, ws.STATUS])]
    return _check(header, ok, current_max, currents)


def _named(status: list[str] | None, header: np.ndarray) -> list[str]:
    """The status names of a cycle's decisions: the policy's own, or the solver's codes'."""
    if status is not None:
        return status
    return _STATUS_NAMES[header[:, ws.STATUS].astype(np.intp)].tolist()


class Joints(Protocol):
    """What the loop needs of the drives (`driver.drive_group.DriveGroup`)."""

    names: list[str]
    period: float  # s

    def sync(self) -> np.ndarray:
        """This cycle's samples, a row per joint (`driver.interface.SAMPLE_*` columns)."""

    def command_currents(self, currents: np.ndarray) -> None: ...

    def warnings(self) -> list[str]: ...

    def clock_trim(self) -> float:
        """s to move the next deadline by (0 unless a line keeps a clock of its own)."""


class Decided(NamedTuple):
    """What the policy decided for every joint this cycle."""

    header: np.ndarray  # (joints, ws.HEADER): the MPC rows' headers (the same columns for
    # another policy): planned current, reference, status code, iterations, cost
    ok: np.ndarray  # per joint: the policy succeeded (its planned current may go out)
    # per joint: the policy's own word for its decision; None: the solver's status, named by
    # the STATUS column (looked up only where a message or a fallback needs the name)
    status: list[str] | None
    finished: bool  # the policy's job is done (an experiment's trajectory is over)
    # per joint, the planned current clipped to the joint's limit (`_check`), and whether
    # every decision may go out as it is; None: the loop checks the header itself
    currents: np.ndarray | None = None
    usable: bool = False


class JointPolicies(Protocol):
    """What decides every joint's command: the batched MPC (`MpcJoints`) or one policy per
    joint (`PolicyJoints`, e.g. an experiment's tracking law)."""

    parameters: list[ActuatorParameters]  # per joint, payload included (for holding)
    limits: list[Limits]  # per joint: what the safety net enforces

    def decide(self, t: float, table: np.ndarray, believed: np.ndarray | None,
               safety: BatchSafety) -> Decided:
        """Decide for every `believed` joint of the samples `table` (None: every joint, as
        in every cycle but a rare one); the others were told to start afresh
        (`joint(j).reset()`) and are not asked."""

    def joint(self, index: int) -> Policy:
        """One joint as its safety net sees it (reference, reset, limits)."""

    def plan(self, index: int, t: float) -> PlanSnapshot | None: ...


class _BatchJoint:
    """One joint of the batched MPC as its safety net sees it: the net asks for the
    reference and tells the joint to start afresh; the batch is ticked by the loop, once."""

    def __init__(self, batch: BatchMpc, index: int):
        self._batch, self._index = batch, index
        joint = batch.joints[index]
        self.parameters = joint.parameters
        self.limits = joint.limits

    def reference_at(self, t: float) -> tuple[float, float]:
        q, qd = reference_at(self._batch.joints[self._index].reference_packed, t)
        return float(q), float(qd)

    def reset(self) -> None:
        self._batch.skip(self._batch.joints[self._index])


class MpcJoints:
    """The batched MPC as the loop's policy: every believed joint's state written into its
    row, one compiled call, the decisions read off the rows' headers as arrays."""

    def __init__(self, batch: BatchMpc):
        self.batch = batch
        self._joints = [_BatchJoint(batch, j) for j in range(len(batch))]
        self.parameters = [joint.parameters for joint in self._joints]
        self.limits = [joint.limits for joint in self._joints]
        self._buffers(len(batch), batch.rows.shape[1])
        # the cycle's kernels loaded now (compiled on a first run), on copies: see ControlLoop
        rows = batch.rows.copy()
        _prepare(rows, np.zeros((len(batch), len(Sample._fields))), ~self._everyone)
        _decisions(rows, self._header.copy(), self._ok.copy(), np.ones(len(batch)),
                   self._currents.copy())

    def decide(self, t: float, table: np.ndarray, believed: np.ndarray | None,
               safety: BatchSafety) -> Decided:
        batch = self.batch
        rows = batch.rows  # read each cycle: a new horizon rebuilds the batch
        count = len(rows)
        if len(self._header) != count or rows.shape[1] != self._width:
            self._buffers(count, rows.shape[1])
        # the others were set to skip this tick by their nets
        if _prepare(rows, table, self._everyone if believed is None else believed):
            # a cold start begins from the current that holds the joint
            cold = rows[:, ws.MODE] == COLD
            positions = table[:, SAMPLE_POSITION]
            rows[cold, ws.INITIAL_CURRENT] = safety.hold_currents(positions)[cold]
        batch.run(t)
        usable = _decisions(rows, self._header, self._ok, safety.current_max, self._currents)
        decided = self._decided
        if decided.usable != usable:
            decided = self._decided = decided._replace(usable=usable)
        return decided

    def _buffers(self, count: int, width: int) -> None:
        self._everyone = np.ones(count, dtype=bool)
        self._header = np.empty((count, ws.HEADER))
        self._ok = np.empty(count, dtype=bool)
        self._currents = np.empty(count)
        self._width = width
        # every cycle's decision: these buffers, written in place by `decide` (a new tuple
        # only when the check's outcome changes, which is rare)
        self._decided = Decided(self._header, self._ok, None, False, self._currents, True)

    def joint(self, index: int) -> _BatchJoint:
        return self._joints[index]

    def plan(self, index: int, t: float) -> PlanSnapshot:
        return self.batch.plan(self.batch.joints[index], t)


class PolicyJoints:
    """One `Policy` per joint (an experiment's tracking law, a test's holding law), each
    ticked with its joint's sample; their decisions in the MPC's header columns."""

    def __init__(self, policies: Sequence[Policy]):
        self.policies = list(policies)
        self.parameters = [policy.parameters for policy in self.policies]
        self.limits = [policy.limits for policy in self.policies]

    def decide(self, t: float, table: np.ndarray, believed: np.ndarray | None,
               safety: BatchSafety) -> Decided:
        count = len(self.policies)
        header = np.zeros((count, ws.HEADER))
        ok = np.zeros(count, dtype=bool)
        status = [NOT_FINITE] * count
        finished = False
        for j in range(count) if believed is None else np.flatnonzero(believed):
            row = table[j].tolist()
            decision = self.policies[j].tick(Sample(*row[:SAMPLE_STATUSWORD],
                                                    int(row[SAMPLE_STATUSWORD])))
            h = header[j]
            h[ws.PLANNED_CURRENT] = decision.planned_current
            h[ws.REFERENCE_POSITION] = decision.reference_position
            h[ws.REFERENCE_VELOCITY] = decision.reference_velocity
            h[ws.ITERATIONS] = decision.iterations
            h[ws.ROLLOUTS] = decision.rollouts
            h[ws.COST] = decision.cost
            ok[j], status[j] = decision.ok, decision.status
            finished = finished or decision.finished
        return Decided(header, ok, status, finished)

    def joint(self, index: int) -> Policy:
        return self.policies[index]

    def plan(self, index: int, t: float) -> PlanSnapshot | None:
        return self.policies[index].plan(t)


def joint_policies(policy: "JointPolicies | BatchMpc | Mpc | Policy | Sequence[Policy]"
                   ) -> JointPolicies:
    """What the loop asks for, from what callers have: the batched MPC (a robot's, or a
    single joint's `Mpc`, itself a batch of one), or one policy per joint."""
    if isinstance(policy, BatchMpc):
        return MpcJoints(policy)
    if isinstance(policy, Mpc):
        return MpcJoints(policy.batch)
    if isinstance(policy, MpcJoints | PolicyJoints):
        return policy
    if isinstance(policy, Sequence):
        return PolicyJoints(policy)
    return PolicyJoints([policy])


class ControlLoop:
    """The cycle works on arrays over the joints (the samples stacked into one table, the
    policy's decisions, the batch safety net): a handful of numpy operations a cycle whatever
    the number of joints, where a Python call per joint per field cost a millisecond for the
    whole TALOS. The per-joint nets remain for the rare joint the batch screens out, to name
    why.

    The rhythm: wait for the period's deadline (real time) or not (lock-step), report a
    stall, apply queued requests at the cycle start, run the cycle, time the decision (the
    first, cold one apart, after which the deadlines start), publish LoopStats every
    `stats_every` s of drive time, and end at the duration, when the policy is done, or when
    a drive fails.

    A robot of several joints publishes one `JointStates` message a cycle; a robot of one
    joint publishes that joint's own view (State, Command, SolverStats, a Plan every
    `plan_every` cycles), the topics dashboards and recordings of one joint read."""

    def __init__(self, joints: Joints, policy: "JointPolicies | BatchMpc | Mpc | Policy",
                 options: LoopOptions, subscribers: Sequence[Subscriber] = (),
                 dropped: Callable[[], int] = lambda: 0, stop: threading.Event | None = None,
                 settle: float = 0.0, take_turn: Callable[[], None] | None = None,
                 wire_subscribers: Sequence[WireSubscriber] = ()):
        """`wire_subscribers`: subscribers that send bytes (a Zenoh publisher), given a robot
        of one joint's view as one `messages.EncodedJointView` (its messages' wire bytes,
        without the messages), a robot's JointStates as `messages.Encoded`, and every other
        message as the others are. `dropped` counts
        the messages subscribers could not pass on (for LoopStats); `stop`,
        when given, is the caller's flag to end the run (a signal handler sets it); `settle`
        (s of drive time): tracking errors count from then on (the approach from where a
        joint rests to its reference is not tracking). `take_turn`: called after each cycle
        on a clock that does not run alone (drive time), where the loop never sleeps, to let
        a subscriber's thread work in turns with it
        (`controller.telemetry.TelemetryPublisher.take_turn`); never on the wall clock."""
        self.policy = policies = joint_policies(policy)
        self.names = list(joints.names)
        count = len(self.names)
        if len(policies.limits) != count:
            raise ValueError(f"{count} joints, {len(policies.limits)} policies")
        self.options = options
        self._view_subscribers = tuple(subscribers)  # the one-joint view as its messages
        self._wire_subscribers = tuple(wire_subscribers)  # ... as its bytes
        self._subscribers = self._view_subscribers + self._wire_subscribers  # every message
        self._take_turn = None if options.clock.runs_alone else take_turn
        self._dropped = dropped
        # appended by other threads, drained by the loop: deque's append and popleft are atomic
        self._requests: collections.deque[Callable[[], None]] = collections.deque()
        self._stop = stop if stop is not None else threading.Event()
        self.report = LoopReport()
        self._t: float | None = None  # drive time of the last sample (None before the first)
        self._mpc_time = 0.0  # s the last cycle spent in the policy's own call
        self._exchange_time = 0.0  # s the last cycle waited for its samples
        # cycles in a row without a sample (lost frames the line rides through): the fault
        # topic hears of a run of them twice, when it starts and when samples come back, not
        # once a cycle (a line whose frames stay lost rides through up to the drives' 100 ms)
        self._lost_in_a_row = 0
        self._joints = joints
        self._nets = [SafetyNet(policies.joint(j)) for j in range(count)]
        self._safety = BatchSafety(policies.parameters, policies.limits)
        self.failed_joint: str | None = None  # the joint whose failure ended the run
        # per joint: sum of squared tracking errors and their count (for tracking_rms)
        self._squared_error = np.zeros(count)
        self._tracked = 0
        self._settle = settle
        self.latest: np.ndarray | None = None  # the last cycle's samples, a row per joint
        # every drive's state while the loop runs (it ends when one leaves operation enabled)
        self._enabled_names = (cia402.State.OPERATION_ENABLED.value,) * count
        self._limits = policies.limits
        self._currents = np.zeros(count)  # what goes out this cycle (written in place)
        self._believed = np.zeros(count, dtype=bool)
        self._screen_limits = self._safety.screen_limits()
        self._decided: Decided | None = None
        # the jitter's and the solve's counts at the last LoopStats (set as a run starts)
        self._stats_counts = (0, 0)
        self._status: list[str] | None = None  # the cycle's status names (None: the codes')
        self._fallbacks: dict[int, str] = {}  # joint -> why the net overrode it this cycle
        self._published = self._joint_view if count == 1 else self._robot_view
        # the cycle's view to wire subscribers: a robot of one joint's three messages, or a
        # robot's one JointStates
        self._encode_view = (messages.JointViewEncoder(self._limits[0]) if count == 1
                             else messages.JointStatesEncoder(self.names, self._enabled_names))
        self._no_fallback = np.zeros(count, dtype=bool)
        self._history = {key: [] for key in HISTORY_KEYS}
        if options.keep_history:
            self.report.history = self._history
        self._load_kernels()

    def _load_kernels(self) -> None:
        """The cycle's compiled kernels loaded now, on scratch arrays of the cycle's types,
        not in the first cycle: on the first run after an install they compile (seconds), and
        a first cycle held that long left the drives without SYNC past their watchdog."""
        count = len(self.names)
        table = np.zeros((count, len(Sample._fields)))  # statusword 0: screened out at once
        _screen(table, self._screen_limits, np.zeros(count, dtype=bool))
        _check(np.zeros((count, ws.HEADER)), np.zeros(count, dtype=bool),
               self._safety.current_max, np.zeros(count))
        self._encode_view.load()

    def solve_first(self, table: np.ndarray) -> None:
        """Every joint's cold solve from its measured state (`table`, a row per joint, as a
        cycle's samples), given by `DriveGroup.start` before any drive is enabled: solved
        at drive time 0, one period before the first sample, so the first cycle starts warm
        and contiguous from it. In the first cycle instead, the 32 cold solves of TALOS held
        the cycle 14-20 ms while the drives were enabled, which the EtherCAT line's keeper
        had to cover and which put its distributed clocks off phase. Only the MPC has a cold
        solve; another policy decides from the first cycle on."""
        if not isinstance(self.policy, MpcJoints):
            return
        start = time.perf_counter()
        self.policy.decide(0.0, table, None, self._safety)
        self.report.cold_solve_us = (time.perf_counter() - start) * 1e6

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

    def tracking_rms(self) -> list[float]:
        """rad, each joint's RMS of position minus reference over the run (after `settle`)."""
        if not self._tracked:
            return [math.nan] * len(self.names)
        return [float(v) for v in np.sqrt(self._squared_error / self._tracked)]

    def run(self) -> LoopReport:
        """Run until stopped, the duration is reached, the policy is done or a drive fails.
        The caller owns the drives' life cycle (start before, close after: close always
        disables them; quick-stop every one first when the run failed)."""
        options, report = self.options, self.report
        clock = report.clock = CycleClock(options.period, options.clock)
        next_stats = options.stats_every
        self._stats_counts = (0, report.solve.count)  # the clock's jitter starts afresh
        missed = 0
        # the last cycle's phases (s, in MISSED_CAUSES order): a plain tuple, looked at only
        # when a cycle was missed (a dict a cycle cost more than the rest of this bookkeeping)
        behind = (0.0, 0.0, 0.0, 0.0)
        perf_counter, requests = time.perf_counter, self._requests
        solve, master, published_view = report.solve, report.master, self._published
        take_turn = self._take_turn
        # an EtherCAT line on distributed clocks leads the cycle's clock
        joints_clock_trim = self._joints.clock_trim
        while not self._stop.is_set():
            skipped = clock.wait(joints_clock_trim())
            if skipped:
                report.count_missed(behind, skipped, clock.clock.now())
                if clock.missed_cycles - missed >= STALL_CYCLES and self._t is not None:
                    self.fault(self._t, "controller",
                               f"loop stalled: {clock.missed_cycles - missed} cycles missed",
                               "continuing from the next sample")
            missed = clock.missed_cycles
            while requests:
                requests.popleft()()
            started = perf_counter()
            decide_time = self._cycle()
            if decide_time.__class__ is LoopReport:
                return decide_time
            if decide_time is None:  # no sample came back: nothing decided, nothing sent
                clock.miss()
                report.count_lost(clock.clock.now())
                continue
            master_time = perf_counter() - started - self._mpc_time
            if report.cycles:
                overrun = clock.check_overrun()
                if overrun:
                    report.count_missed((clock.wake_lateness, self._exchange_time, decide_time,
                                         0.0), overrun, clock.clock.now())
                solve.add(decide_time * 1e6)
                master.add(master_time * 1e6)
            else:
                # the first decision (the cold solve, unless `solve_first` did it) runs once
                # before the rhythm starts: timed on its own, and the deadlines begin after it
                if math.isnan(report.cold_solve_us):
                    report.cold_solve_us = decide_time * 1e6
                clock.restart()
                report.cycles_from = options.clock.now()
                report.wall_from = perf_counter()
            report.cycles += 1
            published = perf_counter()
            published_view(decide_time)
            t = self._t
            if t >= next_stats:
                next_stats += options.stats_every
                self.publish(self._stats(t))
            behind = (clock.wake_lateness, self._exchange_time, decide_time,
                      perf_counter() - published)
            if take_turn is not None:
                take_turn()
            if options.duration is not None and t >= options.duration - 1e-9:
                return self._finish(0, f"ran {options.duration} s", t=t)
            if self._decided.finished:
                return self._finish(0, "the policy finished", t=t)
        return self._finish(0, "stop requested", t=self.time)

    def _cycle(self) -> "float | LoopReport | None":
        """Sample, decide and command: the decision's wall time (s), the report when the run
        ends here, or None when no sample came back (a lost frame the line rides through:
        the drives hold their last command, said on the fault topic)."""
        joints, safety = self._joints, self._safety
        exchange = time.perf_counter()
        try:
            table = self.latest = joints.sync()
            self._exchange_time = time.perf_counter() - exchange
        except SampleLost as exc:
            self._lost_in_a_row += 1
            if self._lost_in_a_row == 1:
                self.fault(self.time + self.options.period, "drive", str(exc),
                           "cycle skipped: no decision, the drives hold their last command")
            return None
        except DriveError as exc:
            return self._fail(exc, self.time + self.options.period)
        t = self._t = float(table[0, SAMPLE_T])
        if self._lost_in_a_row:
            if self._lost_in_a_row > 1:
                self.fault(t, "drive", f"{self._lost_in_a_row} cycles in a row without a "
                           "sample", "samples back: continuing")
            self._lost_in_a_row = 0
        for warning in joints.warnings():
            self.fault(t, "drive", warning, "continuing: the command does not use it")
        believed = self._believed
        disabled, everyone = _screen(table, self._screen_limits, believed)
        if disabled >= 0:
            name, self.failed_joint = self.names[disabled], self.names[disabled]
            statusword = int(table[disabled, SAMPLE_STATUSWORD])
            state = cia402.state_from_statusword(statusword).value
            return self._finish(1, f"joint {name}: drive left operation enabled: {state}",
                                "drive", QUICK_STOPPED, t)
        start = time.perf_counter()
        fallbacks = self._fallbacks = {}
        if not everyone:  # rare: the per-joint nets say why, and hold those joints
            for j in np.flatnonzero(~believed):
                sample = Sample(*table[j, :SAMPLE_STATUSWORD], int(table[j, SAMPLE_STATUSWORD]))
                fallbacks[int(j)] = self._nets[j].screen(sample).fault
        mpc_start = time.perf_counter()
        decided = self._decided = self.policy.decide(t, table, None if everyone else believed,
                                                     safety)
        self._mpc_time = time.perf_counter() - mpc_start
        header, ok, status, _, checked, usable = decided
        if checked is None:  # a policy that leaves the check to the loop
            checked = self._currents
            usable = _check(header, ok, safety.current_max, checked)
        if usable and everyone:  # nearly always
            currents = self._currents = checked
            self._status = status
        else:
            positions, velocities = table[:, SAMPLE_POSITION], table[:, SAMPLE_VELOCITY]
            planned = header[:, ws.PLANNED_CURRENT]
            usable = ok & np.isfinite(planned)
            status = self._status = _named(status, header)
            currents = safety.checked_currents(positions, planned, usable)
            if fallbacks:  # a joint screened out: the net's command for it
                currents = np.where(believed, currents,
                                    safety.screened_currents(positions, velocities))
            for j in np.flatnonzero(believed & ~usable):
                fallbacks[int(j)] = f"solver {status[j]}: holding position"
            for j in fallbacks:
                if not believed[j]:  # decided by the net alone: no solver ran for it
                    status[j] = NOT_FINITE
                    h = header[j]
                    h[ws.PLANNED_CURRENT] = math.nan
                    h[ws.ITERATIONS] = h[ws.ROLLOUTS] = 0
                    h[ws.COST] = math.inf
                    h[ws.REFERENCE_POSITION], h[ws.REFERENCE_VELOCITY] = (
                        self._nets[j].policy.reference_at(t))
            currents = self._currents = np.array(currents)  # a buffer of the loop's own again
        decide_time = time.perf_counter() - start
        try:
            joints.command_currents(currents)
        except DriveError as exc:
            return self._fail(exc, t)
        return decide_time

    def _robot_view(self, decide_time: float) -> None:
        """A robot's cycle: one JointStates message with every joint; to wire subscribers as
        its bytes, encoded in one call (the message is built only for the others)."""
        t, table, header = self._t, self.latest, self._decided.header
        if self._fallbacks:
            fallback = np.zeros(len(self.names), dtype=bool)
            fallback[list(self._fallbacks)] = True
        else:
            fallback = self._no_fallback
        if self._wire_subscribers:
            encoded = self._encode_view(t, table, self._currents, header, self._status,
                                        fallback, decide_time)
            for subscriber in self._wire_subscribers:
                subscriber(encoded)
        if self._view_subscribers:
            message = messages.joint_states(t, self.names, table, self._enabled_names,
                                            self._currents, header,
                                            _named(self._status, header), fallback,
                                            decide_time)
            for subscriber in self._view_subscribers:
                subscriber(message)
        if self._fallbacks:
            self._fallback_faults(t)
        self._track(t, table, header)

    def _joint_view(self, decide_time: float) -> None:
        """A robot of one joint: the joint's own State, Command and SolverStats (and a Plan
        every `plan_every` cycles), the topics of a single-joint dashboard or recording; to
        wire subscribers as their bytes, encoded in one call (the messages are built only
        for the others)."""
        t, table, header = self._t, self.latest, self._decided.header
        status = (STATUS_NAMES[int(header[0, ws.STATUS])] if self._status is None
                  else self._status[0])
        fallback = 0 in self._fallbacks
        if self._wire_subscribers:
            encoded = self._encode_view(t, table, header, self._enabled_names[0],
                                        self._currents, status, fallback, decide_time)
            for subscriber in self._wire_subscribers:
                subscriber(encoded)
        if self._view_subscribers:
            view = messages.joint_view(t, table[0].tolist(), self._enabled_names[0],
                                       self._currents[0].item(), header[0].tolist(), status,
                                       fallback, self._limits[0], decide_time)
            subscribers = self._view_subscribers
            for message in view:  # `publish`'s loop, inline: three calls fewer a cycle
                for subscriber in subscribers:
                    subscriber(message)
        if self._fallbacks:
            self._fallback_faults(t)
        if self.report.cycles % self.options.plan_every == 0:
            snapshot = self.policy.plan(0, t)
            if snapshot is not None:
                data = messages.plan_bytes(snapshot)
                if self._wire_subscribers:
                    encoded = messages.Encoded(messages.Plan, t, data)
                    for subscriber in self._wire_subscribers:
                        subscriber(encoded)
                if self._view_subscribers:
                    plan = messages.Plan.FromString(data)
                    for subscriber in self._view_subscribers:
                        subscriber(plan)
        if t >= self._settle:  # `_track` for the one joint
            error = float(table[0, SAMPLE_POSITION] - header[0, ws.REFERENCE_POSITION])
            self._squared_error[0] += error * error
            self._tracked += 1
        if self.options.keep_history:
            sample, h = table[0].tolist(), header[0].tolist()
            for key, value in zip(HISTORY_KEYS, (
                    t, sample[SAMPLE_POSITION], sample[SAMPLE_VELOCITY],
                    h[ws.REFERENCE_POSITION], self._currents[0].item(),
                    h[ws.PLANNED_CURRENT], *sample[SAMPLE_VELOCITY + 1:SAMPLE_STATUSWORD]),
                    strict=True):
                self._history[key].append(value)

    def _fallback_faults(self, t: float) -> None:
        for j, why in self._fallbacks.items():
            self.report.fallbacks += 1
            self.fault(t, "controller", f"joint {self.names[j]}: {why}",
                       f"commanded {self._currents[j]:.3f} A (safe command)")

    def _track(self, t: float, table: np.ndarray, header: np.ndarray) -> None:
        if t >= self._settle:
            error = table[:, SAMPLE_POSITION] - header[:, ws.REFERENCE_POSITION]
            self._squared_error += error * error
            self._tracked += 1

    def _fail(self, exc: DriveError, t: float) -> LoopReport:
        self.failed_joint = getattr(exc, "joint", None)
        return self._finish(1, f"drive failed: {exc}", "drive", QUICK_STOPPED, t)

    def _stats(self, t: float, whole_run: bool = False):
        """LoopStats: percentiles over the cycles since the last LoopStats (what a dashboard
        plots as the last second's), or over the run (its last message, as the summary);
        maxima over the run. Over the run every second, the percentiles' sorting grew with
        the run to milliseconds in the cycle's time (see `RingStats.recent_percentiles`)."""
        report = self.report
        jitter, solve = report.jitter, report.solve
        if whole_run:
            jitter_p99 = jitter.percentile(99)
            solve_median, solve_p99 = solve.percentile(50), solve.percentile(99)
        else:
            jitter_since, solve_since = self._stats_counts
            (jitter_p99,) = jitter.recent_percentiles((99,), jitter.count - jitter_since)
            solve_median, solve_p99 = solve.recent_percentiles((50, 99),
                                                               solve.count - solve_since)
        self._stats_counts = jitter.count, solve.count
        return messages.loop_stats(t, report.cycles, report.missed_cycles, jitter_p99,
                                   jitter.max, solve_median, solve_p99, solve.max,
                                   self._dropped())

    def _finish(self, code: int, reason: str, source: str | None = None,
                action: str | None = None, t: float = 0.0) -> LoopReport:
        self.report.exit_code = code
        self.report.reason = reason
        self.report.cycles_to = self.options.clock.now()
        self.report.wall_to = time.perf_counter()
        if source is not None:
            self.fault(t, source, reason, action or "")
        self.publish(self._stats(t, whole_run=True))
        return self.report
