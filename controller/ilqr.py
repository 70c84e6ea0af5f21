"""Compiled iLQR for the 2-state, 1-input actuator problem: rollout, backward pass, line search
and iterations. The hot loop of the MPC; the problem itself is `controller.action_model`.

Same algorithm as `ilqr_reference` (read that one first), written out in scalars so numba keeps
everything in registers: exact cost derivatives, Tassa-style regularisation on the value
function, a control box where the torque barrier reaches e^4 (box-DDP), backtracking line
search on the actual cost, convergence on relative cost decrease.

Trajectories are `controller.workspace.Trajectory` views into the joint's workspace row; two of
them are kept so a line-search trial leaves everything the next backward pass needs, and
accepting a trial swaps their roles instead of copying.
"""

from typing import NamedTuple

import numba
import numpy as np

from controller.action_model import discrete_step, stage_cost, terminal_cost
from controller.cost import control_box
from controller.workspace import JIT

CONVERGED = 0
MAX_ITERATIONS = 1
LINE_SEARCH_FAILED = 2
NOT_FINITE = 3
STATUS_NAMES = ("converged", "max_iterations", "line_search_failed", "not_finite")

MU_MIN = 1e-8
MU_MAX = 1e10
ARMIJO = 1e-4
LINE_SEARCH_STEPS = 10  # alpha = 1, 1/2, ..., 1/512
# A warm-started MPC tick's work is bounded (see controller.mpc): its trials (alpha = 1, 1/2,
# 1/4), and how much more than its merit its smallest step may cost and still be taken when
# none passes the Armijo test. Measured in lock-step (actuatord --sim --lockstep, 10 s each),
# such steps cost at most 1.1 times the merit (1.0001 to 1.003 by the median) on talos_32,
# talos_arm and the elbow alike, except in the first 40 ms after the cold solve: there 21
# cost more, 19 of them 10 to 1e177 times it (the plan diverged).
WARM_TRIALS = 3
WARM_COST_RATIO = 2.0


class Outcome(NamedTuple):
    """What a solve ended with; `flipped` says the result sits in the other trajectory."""

    status: int
    iterations: int
    cost: float
    mu: float
    rollouts: int
    flipped: bool


class Backward(NamedTuple):
    """A Riccati sweep's result: the expected change alpha dv1 + alpha^2 dv2 of a step alpha,
    and the value function's gradient and Hessian at the first state."""

    ok: bool
    dv1: float
    dv2: float
    vx1: float
    vx2: float
    v11: float
    v12: float
    v22: float


@numba.njit(**JIT)
def store_stage(traj, k, q, qd, u, step, cost):
    """Keep x_k, u_k, the linearisation and the cost derivatives at step k."""
    X, U, A, B, LX, LXX = traj.X, traj.U, traj.A, traj.B, traj.LX, traj.LXX
    X[k, 0] = q
    X[k, 1] = qd
    U[k] = u
    LX[k, 0] = cost.l_q
    LX[k, 1] = cost.l_qd
    LXX[k, 0] = cost.l_qq
    LXX[k, 1] = cost.l_qdqd
    traj.LU[k] = cost.l_u
    traj.LUU[k] = cost.l_uu
    traj.LC[k] = cost.l
    A[k, 0] = step.a11
    A[k, 1] = step.a12
    A[k, 2] = step.a21
    A[k, 3] = step.a22
    B[k, 0] = step.b1
    B[k, 1] = step.b2


@numba.njit(**JIT)
def evaluate_terminal(q, qd, traj, ref_q, ref_qd, c):
    """Keep the terminal state and its cost derivatives; returns the terminal cost."""
    X, LX, LXX = traj.X, traj.LX, traj.LXX
    n = X.shape[0] - 1
    cost = terminal_cost(q, qd, ref_q[n], ref_qd[n], c)
    X[n, 0] = q
    X[n, 1] = qd
    LX[n, 0] = cost.l_q
    LX[n, 1] = cost.l_qd
    LXX[n, 0] = cost.l_qq
    LXX[n, 1] = cost.l_qdqd
    traj.LC[n] = cost.l
    return cost.l


