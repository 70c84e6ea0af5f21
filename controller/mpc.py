"""Receding-horizon use of the iLQR: warm start shifted by one step, the reference sampled over
the horizon, one (or a few) solver iterations per tick, for J independent joints in one
compiled call (one joint is J = 1: there is one path).

The warm-started tick is a real-time iteration: the previous solution, its linearisation and
its stage costs are shifted by one step (only the last stage is new), the backward pass runs on
them directly, and the forward pass from the measured state is the line search. The merit it
must beat is the shifted cost corrected to the measured state by the value function's quadratic
model, so the Armijo test stays meaningful. One simulation per tick instead of two.

Its work is bounded: at most WARM_TRIALS simulations (alpha = 1, 1/2, 1/4). When none passes
the Armijo test, the smallest step is taken all the same if it costs no more than
WARM_COST_RATIO times the merit: the trial is a trajectory simulated from the measured state
under the previous plan's feedback, and a merit a few per cent too optimistic is the quadratic
model's error, not a failed step (see controller.ilqr for the measured ratios); the next tick
improves on it. A step that costs more than that is a plan that diverged (a kick, the first
ticks after a cold solve): the joint solves anew from its controls, as an unbounded search
did. Why: on talos_32, whose 32 joints tick in four chunks of eight lanes, a tick lasts as
long as the sum of each chunk's longest search. With ten trials and every failed search
solving anew (up to 21 simulations a joint), its p99 was 26 rounds and 490-614 us in
lock-step (12 rounds and 320-380 us bounded), which with the master's exchange overran a 1 ms
cycle in real time.

Two compiled kernels tick a batch: `controller.lanes` puts the joints side by side in SIMD
lanes (the default), `tick_joints` below runs each joint's scalar iLQR in turn, in parallel
across cores (numba prange, one workspace row each; a single joint runs in the calling thread,
where waking a thread team would cost more than it saves). The scalar one is the reference the
lanes are tested against.
"""

import os
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from itertools import repeat

import numba
import numpy as np
from numba.np.unsafe.ndarray import to_fixed_tuple

from controller import lanes
from controller import workspace as ws
from controller.action_model import discrete_step, stage_cost
from controller.ilqr import (
    CONVERGED,
    MAX_ITERATIONS,
    MU_MIN,
    STATUS_NAMES,
    WARM_COST_RATIO,
    WARM_TRIALS,
    Outcome,
    backward,
    evaluate_terminal,
    iterate,
    line_search,
    solve_from_controls,
    store_stage,
)
from controller.policy import Decision, PlanSnapshot
from controller.problem import (
    C_DT,
    C_FRICTION_SHARPNESS,
    N_COST,
    OcpSettings,
    pack_cost,
    resolvable_friction_sharpness,
)
from controller.reference import Reference, Sinusoid, check_reference, reference_at
from controller.safety import holding_current
from controller.workspace import COLD, JIT, RESAMPLE, SKIP, WARM
from driver import Sample
from model.dynamics import N_PARAMS
from model.parameters import ActuatorModel, Payload

# The worker threads of a parallel tick sleep between ticks instead of spinning (unless the user
# chose otherwise). Spinning saves a wake-up of some microseconds on an idle machine, but on a
# busy one the spinners take the cores the other threads of the same tick need: measured here
# with other work running, 32 joints took 14 ms per tick spinning and 0.8 ms sleeping.
# Read once, when the OpenMP runtime starts: at the first parallel tick, not at import.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


@numba.njit(**JIT)
def _lane_plan(trajectories, gains, which, chunk, lane, order, out):  # pragma: no cover
    """One lane joint's plan in step order (`order`: the ring's slots) into `out`'s rows:
    position, velocity, current (its last point unused) and reference position. As numpy
    gathers (fancy indexing, then strided columns that `messages.plan` copied again) a plan
    took 9-15 us, every `plan_every` cycles in the loop's thread."""
    for k in range(order.shape[0]):
        slot = order[k]
        out[0, k] = trajectories[which, chunk, slot, lanes.Q, lane]
        out[1, k] = trajectories[which, chunk, slot, lanes.QD, lane]
        out[2, k] = trajectories[which, chunk, slot, lanes.U, lane]
        out[3, k] = gains[chunk, slot, lanes.REFERENCE_Q, lane]


