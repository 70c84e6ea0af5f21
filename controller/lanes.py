"""The batched MPC tick with the joints side by side in SIMD lanes: the same iLQR as
`controller.ilqr` and `controller.mpc.tick_joint` (read those first), with every innermost loop
running over joints so that LLVM vectorises the backward pass, the forward simulation and the
barrier terms across them (AVX2/FMA, or AVX-512 where the CPU has it).

Layout: a joint-major structure of arrays, `lanes[field, k, j]` for step k of joint j, so the
values of one step for consecutive joints are contiguous. Per-joint scalars (the parameters,
the cost vector, the solver's state) live in `scratch[row, j]` the same way. The tick's inputs
and outputs stay in the joints' workspace rows (`controller.workspace` header), so Python's side
of the batch does not change; the trajectories of a lane batch live only here.

Control flow: every joint keeps its own iLQR. A joint is in a phase (needs a backward pass, a
first simulation, a line-search trial, or is done) and the tick runs rounds of one masked
backward pass and one forward simulation over all joints until every joint is done. Each joint
thus goes through exactly the sequence of passes and decisions it goes through alone in
`tick_joint`: its own modes (cold, warm, resample, skip), regularisation, and line search that
accepts or rejects its own step. A simulation writes every lane of the trial trajectory; the
joints that accept it take it as their current solution (the two trajectories swap roles when
every joint of the block takes it, as in the scalar solver; otherwise the takers' lanes are
copied), and the trial lanes of the others are scratch.

The transcendental functions are `controller.lane_math` (the scalar kernel's are libm's), so a
lane joint's decisions equal the scalar kernel's to rounding, not bit for bit (tested to 1e-9
relative in tests/test_batch_lanes.py). The cost algebra and the discrete step are shared with
the scalar kernel (`controller.cost`, `controller.action_model`); the acceleration is the
paper's joint model of `model.dynamics.smooth_acceleration` written out for lanes, so a batch
whose joints carry an extra effect (`model.effects`) runs the scalar kernel instead
(`supports`).

Threads: the joints are split in contiguous blocks, one per thread of a numba prange; each
block runs the whole tick on its own lanes. One block is the default where the machine has two
cores or fewer (see `default_threads`).
"""

import os

import numba
import numpy as np
from numba.np.unsafe.ndarray import to_fixed_tuple

from controller import workspace as ws
from controller.action_model import stage_cost_given, step_given, terminal_cost_given
from controller.cost import control_box
from controller.ilqr import (
    ARMIJO,
    CONVERGED,
    LINE_SEARCH_FAILED,
    LINE_SEARCH_STEPS,
    MAX_ITERATIONS,
    MU_MAX,
    MU_MIN,
    NOT_FINITE,
)
from controller.lane_math import exp, sin_cos, tanh
from controller.problem import (
    C_ALPHA_POSITION,
    C_ALPHA_TORQUE,
    C_ALPHA_VELOCITY,
    C_DRIVE_GAIN,
    C_DT,
    C_FRICTION_SHARPNESS,
    N_COST,
)
from controller.reference import reference_at
from controller.workspace import JIT
from model.dynamics import (
    EFFECT_OFFSET,
    N_PARAMS,
    P_DRIVE_GAIN,
    P_DRY,
    P_GRAVITY_MX,
    P_GRAVITY_MY,
    P_INERTIA,
    P_LINK_INERTIA,
    P_OFFSET,
    P_VISCOUS,
)

COLD, WARM, RESAMPLE, SKIP = 0, 1, 2, 3  # tick modes, as controller.mpc

# fields of lanes[field, k, j]: two trajectories of TRAJECTORY_FIELDS each, then the rest
Q, QD, U, A11, A12, A21, A22, B1, B2, LQ, LQD, LQQ, LQDQD, LU, LUU, LC = range(16)
TRAJECTORY_FIELDS = 16
K1 = 2 * TRAJECTORY_FIELDS  # feedback gains on q and qd
K2 = K1 + 1
KFF = K1 + 2  # feed-forward steps
REFERENCE_Q = K1 + 3  # q* over the horizon
REFERENCE_QD = K1 + 4  # qd* over the horizon
FIELDS = K1 + 5