@numba.njit(**JIT)
def rollout(q0, qd0, base, K, kff, alpha, out, ref_q, ref_qd, p, c):
    """Simulate u = U_base + alpha kff + K (x - X_base) from x0 into `out`; total cost, or
    inf when it is not finite."""
    X_base, U_base = base.X, base.U
    n = U_base.shape[0]
    q, qd = q0, qd0
    total = 0.0
    for k in range(n):
        u = U_base[k] + alpha * kff[k] + K[k, 0] * (q - X_base[k, 0]) + K[k, 1] * (
            qd - X_base[k, 1])
        step = discrete_step(q, qd, u, p, c)
        cost = stage_cost(q, qd, u, ref_q[k], ref_qd[k], c)
        store_stage(out, k, q, qd, u, step, cost)
        total += cost.l
        q, qd = step.q, step.qd
    total += evaluate_terminal(q, qd, out, ref_q, ref_qd, c)
    if not np.isfinite(total):
        return np.inf
    return total


@numba.njit(**JIT)
def backward(traj, mu, K, kff, c):
    """Riccati sweep filling K and kff. A step that would leave the control box is clamped to
    it, with no feedback at that stage (box-DDP)."""
    U, A, B, LX, LXX, LU, LUU = traj.U, traj.A, traj.B, traj.LX, traj.LXX, traj.LU, traj.LUU
    box = control_box(c)
    n = LU.shape[0]
    vx1, vx2 = LX[n, 0], LX[n, 1]
    v11, v12, v22 = LXX[n, 0], 0.0, LXX[n, 1]
    dv1 = 0.0
    dv2 = 0.0
    for k in range(n - 1, -1, -1):
        a11, a12, a21, a22 = A[k, 0], A[k, 1], A[k, 2], A[k, 3]
        b1, b2 = B[k, 0], B[k, 1]
        qx1 = LX[k, 0] + a11 * vx1 + a21 * vx2
        qx2 = LX[k, 1] + a12 * vx1 + a22 * vx2
        qu = LU[k] + b1 * vx1 + b2 * vx2
        # V B and V A, unregularised (for the value update) ...
        vb1 = v11 * b1 + v12 * b2
        vb2 = v12 * b1 + v22 * b2
        quu = LUU[k] + b1 * vb1 + b2 * vb2
        qux1 = vb1 * a11 + vb2 * a21
        qux2 = vb1 * a12 + vb2 * a22
        # ... and with mu I added to V (Tassa 2012) for the gains
        rb1 = vb1 + mu * b1
        rb2 = vb2 + mu * b2
        quu_r = LUU[k] + b1 * rb1 + b2 * rb2
        if not quu_r > 0.0:
            return Backward(False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        qux1_r = rb1 * a11 + rb2 * a21
        qux2_r = rb1 * a12 + rb2 * a22
        va11 = v11 * a11 + v12 * a21
        va12 = v11 * a12 + v12 * a22
        va21 = v12 * a11 + v22 * a21
        va22 = v12 * a12 + v22 * a22
        qxx11 = LXX[k, 0] + a11 * va11 + a21 * va21
        qxx12 = a11 * va12 + a21 * va22
        qxx22 = LXX[k, 1] + a12 * va12 + a22 * va22
        kk = -qu / quu_r
        k1 = -qux1_r / quu_r
        k2 = -qux2_r / quu_r
        if abs(U[k] + kk) > box:
            kk = (box if U[k] + kk > 0.0 else -box) - U[k]
            k1 = 0.0
            k2 = 0.0
        kff[k] = kk
        K[k, 0] = k1
        K[k, 1] = k2
        vx1 = qx1 + k1 * quu * kk + k1 * qu + qux1 * kk
        vx2 = qx2 + k2 * quu * kk + k2 * qu + qux2 * kk
        v11 = qxx11 + k1 * quu * k1 + 2.0 * k1 * qux1
        v12 = qxx12 + k1 * quu * k2 + k1 * qux2 + qux1 * k2
        v22 = qxx22 + k2 * quu * k2 + 2.0 * k2 * qux2
        dv1 += kk * qu
        dv2 += 0.5 * kk * kk * quu
    return Backward(True, dv1, dv2, vx1, vx2, v11, v12, v22)


@numba.njit(**JIT)
def line_search(q0, qd0, cur, trial, K, kff, dv1, dv2, merit, ref_q, ref_qd, p, c, trials):
    """Backtrack alpha over at most `trials` simulations until the trial beats `merit` by the
    Armijo fraction of the predicted decrease; returns (accepted, the last trial's cost (inf
    if not finite), rollouts). A rejected search leaves its smallest step in `trial`."""
    alpha = 1.0
    new_cost = np.inf
    for attempt in range(trials):
        new_cost = rollout(q0, qd0, cur, K, kff, alpha, trial, ref_q, ref_qd, p, c)
        expected = -(alpha * dv1 + alpha * alpha * dv2)
        if np.isfinite(new_cost) and merit - new_cost > ARMIJO * expected:
            return True, new_cost, attempt + 1
        alpha *= 0.5
    return False, new_cost, trials


@numba.njit(**JIT)
def iterate(q0, qd0, cur, trial, K, kff, cost, ref_q, ref_qd, p, c, max_iterations,
            tolerance):
    """iLQR iterations from `cur` (states, derivatives and `cost` valid)."""
    flipped = False
    mu = MU_MIN
    status = MAX_ITERATIONS
    iteration = 0
    rollouts = 0
    while iteration < max_iterations:
        iteration += 1
        sweep = backward(cur, mu, K, kff, c)
        if not sweep.ok:
            mu = max(mu * 10.0, 1e-6)
            if mu > MU_MAX:
                status = LINE_SEARCH_FAILED
                break
            continue
        if -sweep.dv1 < tolerance * max(cost, 1.0) * 1e-3:
            status = CONVERGED  # the model predicts no meaningful improvement is left
            break
        accepted, new_cost, trials = line_search(q0, qd0, cur, trial, K, kff, sweep.dv1,
                                                 sweep.dv2, cost, ref_q, ref_qd, p, c,
                                                 LINE_SEARCH_STEPS)
        rollouts += trials
        if not accepted:
            mu = max(mu * 10.0, 1e-6)
            if mu > MU_MAX:
                status = LINE_SEARCH_FAILED
                break
            continue
        cur, trial = trial, cur
        flipped = not flipped
        improvement = cost - new_cost
        cost = new_cost
        mu = mu / 10.0 if mu > MU_MIN * 10.0 else MU_MIN
        if improvement < tolerance * max(cost, 1.0):
            status = CONVERGED
            break
    return Outcome(status, iteration, cost, mu, rollouts, flipped)


@numba.njit(**JIT)
def solve_from_controls(q0, qd0, cur, trial, K, kff, ref_q, ref_qd, p, c, max_iterations,
                        tolerance):
    """Classic iLQR: simulate the controls in cur.U open loop, then iterate."""
    K[:, :] = 0.0
    cost = rollout(q0, qd0, cur, K, kff, 0.0, cur, ref_q, ref_qd, p, c)
    if not np.isfinite(cost):
        return Outcome(NOT_FINITE, 0, cost, MU_MIN, 1, False)
    outcome = iterate(q0, qd0, cur, trial, K, kff, cost, ref_q, ref_qd, p, c, max_iterations,
                      tolerance)
    return Outcome(outcome.status, outcome.iterations, outcome.cost, outcome.mu,
                   outcome.rollouts + 1, outcome.flipped)