@numba.njit(**JIT)
def _shift(cur, K, ref_q, ref_qd, p, c):
    """Advance the stored solution one step: everything moves up by one (in place, ascending,
    so no temporaries), the last control is repeated and only the last stage and the terminal
    state are evaluated anew."""
    X, U, A, B, LX, LXX, LU, LUU, LC = cur
    n = U.shape[0]
    for k in range(n):
        X[k, 0] = X[k + 1, 0]
        X[k, 1] = X[k + 1, 1]
        LX[k, 0] = LX[k + 1, 0]
        LX[k, 1] = LX[k + 1, 1]
        LXX[k, 0] = LXX[k + 1, 0]
        LXX[k, 1] = LXX[k + 1, 1]
        LC[k] = LC[k + 1]
    for k in range(n - 1):
        U[k] = U[k + 1]
        A[k, 0] = A[k + 1, 0]
        A[k, 1] = A[k + 1, 1]
        A[k, 2] = A[k + 1, 2]
        A[k, 3] = A[k + 1, 3]
        B[k, 0] = B[k + 1, 0]
        B[k, 1] = B[k + 1, 1]
        LU[k] = LU[k + 1]
        LUU[k] = LUU[k + 1]
        K[k, 0] = K[k + 1, 0]
        K[k, 1] = K[k + 1, 1]
    q, qd, u = X[n - 1, 0], X[n - 1, 1], U[n - 2]
    step = discrete_step(q, qd, u, p, c)
    store_stage(cur, n - 1, q, qd, u, step, stage_cost(q, qd, u, ref_q[n - 1], ref_qd[n - 1], c))
    evaluate_terminal(step.q, step.qd, cur, ref_q, ref_qd, c)


@numba.njit(**JIT)
def _tick_warm(q0, qd0, w, p, c, max_iterations, tolerance):
    """Real-time iteration from the shifted previous solution (see the module docstring)."""
    cur, trial = w.current, w.trial
    _shift(cur, w.K, w.reference_position, w.reference_velocity, p, c)
    sweep = backward(cur, MU_MIN, w.K, w.kff, c)
    rollouts = 0
    if sweep.ok:
        d1, d2 = q0 - cur.X[0, 0], qd0 - cur.X[0, 1]
        shifted_cost = 0.0
        for cost in cur.LC:
            shifted_cost += cost
        merit = shifted_cost + sweep.vx1 * d1 + sweep.vx2 * d2 + 0.5 * (
            sweep.v11 * d1 * d1 + 2.0 * sweep.v12 * d1 * d2 + sweep.v22 * d2 * d2)
        accepted, new_cost, rollouts = line_search(
            q0, qd0, cur, trial, w.K, w.kff, sweep.dv1, sweep.dv2, merit, w.reference_position,
            w.reference_velocity, p, c, WARM_TRIALS)
        if accepted or new_cost <= WARM_COST_RATIO * merit:  # see the module docstring
            if max_iterations == 1:
                return Outcome(MAX_ITERATIONS, 1, new_cost, MU_MIN, rollouts, True)
            more = iterate(q0, qd0, trial, cur, w.K, w.kff, new_cost, w.reference_position,
                           w.reference_velocity, p, c, max_iterations - 1, tolerance)
            return Outcome(more.status, more.iterations + 1, more.cost, more.mu,
                           rollouts + more.rollouts, not more.flipped)
    fresh = solve_from_controls(q0, qd0, cur, trial, w.K, w.kff, w.reference_position,
                                w.reference_velocity, p, c, max_iterations, tolerance)
    return Outcome(fresh.status, fresh.iterations, fresh.cost, fresh.mu,
                   fresh.rollouts + rollouts, fresh.flipped)