# rows of scratch[row, j]: the dynamics parameters, the cost vector, then the solver's state
PARAMETERS = 0
COSTS = N_PARAMS
(Q0, QD0, BOX, TOLERANCE, MU, COST, MERIT, DV1, DV2, ALPHA, VX1, VX2, V11, V12, V22, SWEEP_OK,
 TOTAL, NEEDS_SWEEP, TAKES, SHIFTS, SUM) = range(COSTS + N_COST, COSTS + N_COST + 21)
SCRATCH = COSTS + N_COST + 21

# phases of a joint within a tick
DONE, WARM_SWEEP, FIRST_ROLLOUT, SWEEP, SEARCH = range(5)
# per-joint integer state, state[row, j]
(PHASE, ATTEMPT, ITERATION, MAX_ITER, AFTER_WARM, STATUS_, ITERATION_OFFSET,
 ROLLOUTS_OFFSET, ROLLOUTS_) = range(9)
STATE = 9


def supports(packed_parameters: np.ndarray) -> bool:
    """Whether a joint's model is one the lanes compute: the paper's model, no extra effect
    switched on (their terms are the scalar kernel's alone)."""
    first = min(EFFECT_OFFSET.values(), default=P_LINK_INERTIA)
    return not np.any(packed_parameters[first:P_LINK_INERTIA])


