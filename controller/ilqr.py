"""Compiled iLQR for the 2-state, 1-input actuator problem: the hot loop of the MPC.

Same algorithm as `ilqr_reference` (read that one first), written out in scalars so numba keeps
everything in registers: semi-implicit Euler discretisation of the model's smooth dynamics,
exact cost derivatives, Tassa-style regularisation on the value function, backtracking line
search on the actual cost, convergence on relative cost decrease.

A trajectory is a tuple of arrays (X, U, A, B, LX, LXX, LU, LUU, LC): states, controls, the
linearisation and the cost derivatives along it, and the stage costs. Two of them are kept so a
line-search trial leaves everything the next backward pass needs.

The warm-started MPC tick is a real-time iteration: the previous solution, its linearisation
and its stage costs are shifted by one step (only the last stage is new), the backward pass runs
on them directly, and the forward pass from the measured state is the line search. The merit it
must beat is the shifted cost corrected to the measured state by the value function's quadratic
model, so the Armijo test stays meaningful. One simulation per tick instead of two.
"""

from typing import NamedTuple

import numba
import numpy as np

from controller.cost import control_box, control_cost, state_cost
from controller.problem import C_DT, C_FRICTION_SHARPNESS, OcpSettings
from controller.reference import reference_at
from model.dynamics import smooth_acceleration

CONVERGED = 0
MAX_ITERATIONS = 1
LINE_SEARCH_FAILED = 2
NOT_FINITE = 3
STATUS_NAMES = ("converged", "max_iterations", "line_search_failed", "not_finite")

COLD, WARM, RESAMPLE = 0, 1, 2  # tick modes

MU_MIN = 1e-8
MU_MAX = 1e10
ARMIJO = 1e-4
LINE_SEARCH_STEPS = 10  # alpha = 1, 1/2, ..., 1/512
JIT = {"cache": True, "error_model": "numpy", "nogil": True}


@numba.njit(**JIT)
def _stage(k, q, qd, u, traj, ref_q, ref_qd, p, c):
    """Store x_k, u_k, the linearisation and cost derivatives at step k; return x_{k+1} and
    the stage cost."""
    X, U, A, B, LX, LXX, LU, LUU, LC = traj
    dt = c[C_DT]
    X[k, 0] = q
    X[k, 1] = qd
    U[k] = u
    ls, ls_q, ls_qd, ls_qq, ls_qdqd = state_cost(q, qd, ref_q[k], ref_qd[k], c)
    lc, lc_u, lc_uu = control_cost(u, c)
    LX[k, 0] = ls_q
    LX[k, 1] = ls_qd
    LXX[k, 0] = ls_qq
    LXX[k, 1] = ls_qdqd
    LU[k] = lc_u
    LUU[k] = lc_uu
    LC[k] = ls + lc
    a, a_q, a_qd, a_u = smooth_acceleration(q, qd, u, p, c[C_FRICTION_SHARPNESS])
    # semi-implicit Euler: qd+ = qd + dt a, q+ = q + dt qd+
    A[k, 0] = 1.0 + dt * dt * a_q
    A[k, 1] = dt + dt * dt * a_qd
    A[k, 2] = dt * a_q
    A[k, 3] = 1.0 + dt * a_qd
    B[k, 0] = dt * dt * a_u
    B[k, 1] = dt * a_u
    qd_next = qd + dt * a
    return q + dt * qd_next, qd_next, ls + lc


@numba.njit(**JIT)
def _terminal(q, qd, traj, ref_q, ref_qd, c):
    X, _, _, _, LX, LXX, _, _, LC = traj
    n = X.shape[0] - 1
    ls, ls_q, ls_qd, ls_qq, ls_qdqd = state_cost(q, qd, ref_q[n], ref_qd[n], c)
    X[n, 0] = q
    X[n, 1] = qd
    LX[n, 0] = ls_q
    LX[n, 1] = ls_qd
    LXX[n, 0] = ls_qq
    LXX[n, 1] = ls_qdqd
    LC[n] = ls
    return ls