@numba.njit(**JIT)
def tick_joint(row, t0, n):
    """One joint's MPC step, inputs and outputs in its row (controller.workspace). Mode COLD:
    solve from a constant initial current. WARM: if t0 is exactly one step after the previous
    tick, a real-time iteration on the shifted solution; otherwise (a missed cycle) the shifted
    controls are re-simulated and iterated. RESAMPLE: the reference or the weights changed, so
    the reference is sampled anew before doing the latter. SKIP: nothing this time, cold next.
    The next tick's mode is left in the row: WARM after a usable solution, COLD otherwise."""
    mode = row[ws.MODE]
    if mode == SKIP:
        row[ws.MODE] = COLD
        return
    w = ws.views(row, n)
    # the parameters and the cost vector as tuples: values the compiler keeps in registers,
    # with no reference counting in each nested call and no aliasing with the trajectories
    p = to_fixed_tuple(row[ws.PARAMETERS:ws.COST_VECTOR], N_PARAMS)
    c = to_fixed_tuple(row[ws.COST_VECTOR:ws.TRAJECTORIES], N_COST)
    reference = row[ws.REFERENCE:ws.REFERENCE + 4]
    q0, qd0 = row[ws.POSITION], row[ws.VELOCITY]
    max_iterations = int(row[ws.COLD_ITERATIONS] if mode == COLD else row[ws.WARM_ITERATIONS])
    tolerance = row[ws.TOLERANCE]
    ref_q, ref_qd = w.reference_position, w.reference_velocity
    dt = c[C_DT]
    contiguous = abs(t0 - row[ws.LAST_T0] - dt) < 1e-6 * dt
    row[ws.LAST_T0] = t0
    if mode == WARM and contiguous:
        for k in range(n):
            ref_q[k] = ref_q[k + 1]
            ref_qd[k] = ref_qd[k + 1]
        ref_q[n], ref_qd[n] = reference_at(reference, t0 + n * dt)
        outcome = _tick_warm(q0, qd0, w, p, c, max_iterations, tolerance)
    else:
        for k in range(n + 1):
            ref_q[k], ref_qd[k] = reference_at(reference, t0 + k * dt)
        U = w.current.U
        if mode == COLD:
            U[:] = row[ws.INITIAL_CURRENT]
        else:
            for k in range(n - 1):
                U[k] = U[k + 1]
        outcome = solve_from_controls(q0, qd0, w.current, w.trial, w.K, w.kff, ref_q, ref_qd, p,
                                      c, max_iterations, tolerance)
    row[ws.STATUS] = outcome.status
    row[ws.ITERATIONS] = outcome.iterations
    row[ws.COST] = outcome.cost
    row[ws.MU] = outcome.mu
    row[ws.ROLLOUTS] = outcome.rollouts
    if outcome.flipped:
        row[ws.SECOND_IS_CURRENT] = 1.0 - row[ws.SECOND_IS_CURRENT]
    planned = (w.trial.U if outcome.flipped else w.current.U)[0]
    row[ws.PLANNED_CURRENT] = planned
    row[ws.REFERENCE_POSITION] = ref_q[0]
    row[ws.REFERENCE_VELOCITY] = ref_qd[0]
    usable = outcome.status == CONVERGED or outcome.status == MAX_ITERATIONS
    row[ws.MODE] = WARM if usable and np.isfinite(planned) else COLD


@numba.njit(parallel=True, **JIT)
def tick_joints(rows, t0, n):
    """Every joint's MPC step at time t0: one compiled call for the whole robot."""
    if rows.shape[0] == 1:
        tick_joint(rows[0], t0, n)
        return
    for j in numba.prange(rows.shape[0]):
        tick_joint(rows[j], t0, n)


@dataclass(frozen=True)
class JointProblem:
    """One joint's optimal control problem: its model, solver settings, payload, reference."""

    model: ActuatorModel
    settings: OcpSettings = field(default_factory=OcpSettings)
    payload: Payload = field(default_factory=Payload)
    reference: Reference = field(default_factory=Sinusoid)

    @property
    def friction_sharpness_solved(self) -> float:
        """The beta of tanh(beta qd) the solver will use for this joint (see
        `JointRow.friction_sharpness_solved`), for reports made before the batch exists."""
        parameters = self.model.parameters.with_payload(self.payload).packed()
        return resolvable_friction_sharpness(self.settings, parameters)