def default_threads() -> int:
    """One thread on a machine with two cores or fewer, else two. Measured here (bench, two
    cores shared): a second thread saves at most what one block's tick takes minus the wake-up
    of the thread team, and costs that team's wake-up and the cache traffic of two cores on one
    workspace; on a robot PC with two cores the second belongs to the bus and the telemetry."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return 1 if (cores or 1) <= 2 else 2


def allocate(joints: int, n: int, blocks: int) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                         np.ndarray]:
    """The lane workspace of a batch: (lanes, scratch, state, current) where current[b] says
    which trajectory is the current one in block b."""
    return (np.zeros((FIELDS, n + 1, joints)), np.zeros((SCRATCH, joints)),
            np.zeros((STATE, joints), dtype=np.int64), np.zeros(max(blocks, 1), dtype=np.int64))


@numba.njit(**JIT)
def _acceleration(q, qd, u, S, j):
    """`model.dynamics.smooth_acceleration` for a joint without extra effects, with the lane
    maths: qdd and its partial derivatives in q, qd and u."""
    th = tanh(S[COSTS + C_FRICTION_SHARPNESS, j] * qd)
    inv_inertia = 1.0 / S[PARAMETERS + P_INERTIA, j]
    sin_q, cos_q = sin_cos(q)
    my, mx = S[PARAMETERS + P_GRAVITY_MY, j], S[PARAMETERS + P_GRAVITY_MX, j]
    gravity = my * sin_q + mx * cos_q
    d_gravity = my * cos_q - mx * sin_q
    level = S[PARAMETERS + P_DRY, j]
    viscous = S[PARAMETERS + P_VISCOUS, j]
    gain = S[PARAMETERS + P_DRIVE_GAIN, j]
    torque = gain * u - viscous * qd - level * th - S[PARAMETERS + P_OFFSET, j] - gravity
    d_friction = viscous + level * S[COSTS + C_FRICTION_SHARPNESS, j] * (1.0 - th * th)
    return (torque * inv_inertia, -d_gravity * inv_inertia, -d_friction * inv_inertia,
            gain * inv_inertia)


@numba.njit(**JIT)
def _store_stage(L, o, k, j, q, qd, u, S, c):
    """Step k of lane j into the trajectory at field offset o: state, control, linearisation
    and cost derivatives (controller.ilqr.store_stage). Returns the stage cost and x+."""
    a, a_q, a_qd, a_u = _acceleration(q, qd, u, S, j)
    step = step_given(q, qd, c[C_DT], a, a_q, a_qd, a_u)
    cost = stage_cost_given(q, qd, u, L[REFERENCE_Q, k, j], L[REFERENCE_QD, k, j], c,
                            exp(c[C_ALPHA_POSITION] * q), exp(c[C_ALPHA_VELOCITY] * qd),
                            exp(c[C_ALPHA_TORQUE] * (c[C_DRIVE_GAIN] * u)))
    L[o + Q, k, j] = q
    L[o + QD, k, j] = qd
    L[o + U, k, j] = u
    L[o + LQ, k, j] = cost.l_q
    L[o + LQD, k, j] = cost.l_qd
    L[o + LQQ, k, j] = cost.l_qq
    L[o + LQDQD, k, j] = cost.l_qdqd
    L[o + LU, k, j] = cost.l_u
    L[o + LUU, k, j] = cost.l_uu
    L[o + LC, k, j] = cost.l
    L[o + A11, k, j] = step.a11
    L[o + A12, k, j] = step.a12
    L[o + A21, k, j] = step.a21
    L[o + A22, k, j] = step.a22
    L[o + B1, k, j] = step.b1
    L[o + B2, k, j] = step.b2
    return cost.l, step.q, step.qd


@numba.njit(**JIT)
def _store_terminal(L, o, n, j, q, qd, c):
    """The terminal state and its cost derivatives; returns the terminal cost."""
    cost = terminal_cost_given(q, qd, L[REFERENCE_Q, n, j], L[REFERENCE_QD, n, j], c,
                               exp(c[C_ALPHA_POSITION] * q), exp(c[C_ALPHA_VELOCITY] * qd))
    L[o + Q, n, j] = q
    L[o + QD, n, j] = qd
    L[o + LQ, n, j] = cost.l_q
    L[o + LQD, n, j] = cost.l_qd
    L[o + LQQ, n, j] = cost.l_qq
    L[o + LQDQD, n, j] = cost.l_qdqd
    L[o + LC, n, j] = cost.l
    return cost.l


@numba.njit(**JIT)
def _rollout(L, S, cur, trial, n, j0, j1):
    """Simulate u = U_cur + alpha kff + K (x - X_cur) from x0 into the trial trajectory, for
    every lane of [j0, j1) with its own alpha and gains (controller.ilqr.rollout); the total
    cost, inf when not finite, goes to scratch[TOTAL]."""
    for j in range(j0, j1):
        L[trial + Q, 0, j] = S[Q0, j]
        L[trial + QD, 0, j] = S[QD0, j]
        S[TOTAL, j] = 0.0
    for k in range(n):
        for j in range(j0, j1):
            c = to_fixed_tuple(S[COSTS:COSTS + N_COST, j], N_COST)
            q, qd = L[trial + Q, k, j], L[trial + QD, k, j]
            u = L[cur + U, k, j] + S[ALPHA, j] * L[KFF, k, j] + L[K1, k, j] * (
                q - L[cur + Q, k, j]) + L[K2, k, j] * (qd - L[cur + QD, k, j])
            cost, q_next, qd_next = _store_stage(L, trial, k, j, q, qd, u, S, c)
            S[TOTAL, j] += cost
            L[trial + Q, k + 1, j] = q_next
            L[trial + QD, k + 1, j] = qd_next
    for j in range(j0, j1):
        c = to_fixed_tuple(S[COSTS:COSTS + N_COST, j], N_COST)
        total = S[TOTAL, j] + _store_terminal(L, trial, n, j, L[trial + Q, n, j],
                                              L[trial + QD, n, j], c)
        S[TOTAL, j] = total if np.isfinite(total) else np.inf


@numba.njit(**JIT)
def _backward(L, S, cur, n, j0, j1):
    """Riccati sweep of every lane of [j0, j1) with its own mu (controller.ilqr.backward);
    writes the gains only of lanes with scratch[NEEDS_SWEEP] set. A lane whose regularised
    Quu is not positive at some step ends with scratch[SWEEP_OK] = 0 (its later steps are
    computed and ignored, as the scalar sweep would have stopped there)."""
    for j in range(j0, j1):
        S[VX1, j] = L[cur + LQ, n, j]
        S[VX2, j] = L[cur + LQD, n, j]
        S[V11, j] = L[cur + LQQ, n, j]
        S[V12, j] = 0.0
        S[V22, j] = L[cur + LQDQD, n, j]
        S[DV1, j] = 0.0
        S[DV2, j] = 0.0
        S[SWEEP_OK, j] = 1.0
    for k in range(n - 1, -1, -1):
        for j in range(j0, j1):
            mu = S[MU, j]
            box = S[BOX, j]
            vx1, vx2 = S[VX1, j], S[VX2, j]
            v11, v12, v22 = S[V11, j], S[V12, j], S[V22, j]
            a11, a12 = L[cur + A11, k, j], L[cur + A12, k, j]
            a21, a22 = L[cur + A21, k, j], L[cur + A22, k, j]
            b1, b2 = L[cur + B1, k, j], L[cur + B2, k, j]
            luu = L[cur + LUU, k, j]
            qx1 = L[cur + LQ, k, j] + a11 * vx1 + a21 * vx2
            qx2 = L[cur + LQD, k, j] + a12 * vx1 + a22 * vx2
            qu = L[cur + LU, k, j] + b1 * vx1 + b2 * vx2
            vb1 = v11 * b1 + v12 * b2
            vb2 = v12 * b1 + v22 * b2
            quu = luu + b1 * vb1 + b2 * vb2
            qux1 = vb1 * a11 + vb2 * a21
            qux2 = vb1 * a12 + vb2 * a22
            rb1 = vb1 + mu * b1
            rb2 = vb2 + mu * b2
            quu_r = luu + b1 * rb1 + b2 * rb2
            ok = quu_r > 0.0
            S[SWEEP_OK, j] = S[SWEEP_OK, j] if ok else 0.0
            qux1_r = rb1 * a11 + rb2 * a21
            qux2_r = rb1 * a12 + rb2 * a22
            va11 = v11 * a11 + v12 * a21
            va12 = v11 * a12 + v12 * a22
            va21 = v12 * a11 + v22 * a21
            va22 = v12 * a12 + v22 * a22
            qxx11 = L[cur + LQQ, k, j] + a11 * va11 + a21 * va21
            qxx12 = a11 * va12 + a21 * va22
            qxx22 = L[cur + LQDQD, k, j] + a12 * va12 + a22 * va22
            kk = -qu / quu_r
            k1 = -qux1_r / quu_r
            k2 = -qux2_r / quu_r
            u = L[cur + U, k, j]
            clamped = abs(u + kk) > box
            kk = ((box if u + kk > 0.0 else -box) - u) if clamped else kk
            k1 = 0.0 if clamped else k1
            k2 = 0.0 if clamped else k2
            writes = S[NEEDS_SWEEP, j] != 0.0
            L[KFF, k, j] = kk if writes else L[KFF, k, j]
            L[K1, k, j] = k1 if writes else L[K1, k, j]
            L[K2, k, j] = k2 if writes else L[K2, k, j]
            S[VX1, j] = qx1 + k1 * quu * kk + k1 * qu + qux1 * kk
            S[VX2, j] = qx2 + k2 * quu * kk + k2 * qu + qux2 * kk
            S[V11, j] = qxx11 + k1 * quu * k1 + 2.0 * k1 * qux1
            S[V12, j] = qxx12 + k1 * quu * k2 + k1 * qux2 + qux1 * k2
            S[V22, j] = qxx22 + k2 * quu * k2 + 2.0 * k2 * qux2
            S[DV1, j] += kk * qu
            S[DV2, j] += 0.5 * kk * kk * quu


@numba.njit(**JIT)
def _shift(L, S, cur, n, j0, j1):
    """Lanes with scratch[SHIFTS] set advance their stored solution one step
    (controller.mpc._shift): everything moves up by one, the last control is repeated, the last
    stage and the terminal state are evaluated anew. The other lanes are left as they are."""
    for f in (Q, QD, LQ, LQD, LQQ, LQDQD, LC):
        for k in range(n):
            for j in range(j0, j1):
                L[cur + f, k, j] = L[cur + f, k + 1, j] if S[SHIFTS, j] != 0.0 else L[
                    cur + f, k, j]
    for f in (cur + U, cur + A11, cur + A12, cur + A21, cur + A22, cur + B1, cur + B2,
              cur + LU, cur + LUU, K1, K2):
        for k in range(n - 1):
            for j in range(j0, j1):
                L[f, k, j] = L[f, k + 1, j] if S[SHIFTS, j] != 0.0 else L[f, k, j]
    for j in range(j0, j1):
        if S[SHIFTS, j] != 0.0:
            c = to_fixed_tuple(S[COSTS:COSTS + N_COST, j], N_COST)
            _, q_next, qd_next = _store_stage(L, cur, n - 1, j, L[cur + Q, n - 1, j],
                                              L[cur + QD, n - 1, j], L[cur + U, n - 2, j], S, c)
            _store_terminal(L, cur, n, j, q_next, qd_next, c)


@numba.njit(**JIT)
def _take(L, S, current, block, n, j0, j1):
    """The trial becomes the current solution of lanes with scratch[TAKES] set: a swap of the
    two trajectories' roles when every lane of the block takes it, a copy of the takers' lanes
    otherwise."""
    takers = 0
    for j in range(j0, j1):
        takers += S[TAKES, j] != 0.0
    if takers == 0:
        return
    if takers == j1 - j0:
        current[block] = 1 - current[block]
        return
    cur = current[block] * TRAJECTORY_FIELDS
    trial = (1 - current[block]) * TRAJECTORY_FIELDS
    for f in range(TRAJECTORY_FIELDS):
        for k in range(n + 1):
            for j in range(j0, j1):
                L[cur + f, k, j] = L[trial + f, k, j] if S[TAKES, j] != 0.0 else L[cur + f, k, j]


@numba.njit(**JIT)
def _finish(state, S, j, status):
    """A lane's iLQR ended with `status` (its iterations, cost and mu are in its state)."""
    state[PHASE, j] = DONE
    state[STATUS_, j] = status