@numba.njit(**JIT)
def _rollout(q0, qd0, base, K, kff, alpha, out, ref_q, ref_qd, p, c):
    """Simulate u = U_base + alpha kff + K (x - X_base) from x0 into `out`; total cost, or
    inf when it is not finite."""
    X_base, U_base = base[0], base[1]
    n = U_base.shape[0]
    q, qd = q0, qd0
    total = 0.0
    for k in range(n):
        u = U_base[k] + alpha * kff[k] + K[k, 0] * (q - X_base[k, 0]) + K[k, 1] * (
            qd - X_base[k, 1])
        q, qd, cost = _stage(k, q, qd, u, out, ref_q, ref_qd, p, c)
        total += cost
    total += _terminal(q, qd, out, ref_q, ref_qd, c)
    if not np.isfinite(total):
        return np.inf
    return total


@numba.njit(**JIT)
def _backward(traj, mu, K, kff, c):
    """Riccati sweep. Returns ok, the expected change alpha dv1 + alpha^2 dv2 of a step alpha,
    and the value function's gradient and Hessian at the first state. A step that would leave
    the control box is clamped to it, with no feedback at that stage (box-DDP)."""
    _, U, A, B, LX, LXX, LU, LUU, _ = traj
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
            return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
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
    return True, dv1, dv2, vx1, vx2, v11, v12, v22


@numba.njit(**JIT)
def _line_search(q0, qd0, cur, trial, K, kff, dv1, dv2, merit, ref_q, ref_qd, p, c):
    """Backtrack alpha until the trial beats `merit` by the Armijo fraction of the predicted
    decrease; returns (accepted, new cost, rollouts)."""
    alpha = 1.0
    for attempt in range(LINE_SEARCH_STEPS):
        new_cost = _rollout(q0, qd0, cur, K, kff, alpha, trial, ref_q, ref_qd, p, c)
        expected = -(alpha * dv1 + alpha * alpha * dv2)
        if np.isfinite(new_cost) and merit - new_cost > ARMIJO * expected:
            return True, new_cost, attempt + 1
        alpha *= 0.5
    return False, np.inf, LINE_SEARCH_STEPS


@numba.njit(**JIT)
def _iterate(q0, qd0, cur, trial, K, kff, cost, ref_q, ref_qd, p, c, max_iterations,
             tolerance, stats):
    """iLQR iterations from `cur` (states, derivatives and `cost` valid). Accepting a trial
    swaps the roles of the two buffers instead of copying; returns True when the result ends
    up in `trial`. stats <- [status, iterations, cost, mu, rollouts] (rollouts added)."""
    flipped = False
    mu = MU_MIN
    status = MAX_ITERATIONS
    iteration = 0
    rollouts = 0
    while iteration < max_iterations:
        iteration += 1
        ok, dv1, dv2, _, _, _, _, _ = _backward(cur, mu, K, kff, c)
        if not ok:
            mu = max(mu * 10.0, 1e-6)
            if mu > MU_MAX:
                status = LINE_SEARCH_FAILED
                break
            continue
        if -dv1 < tolerance * max(cost, 1.0) * 1e-3:
            status = CONVERGED  # the model predicts no meaningful improvement is left
            break
        accepted, new_cost, trials = _line_search(q0, qd0, cur, trial, K, kff, dv1, dv2, cost,
                                                  ref_q, ref_qd, p, c)
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
    stats[0], stats[1], stats[2], stats[3] = status, iteration, cost, mu
    stats[4] += rollouts
    return flipped


@numba.njit(**JIT)
def _solve_from_controls(q0, qd0, cur, trial, K, kff, ref_q, ref_qd, p, c, max_iterations,
                         tolerance, stats):
    """Classic iLQR: simulate the controls in cur.U open loop, then iterate; returns True when
    the result is in `trial`."""
    K[:, :] = 0.0
    cost = _rollout(q0, qd0, cur, K, kff, 0.0, cur, ref_q, ref_qd, p, c)
    stats[4] = 1
    if not np.isfinite(cost):
        stats[0], stats[1], stats[2], stats[3] = NOT_FINITE, 0, cost, MU_MIN
        return False
    return _iterate(q0, qd0, cur, trial, K, kff, cost, ref_q, ref_qd, p, c, max_iterations,
                    tolerance, stats)


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
    q, qd, _ = _stage(n - 1, X[n - 1, 0], X[n - 1, 1], U[n - 2], cur, ref_q, ref_qd, p, c)
    _terminal(q, qd, cur, ref_q, ref_qd, c)