class JointRow:
    """Python's side of one joint's workspace row: its problem and named views into the row
    (the row itself holds the mode of its next tick)."""

    def __init__(self, problem: JointProblem, row: np.ndarray, n: int):
        self.problem = problem
        self.row = row
        self.parameters = problem.model.parameters.with_payload(problem.payload)
        self.packed_parameters = self.parameters.packed()
        self.limits = problem.model.limits
        self.trajectories = ws.trajectories(row, n)
        w = ws.views(row, n)
        self.reference_position, self.reference_velocity = (w.reference_position,
                                                            w.reference_velocity)
        row[ws.MODE] = COLD
        row[ws.PARAMETERS:ws.COST_VECTOR] = self.packed_parameters
        self.set_settings(problem.settings)
        self.set_reference(problem.reference)

    @property
    def mode(self) -> int:
        return int(self.row[ws.MODE])

    @property
    def friction_sharpness_solved(self) -> float:
        """The beta of tanh(beta qd) the solver uses: the settings' one, or the sharpest
        this step resolves (`controller.problem.resolvable_friction_sharpness`)."""
        return float(self.row[ws.COST_VECTOR + C_FRICTION_SHARPNESS])

    def start_cold(self) -> None:
        self.row[ws.MODE] = COLD

    def _resample(self) -> None:
        if self.row[ws.MODE] == WARM:
            self.row[ws.MODE] = RESAMPLE  # the stored reference or derivatives are stale

    def set_settings(self, settings: OcpSettings) -> None:
        self.settings = settings
        row = self.row
        row[ws.COST_VECTOR:ws.TRAJECTORIES] = pack_cost(settings, self.limits,
                                                        self.packed_parameters)
        row[ws.TOLERANCE] = settings.tolerance
        row[ws.COLD_ITERATIONS] = settings.max_iterations
        row[ws.WARM_ITERATIONS] = settings.tick_iterations
        self._resample()

    def set_reference(self, reference: Reference) -> None:
        check_reference(reference, self.limits)
        self.reference = reference
        self.reference_packed = reference.packed()
        self.row[ws.REFERENCE:ws.REFERENCE + 4] = self.reference_packed
        self._resample()

    def hold_current(self, position: float) -> float:
        return holding_current(position, self.parameters, self.packed_parameters,
                               self.limits.current_max)

    def solution(self) -> "ws.Trajectory":
        return self.trajectories[int(self.row[ws.SECOND_IS_CURRENT])]


def _decision(header: list[float]) -> Decision:
    """A joint's decision from its row's header (as a list: one conversion for all fields)."""
    status = int(header[ws.STATUS])
    return Decision(header[ws.PLANNED_CURRENT], header[ws.REFERENCE_POSITION],
                    header[ws.REFERENCE_VELOCITY], STATUS_NAMES[status],
                    status == CONVERGED or status == MAX_ITERATIONS, int(header[ws.ITERATIONS]),
                    int(header[ws.ROLLOUTS]), header[ws.COST])


USABLE = tuple(code in (CONVERGED, MAX_ITERATIONS) for code in range(len(STATUS_NAMES)))


def _decisions(rows: np.ndarray) -> list[Decision]:
    """Every joint's decision from the rows, as `_decision` builds one, a column at a time:
    half the Python time of one call per joint (30 us of a 32-joint tick of ~100 us)."""
    status = rows[:, ws.STATUS].astype(np.int64).tolist()
    return list(map(Decision._make, zip(
        rows[:, ws.PLANNED_CURRENT].tolist(), rows[:, ws.REFERENCE_POSITION].tolist(),
        rows[:, ws.REFERENCE_VELOCITY].tolist(), map(STATUS_NAMES.__getitem__, status),
        map(USABLE.__getitem__, status), rows[:, ws.ITERATIONS].astype(np.int64).tolist(),
        rows[:, ws.ROLLOUTS].astype(np.int64).tolist(), rows[:, ws.COST].tolist(),
        repeat(False))))


KERNELS = ("lanes", "scalar")