@numba.njit(**JIT)
def _start_first_rollout(L, state, S, j, n):
    """Classic iLQR from the controls in the current trajectory (controller.ilqr
    solve_from_controls): no feedback, alpha 0."""
    for k in range(n):
        L[K1, k, j] = 0.0
        L[K2, k, j] = 0.0
        L[KFF, k, j] = 0.0  # times alpha 0; the scalar solver's are finite leftovers, these
        # may be a failed sweep's
    S[ALPHA, j] = 0.0
    state[PHASE, j] = FIRST_ROLLOUT


@numba.njit(**JIT)
def _start_iterations(state, S, j, cost, max_iterations, iteration_offset, rollouts_offset):
    """controller.ilqr.iterate from a current trajectory of cost `cost`."""
    S[COST, j] = cost
    S[MU, j] = MU_MIN
    state[ITERATION, j] = 0
    state[MAX_ITER, j] = max_iterations
    state[ITERATION_OFFSET, j] = iteration_offset
    state[ROLLOUTS_OFFSET, j] = rollouts_offset
    state[ROLLOUTS_, j] = 0
    state[AFTER_WARM, j] = 0
    state[PHASE, j] = SWEEP


@numba.njit(**JIT)
def _start_search(state, S, j, merit):
    state[PHASE, j] = SEARCH
    state[ATTEMPT, j] = 0
    S[ALPHA, j] = 1.0
    S[MERIT, j] = merit