@numba.njit(**JIT)
def _tick_warm(q0, qd0, cur, trial, K, kff, ref_q, ref_qd, p, c, max_iterations, tolerance,
               stats):
    """Real-time iteration from the shifted previous solution (see the module docstring);
    returns True when the result is in `trial`."""
    _shift(cur, K, ref_q, ref_qd, p, c)
    X = cur[0]
    ok, dv1, dv2, vx1, vx2, v11, v12, v22 = _backward(cur, MU_MIN, K, kff, c)
    stats[4] = 0
    if ok:
        d1, d2 = q0 - X[0, 0], qd0 - X[0, 1]
        shifted_cost = 0.0
        for cost in cur[8]:
            shifted_cost += cost
        merit = shifted_cost + vx1 * d1 + vx2 * d2 + 0.5 * (v11 * d1 * d1 + 2.0 * v12 * d1 * d2
                                                            + v22 * d2 * d2)
        accepted, new_cost, trials = _line_search(q0, qd0, cur, trial, K, kff, dv1, dv2, merit,
                                                  ref_q, ref_qd, p, c)
        stats[4] = trials
        if accepted:
            stats[0], stats[1], stats[2], stats[3] = MAX_ITERATIONS, 1, new_cost, MU_MIN
            if max_iterations == 1:
                return True
            flipped = _iterate(q0, qd0, trial, cur, K, kff, new_cost, ref_q, ref_qd, p, c,
                               max_iterations - 1, tolerance, stats)
            stats[1] += 1
            return not flipped
    rollouts = stats[4]
    flipped = _solve_from_controls(q0, qd0, cur, trial, K, kff, ref_q, ref_qd, p, c,
                                   max_iterations, tolerance, stats)
    stats[4] += rollouts
    return flipped


@numba.njit(**JIT)
def _trajectory(ws, start, n):
    """The nine arrays of one trajectory laid out from ws[start]; returns them and the end."""
    sizes = (2 * (n + 1), n, 4 * n, 2 * n, 2 * (n + 1), 2 * (n + 1), n, n, n + 1)
    o = np.empty(10, np.int64)
    o[0] = start
    for i in range(9):
        o[i + 1] = o[i] + sizes[i]
    return (ws[o[0]:o[1]].reshape((n + 1, 2)), ws[o[1]:o[2]], ws[o[2]:o[3]].reshape((n, 4)),
            ws[o[3]:o[4]].reshape((n, 2)), ws[o[4]:o[5]].reshape((n + 1, 2)),
            ws[o[5]:o[6]].reshape((n + 1, 2)), ws[o[6]:o[7]], ws[o[7]:o[8]],
            ws[o[8]:o[9]]), o[9]


@numba.njit(**JIT)
def _workspace(ws, n):
    """Named views into the one flat workspace (one array crosses the Python/numba border,
    which keeps the per-call dispatch cost low): the current and the trial trajectory, the
    policy (K, kff), the reference over the horizon, the time it was sampled from, and which
    buffer holds the current solution."""
    first, end = _trajectory(ws, 0, n)
    second, end = _trajectory(ws, end, n)
    K = ws[end:end + 2 * n].reshape((n, 2))
    end += 2 * n
    kff = ws[end:end + n]
    end += n
    ref_q = ws[end:end + n + 1]
    ref_qd = ws[end + n + 1:end + 2 * n + 2]
    flags = ws[end + 2 * n + 2:end + 2 * n + 4]  # [last t0, 1.0 when `second` is current]
    if flags[1] == 1.0:
        return second, first, K, kff, ref_q, ref_qd, flags
    return first, second, K, kff, ref_q, ref_qd, flags