class BatchMpc:
    """The paper's controller for J independent joints (the paper's independent joint models),
    ticked together. All joints share the horizon length (one row width).

    Two compiled kernels tick the batch with the same decisions (to rounding): "lanes" puts the
    joints side by side in SIMD lanes (controller.lanes), "scalar" runs each joint's scalar
    iLQR in turn (tick_joint, the reference). The default is "lanes", with the extra effects'
    terms computed when a joint's model switches one on. `threads` splits the lanes
    among that many threads, each taking the next untaken chunk of lanes (default
    `lanes.default_threads()`); the scalar kernel uses numba's thread count, as before."""

    def __init__(self, problems: Sequence[JointProblem], kernel: str | None = None,
                 threads: int | None = None):
        if not problems:
            raise ValueError("a batch needs at least one joint")
        horizons = {problem.settings.horizon for problem in problems}
        if len(horizons) != 1:
            raise ValueError(f"every joint needs the same horizon, got {sorted(horizons)}")
        if kernel is not None and kernel not in KERNELS:
            raise ValueError(f"kernel must be one of {KERNELS}, got {kernel!r}")
        if threads is not None and threads < 1:
            raise ValueError(f"threads must be >= 1, got {threads}")
        self._kernel_asked = kernel
        self.threads = lanes.default_threads() if threads is None else threads
        self._build(list(problems))

    def _build(self, problems: list[JointProblem]) -> None:
        n = problems[0].settings.horizon
        self.horizon = n
        self.rows = np.zeros((len(problems), ws.row_size(n)))
        self.joints = [JointRow(problem, self.rows[j], n) for j, problem in enumerate(problems)]
        # one joint with an extra effect puts the batch on the lane kernel that computes them
        effects = any(lanes.has_effects(joint.packed_parameters) for joint in self.joints)
        self.kernel = self._kernel_asked or "lanes"
        self._lanes = lanes.allocate(len(problems), n)
        steps = np.arange(n + 1)
        self._ring_orders = (steps[None, :] + steps[:, None]) % (n + 1)  # [ring] -> slots
        self._tick_lanes = lanes.tick_kernel(len(problems), effects, self.threads)
        # load the compiled code now, not in the first control cycle: one iteration each
        for joint in self.joints:
            joint.row[ws.COLD_ITERATIONS] = 1
            self.prepare(joint, 0.5 * (joint.limits.position_min + joint.limits.position_max),
                         0.0)
        self.run(0.0)
        self.plan(self.joints[0], 0.0)  # the plan's kernel too (the loop's first cycle plans)
        for joint in self.joints:
            joint.set_settings(joint.settings)
            joint.start_cold()

    def __len__(self) -> int:
        return len(self.joints)

    def lane_threads(self) -> int:
        """How many threads tick the lanes kernel's chunks (0 for the scalar kernel): at most one
        per chunk, so one for fewer than 9 joints whatever `threads` says."""
        if self.kernel != "lanes":
            return 0
        return min(self.threads, lanes.chunks(len(self.joints)))

    def prepare(self, joint: JointRow, position: float, velocity: float) -> None:
        """Write one joint's measured state for the next tick; a cold start begins from the
        current that holds the joint where it is."""
        row = joint.row
        row[ws.POSITION] = position
        row[ws.VELOCITY] = velocity
        if row[ws.MODE] == COLD:
            row[ws.INITIAL_CURRENT] = joint.hold_current(position)

    def skip(self, joint: JointRow) -> None:
        """Leave this joint out of the next tick; it starts cold after."""
        joint.row[ws.MODE] = SKIP

    def run(self, t: float) -> None:
        """Tick every joint at time t (one compiled call)."""
        if self.kernel == "lanes":
            self._tick_lanes(self.rows, *self._lanes, t, self.horizon, self.threads)
        else:
            tick_joints(self.rows, t, self.horizon)

    def decision(self, joint: JointRow) -> Decision:
        """What the last tick decided for this joint."""
        return _decision(joint.row[:ws.HEADER].tolist())

    def tick(self, t: float, positions: Sequence[float], velocities: Sequence[float]
             ) -> list[Decision]:
        """Every joint from its measured state at time t (array writes, whatever J)."""
        rows = self.rows
        rows[:, ws.POSITION] = positions
        rows[:, ws.VELOCITY] = velocities
        for j in np.flatnonzero(rows[:, ws.MODE] == COLD):
            joint = self.joints[j]
            rows[j, ws.INITIAL_CURRENT] = joint.hold_current(rows[j, ws.POSITION])
        self.run(t)
        return _decisions(rows)

    def plan(self, joint: JointRow, t: float) -> PlanSnapshot:
        if self.kernel == "lanes":
            j = self.joints.index(joint)
            trajectories, gains, _, _, current, _ = self._lanes
            chunk, lane = divmod(j, lanes.width(len(self.joints)))
            which, ring = current[chunk, lanes.WHICH], current[chunk, lanes.RING]
            # the steps in order from the ring, with the step order of each ring position
            # made once (np.roll took 22 us a plan)
            order = self._ring_orders[int(ring)]
            # one new buffer a snapshot (a snapshot is a copy), each array one of its rows
            out = np.empty((4, len(order)))
            _lane_plan(trajectories, gains, int(which), chunk, lane, order, out)
            return PlanSnapshot(t, joint.settings.dt, out[0], out[1], out[2, :-1], out[3])
        solution = joint.solution()
        return PlanSnapshot(t, joint.settings.dt, solution.X[:, 0].copy(),
                            solution.X[:, 1].copy(), solution.U.copy(),
                            joint.reference_position.copy())

    def set_settings(self, joint: JointRow, settings: OcpSettings) -> None:
        """New weights, sharpness or dt for one joint; a new horizon rebuilds the batch (every
        joint's horizon changes with it, all start cold)."""
        if settings.horizon != self.horizon:
            problems = [JointProblem(j.problem.model, replace(j.settings, horizon=settings.horizon),
                                     j.problem.payload, j.reference) for j in self.joints]
            index = self.joints.index(joint)
            problems[index] = JointProblem(joint.problem.model, settings, joint.problem.payload,
                                           joint.reference)
            self._build(problems)
            return
        dt_changed = settings.dt != joint.settings.dt
        joint.set_settings(settings)
        if dt_changed:
            joint.start_cold()