@numba.njit(**JIT)
def _bump_mu(state, S, j):
    """Regularise more after a failed sweep or line search; False when it is out of range."""
    S[MU, j] = max(S[MU, j] * 10.0, 1e-6)
    if S[MU, j] > MU_MAX:
        _finish(state, S, j, LINE_SEARCH_FAILED)
        return False
    return True


@numba.njit(**JIT)
def _begin(rows, L, S, state, cur, t0, n, j0, j1):
    """Read each joint's inputs and mode from its row and set it on its way (tick_joint's
    opening); returns whether any lane shifts its warm solution."""
    shifts = False
    for j in range(j0, j1):
        row = rows[j]
        S[SHIFTS, j] = 0.0
        S[NEEDS_SWEEP, j] = 0.0
        mode = row[ws.MODE]
        if mode == SKIP:
            row[ws.MODE] = COLD
            state[PHASE, j] = DONE
            state[STATUS_, j] = -1
            continue
        for i in range(N_PARAMS):
            S[PARAMETERS + i, j] = row[ws.PARAMETERS + i]
        for i in range(N_COST):
            S[COSTS + i, j] = row[ws.COST_VECTOR + i]
        c = to_fixed_tuple(S[COSTS:COSTS + N_COST, j], N_COST)
        S[BOX, j] = control_box(c)
        S[Q0, j] = row[ws.POSITION]
        S[QD0, j] = row[ws.VELOCITY]
        max_iterations = int(row[ws.COLD_ITERATIONS] if mode == COLD else row[ws.WARM_ITERATIONS])
        state[MAX_ITER, j] = max_iterations
        S[TOLERANCE, j] = row[ws.TOLERANCE]
        S[COST, j] = np.inf
        S[MU, j] = MU_MIN
        state[ITERATION, j] = 0
        state[ROLLOUTS_, j] = 0
        reference = row[ws.REFERENCE:ws.REFERENCE + 4]
        dt = c[C_DT]
        contiguous = abs(t0 - row[ws.LAST_T0] - dt) < 1e-6 * dt
        row[ws.LAST_T0] = t0
        if mode == WARM and contiguous:
            for k in range(n):
                L[REFERENCE_Q, k, j] = L[REFERENCE_Q, k + 1, j]
                L[REFERENCE_QD, k, j] = L[REFERENCE_QD, k + 1, j]
            L[REFERENCE_Q, n, j], L[REFERENCE_QD, n, j] = reference_at(reference, t0 + n * dt)
            S[SHIFTS, j] = 1.0
            shifts = True
            state[PHASE, j] = WARM_SWEEP
            state[ROLLOUTS_OFFSET, j] = 0
        else:
            for k in range(n + 1):
                L[REFERENCE_Q, k, j], L[REFERENCE_QD, k, j] = reference_at(reference,
                                                                           t0 + k * dt)
            if mode == COLD:
                for k in range(n):
                    L[cur + U, k, j] = row[ws.INITIAL_CURRENT]
            else:
                for k in range(n - 1):
                    L[cur + U, k, j] = L[cur + U, k + 1, j]
            state[ROLLOUTS_OFFSET, j] = 0
            _start_first_rollout(L, state, S, j, n)
    return shifts