def workspace_size(n: int) -> int:
    trajectory = 2 * (n + 1) + n + 4 * n + 2 * n + 4 * (n + 1) + 2 * n + n + 1
    return 2 * trajectory + 2 * n + n + 2 * (n + 1) + 2


@numba.njit(**JIT)
def _tick(q0, qd0, t0, reference, mode, initial_current, ws, n, p, c, max_iterations,
          tolerance, stats):
    """One MPC step. mode COLD: solve from a constant `initial_current`. mode WARM: if t0 is
    exactly one step after the previous tick, a real-time iteration on the shifted solution;
    otherwise (a missed cycle) the shifted controls are re-simulated and iterated. mode
    RESAMPLE: the reference changed, so it is sampled anew before doing the latter."""
    cur, trial, K, kff, ref_q, ref_qd, flags = _workspace(ws, n)
    dt = c[C_DT]
    contiguous = abs(t0 - flags[0] - dt) < 1e-6 * dt
    flags[0] = t0
    if mode == WARM and contiguous:
        for k in range(n):
            ref_q[k] = ref_q[k + 1]
            ref_qd[k] = ref_qd[k + 1]
        ref_q[n], ref_qd[n] = reference_at(reference, t0 + n * dt)
        if _tick_warm(q0, qd0, cur, trial, K, kff, ref_q, ref_qd, p, c, max_iterations,
                      tolerance, stats):
            flags[1] = 1.0 - flags[1]
        return
    for k in range(n + 1):
        ref_q[k], ref_qd[k] = reference_at(reference, t0 + k * dt)
    U = cur[1]
    if mode == COLD:
        U[:] = initial_current
    else:
        for k in range(n - 1):
            U[k] = U[k + 1]
    if _solve_from_controls(q0, qd0, cur, trial, K, kff, ref_q, ref_qd, p, c, max_iterations,
                            tolerance, stats):
        flags[1] = 1.0 - flags[1]


class SolveResult(NamedTuple):
    status: int
    iterations: int
    cost: float
    rollouts: int = 0  # trajectory simulations, line-search trials included

    @property
    def status_name(self) -> str:
        return STATUS_NAMES[self.status]

    @property
    def ok(self) -> bool:
        return self.status in (CONVERGED, MAX_ITERATIONS)


class IlqrSolver:
    """The compiled solver with its preallocated workspace; the plan (`U`, `X`) persists
    between calls so the MPC can warm start."""

    def __init__(self, settings: OcpSettings, dynamics_params: np.ndarray,
                 cost_params: np.ndarray):
        n = settings.horizon
        self.settings = settings
        self.horizon = n
        self.p = np.ascontiguousarray(dynamics_params, dtype=np.float64)
        self.c = np.ascontiguousarray(cost_params, dtype=np.float64)
        self._ws = np.zeros(workspace_size(n))
        first, second, self.K, _, self.reference_position, self.reference_velocity, \
            self._flags = _workspace(self._ws, n)
        self._buffers = (first, second)
        self.stats = np.zeros(5)

    @property
    def X(self) -> np.ndarray:
        """Predicted states of the current solution, shape (N + 1, 2)."""
        return self._buffers[int(self._flags[1])][0]

    @property
    def U(self) -> np.ndarray:
        """Controls of the current solution (A), shape (N,)."""
        return self._buffers[int(self._flags[1])][1]

    def tick(self, x0: tuple[float, float], t0: float, reference: np.ndarray, mode: int,
             initial_current: float, max_iterations: int) -> SolveResult:
        """Sample the packed reference from t0 and solve (see `_tick` for the modes)."""
        _tick(float(x0[0]), float(x0[1]), float(t0), reference, mode, float(initial_current),
              self._ws, self.horizon, self.p, self.c, max_iterations, self.settings.tolerance,
              self.stats)
        return SolveResult(int(self.stats[0]), int(self.stats[1]), float(self.stats[2]),
                           int(self.stats[4]))