class Mpc:
    """The paper's controller on one joint, as a policy of the control loop: iLQR with
    exponential barriers, run at every control period (a batch of one)."""

    def __init__(self, model: ActuatorModel, settings: OcpSettings = OcpSettings(),
                 payload: Payload = Payload(), reference: Reference = Sinusoid(),
                 kernel: str | None = None):
        self.model = model
        self.payload = payload
        self.batch = BatchMpc([JointProblem(model, settings, payload, reference)], kernel, 1)
        self._joint = self.batch.joints[0]
        self.parameters = self._joint.parameters
        self.limits = model.limits

    @property
    def settings(self) -> OcpSettings:
        return self._joint.settings

    @property
    def reference(self) -> Reference:
        return self._joint.reference

    @property
    def dynamics_parameters(self) -> np.ndarray:
        """The packed parameters the solver predicts with (model.dynamics layout)."""
        return self._joint.packed_parameters

    def set_reference(self, reference: Reference) -> None:
        self._joint.set_reference(reference)

    def set_settings(self, settings: OcpSettings) -> None:
        self.batch.set_settings(self._joint, settings)
        self._joint = self.batch.joints[0]

    def tick(self, sample: Sample) -> Decision:
        batch, joint = self.batch, self._joint
        batch.prepare(joint, sample.position, sample.velocity)
        batch.run(sample.t)
        return batch.decision(joint)

    def solve(self, position: float, velocity: float, t: float, initial_current: float,
              max_iterations: int) -> Decision:
        """A cold solve from a constant initial current (what the first tick does with the
        holding current); the next tick starts warm from it if it succeeded."""
        joint = self._joint
        joint.start_cold()
        self.batch.prepare(joint, position, velocity)
        joint.row[ws.INITIAL_CURRENT] = initial_current
        joint.row[ws.COLD_ITERATIONS] = max_iterations
        self.batch.run(t)
        joint.set_settings(joint.settings)  # the settings' iterations back
        return self.batch.decision(joint)

    def reference_at(self, t: float) -> tuple[float, float]:
        q_ref, qd_ref = reference_at(self._joint.reference_packed, t)
        return float(q_ref), float(qd_ref)

    def reset(self) -> None:
        self._joint.start_cold()

    def plan(self, t: float) -> PlanSnapshot:
        return self.batch.plan(self._joint, t)