@numba.njit(**JIT)
def _before_sweep(state, S, j0, j1):
    """Mark the lanes that sweep this round; an iterating lane first checks its iteration
    budget (the head of controller.ilqr.iterate's loop). Returns whether any lane sweeps."""
    any_sweep = False
    for j in range(j0, j1):
        phase = state[PHASE, j]
        if phase == SWEEP:
            if state[ITERATION, j] >= state[MAX_ITER, j]:
                _finish(state, S, j, MAX_ITERATIONS)
                continue
            state[ITERATION, j] += 1
        elif phase != WARM_SWEEP:
            continue
        S[NEEDS_SWEEP, j] = 1.0
        any_sweep = True
    return any_sweep


@numba.njit(**JIT)
def _after_sweep(L, S, state, cur, n, j0, j1):
    """Each lane that swept decides, as the scalar solver does after `backward`."""
    for j in range(j0, j1):
        if S[NEEDS_SWEEP, j] == 0.0:
            continue
        S[NEEDS_SWEEP, j] = 0.0
        ok = S[SWEEP_OK, j] != 0.0
        if state[PHASE, j] == WARM_SWEEP:
            if not ok:
                _start_first_rollout(L, state, S, j, n)
                continue
            d1, d2 = S[Q0, j] - L[cur + Q, 0, j], S[QD0, j] - L[cur + QD, 0, j]
            merit = S[SUM, j] + S[VX1, j] * d1 + S[VX2, j] * d2 + 0.5 * (
                S[V11, j] * d1 * d1 + 2.0 * S[V12, j] * d1 * d2 + S[V22, j] * d2 * d2)
            _start_search(state, S, j, merit)
            state[AFTER_WARM, j] = 1
            continue
        if not ok:
            _bump_mu(state, S, j)
            continue
        cost = S[COST, j]
        if -S[DV1, j] < S[TOLERANCE, j] * max(cost, 1.0) * 1e-3:
            _finish(state, S, j, CONVERGED)  # the model predicts no meaningful improvement
            continue
        _start_search(state, S, j, cost)


@numba.njit(**JIT)
def _after_rollout(L, S, state, j0, j1):
    """Each lane that simulated decides (solve_from_controls after its first simulation, the
    line search after a trial); sets scratch[TAKES] on the lanes whose trial becomes their
    current solution."""
    for j in range(j0, j1):
        S[TAKES, j] = 0.0
        phase = state[PHASE, j]
        total = S[TOTAL, j]
        if phase == FIRST_ROLLOUT:
            S[TAKES, j] = 1.0  # simulated in place in the scalar solver, finite or not
            rollouts_offset = state[ROLLOUTS_OFFSET, j] + 1
            if not np.isfinite(total):
                S[COST, j] = total
                S[MU, j] = MU_MIN
                state[ITERATION, j] = 0
                state[ROLLOUTS_, j] = 0
                state[ITERATION_OFFSET, j] = 0
                state[ROLLOUTS_OFFSET, j] = rollouts_offset
                _finish(state, S, j, NOT_FINITE)
                continue
            _start_iterations(state, S, j, total, state[MAX_ITER, j], 0, rollouts_offset)
            continue
        if phase != SEARCH:
            continue
        state[ATTEMPT, j] += 1
        alpha = S[ALPHA, j]
        expected = -(alpha * S[DV1, j] + alpha * alpha * S[DV2, j])
        accepted = np.isfinite(total) and S[MERIT, j] - total > ARMIJO * expected
        if accepted:
            S[TAKES, j] = 1.0
            trials = state[ATTEMPT, j]
            if state[AFTER_WARM, j] == 1:
                if state[MAX_ITER, j] == 1:
                    S[COST, j] = total
                    S[MU, j] = MU_MIN
                    state[ITERATION, j] = 1
                    state[ROLLOUTS_, j] = trials
                    state[ITERATION_OFFSET, j] = 0
                    state[ROLLOUTS_OFFSET, j] = 0
                    _finish(state, S, j, MAX_ITERATIONS)
                else:
                    _start_iterations(state, S, j, total, state[MAX_ITER, j] - 1, 1, trials)
                continue
            state[ROLLOUTS_, j] += trials
            improvement = S[COST, j] - total
            S[COST, j] = total
            mu = S[MU, j]
            S[MU, j] = mu / 10.0 if mu > MU_MIN * 10.0 else MU_MIN
            state[PHASE, j] = SWEEP
            if improvement < S[TOLERANCE, j] * max(total, 1.0):
                _finish(state, S, j, CONVERGED)
            continue
        if state[ATTEMPT, j] < LINE_SEARCH_STEPS:
            S[ALPHA, j] = alpha * 0.5
            continue
        if state[AFTER_WARM, j] == 1:  # the warm step failed: solve anew from the controls
            state[AFTER_WARM, j] = 0
            state[ROLLOUTS_OFFSET, j] = LINE_SEARCH_STEPS
            _start_first_rollout(L, state, S, j, L.shape[1] - 1)
            continue
        state[ROLLOUTS_, j] += LINE_SEARCH_STEPS
        _bump_mu(state, S, j)
        if state[PHASE, j] == SEARCH:
            state[PHASE, j] = SWEEP


@numba.njit(**JIT)
def _shifted_costs(L, S, state, cur, n, j0, j1):
    """The shifted trajectory's cost of each warm lane, summed in the scalar tick's order."""
    for j in range(j0, j1):
        S[SUM, j] = 0.0
    for k in range(n + 1):
        for j in range(j0, j1):
            S[SUM, j] += L[cur + LC, k, j]


@numba.njit(**JIT)
def _end(rows, L, S, state, cur, j0, j1):
    """Each ticked joint's outcome into its row's header, and its next mode."""
    for j in range(j0, j1):
        status = state[STATUS_, j]
        if status < 0:
            continue  # skipped
        row = rows[j]
        row[ws.STATUS] = status
        row[ws.ITERATIONS] = state[ITERATION, j] + state[ITERATION_OFFSET, j]
        row[ws.COST] = S[COST, j]
        row[ws.MU] = S[MU, j]
        row[ws.ROLLOUTS] = state[ROLLOUTS_, j] + state[ROLLOUTS_OFFSET, j]
        planned = L[cur + U, 0, j]
        row[ws.PLANNED_CURRENT] = planned
        row[ws.REFERENCE_POSITION] = L[REFERENCE_Q, 0, j]
        row[ws.REFERENCE_VELOCITY] = L[REFERENCE_QD, 0, j]
        usable = status == CONVERGED or status == MAX_ITERATIONS
        row[ws.MODE] = WARM if usable and np.isfinite(planned) else COLD


@numba.njit(**JIT)
def tick_block(rows, L, S, state, current, block, t0, n, j0, j1):
    """Every joint of lanes [j0, j1) at time t0: rounds of one masked backward pass and one
    simulation until each joint's iLQR has ended (see the module docstring)."""
    cur = current[block] * TRAJECTORY_FIELDS
    if _begin(rows, L, S, state, cur, t0, n, j0, j1):
        _shift(L, S, cur, n, j0, j1)
        _shifted_costs(L, S, state, cur, n, j0, j1)
    while True:
        cur = current[block] * TRAJECTORY_FIELDS
        swept = _before_sweep(state, S, j0, j1)
        if swept:
            _backward(L, S, cur, n, j0, j1)
            _after_sweep(L, S, state, cur, n, j0, j1)
        simulates = False
        for j in range(j0, j1):
            phase = state[PHASE, j]
            simulates = simulates or phase == FIRST_ROLLOUT or phase == SEARCH
        if simulates:
            _rollout(L, S, cur, TRAJECTORY_FIELDS - cur, n, j0, j1)
            _after_rollout(L, S, state, j0, j1)
            _take(L, S, current, block, n, j0, j1)
        if not swept and not simulates:
            break
    _end(rows, L, S, state, current[block] * TRAJECTORY_FIELDS, j0, j1)


@numba.njit(parallel=True, **JIT)
def tick_lanes(rows, L, S, state, current, t0, n):
    """Every joint's MPC step at time t0, the joints in len(current) blocks of lanes, one per
    thread (one block: no thread team is woken)."""
    joints = rows.shape[0]
    blocks = current.shape[0]
    if blocks == 1:
        tick_block(rows, L, S, state, current, 0, t0, n, 0, joints)
        return
    for block in numba.prange(blocks):
        tick_block(rows, L, S, state, current, block, t0, n, block * joints // blocks,
                   (block + 1) * joints // blocks)
