"""Compiled iLQR for the 2-state, 1-input actuator problem: the hot loop of the MPC.

Same algorithm as `ilqr_reference` (read that one first), written out in scalars so numba
keeps everything in registers: semi-implicit Euler discretisation of the model's smooth
dynamics, exact cost derivatives, Tassa-style regularisation on the value function,
backtracking line search on the actual cost, convergence on relative cost decrease.
Trajectories are double-buffered so a line-search rollout also leaves the derivatives the
next backward pass needs.
"""

from dataclasses import dataclass

import numba
import numpy as np

from controller.cost import control_cost, state_cost
from controller.problem import C_DT, C_FRICTION_SHARPNESS, OcpSettings
from model.dynamics import smooth_acceleration

CONVERGED = 0
MAX_ITERATIONS = 1
LINE_SEARCH_FAILED = 2
NOT_FINITE = 3
STATUS_NAMES = ("converged", "max_iterations", "line_search_failed", "not_finite")

MU_MIN = 1e-8
MU_MAX = 1e10
ARMIJO = 1e-4
LINE_SEARCH_STEPS = 10  # alpha = 1, 1/2, ..., 1/512


@numba.njit(cache=True)
def _rollout(q0, qd0, U_base, X_base, K, kff, alpha, closed_loop, X, U, A, B, LX, LXX, LU,
             LUU, ref_q, ref_qd, p, c):
    """Simulate the policy u = U_base + alpha kff + K (x - X_base) from x0, storing the
    trajectory, its linearisation and cost derivatives; returns the total cost."""
    n = U.shape[0]
    dt = c[C_DT]
    beta = c[C_FRICTION_SHARPNESS]
    q, qd = q0, qd0
    total = 0.0
    for k in range(n):
        u = U_base[k]
        if closed_loop:
            u += alpha * kff[k] + K[k, 0] * (q - X_base[k, 0]) + K[k, 1] * (qd - X_base[k, 1])
        X[k, 0] = q
        X[k, 1] = qd
        U[k] = u
        ls, ls_q, ls_qd, ls_qq, ls_qdqd = state_cost(q, qd, ref_q[k], ref_qd[k], c)
        lc, lc_u, lc_uu = control_cost(u, c)
        total += ls + lc
        LX[k, 0] = ls_q
        LX[k, 1] = ls_qd
        LXX[k, 0] = ls_qq
        LXX[k, 1] = ls_qdqd
        LU[k] = lc_u
        LUU[k] = lc_uu
        a, a_q, a_qd, a_u = smooth_acceleration(q, qd, u, p, beta)
        # semi-implicit Euler: qd+ = qd + dt a, q+ = q + dt qd+
        A[k, 0] = 1.0 + dt * dt * a_q
        A[k, 1] = dt + dt * dt * a_qd
        A[k, 2] = dt * a_q
        A[k, 3] = 1.0 + dt * a_qd
        B[k, 0] = dt * dt * a_u
        B[k, 1] = dt * a_u
        qd = qd + dt * a
        q = q + dt * qd
    X[n, 0] = q
    X[n, 1] = qd
    ls, ls_q, ls_qd, ls_qq, ls_qdqd = state_cost(q, qd, ref_q[n], ref_qd[n], c)
    LX[n, 0] = ls_q
    LX[n, 1] = ls_qd
    LXX[n, 0] = ls_qq
    LXX[n, 1] = ls_qdqd
    total += ls
    if not np.isfinite(total):
        return np.inf
    return total


@numba.njit(cache=True)
def _backward(A, B, LX, LXX, LU, LUU, mu, K, kff):
    """Riccati sweep; returns (ok, dV1, dV2) with the expected cost change
    alpha dV1 + alpha^2 dV2 of a step alpha along the new policy."""
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
            return False, 0.0, 0.0
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
    return True, dv1, dv2


@numba.njit(cache=True)
def _solve(q0, qd0, U, X, K, kff, work_x, work_u, A, B, LX, LXX, LU, LUU, A2, B2, LX2,
           LXX2, LU2, LUU2, ref_q, ref_qd, p, c, max_iterations, tolerance, stats):
    """iLQR from the warm start U (in place). stats <- [status, iterations, cost, mu]."""
    cost = _rollout(q0, qd0, U, X, K, kff, 0.0, False, X, U, A, B, LX, LXX, LU, LUU, ref_q,
                    ref_qd, p, c)
    if not np.isfinite(cost):
        stats[0], stats[1], stats[2], stats[3] = NOT_FINITE, 0, cost, MU_MIN
        return
    mu = MU_MIN
    status = MAX_ITERATIONS
    iteration = 0
    while iteration < max_iterations:
        iteration += 1
        ok, dv1, dv2 = _backward(A, B, LX, LXX, LU, LUU, mu, K, kff)
        if not ok:
            mu = max(mu * 10.0, 1e-6)
            if mu > MU_MAX:
                status = LINE_SEARCH_FAILED
                break
            continue
        if -dv1 < tolerance * max(cost, 1.0) * 1e-3:
            status = CONVERGED  # the model predicts no meaningful improvement is left
            break
        accepted = False
        alpha = 1.0
        new_cost = cost
        for _ in range(LINE_SEARCH_STEPS):
            new_cost = _rollout(q0, qd0, U, X, K, kff, alpha, True, work_x, work_u, A2, B2,
                                LX2, LXX2, LU2, LUU2, ref_q, ref_qd, p, c)
            expected = -(alpha * dv1 + alpha * alpha * dv2)
            if np.isfinite(new_cost) and cost - new_cost > ARMIJO * expected:
                accepted = True
                break
            alpha *= 0.5
        if not accepted:
            mu = max(mu * 10.0, 1e-6)
            if mu > MU_MAX:
                status = LINE_SEARCH_FAILED
                break
            continue
        X[:, :] = work_x
        U[:] = work_u
        A[:, :] = A2
        B[:, :] = B2
        LX[:, :] = LX2
        LXX[:, :] = LXX2
        LU[:] = LU2
        LUU[:] = LUU2
        improvement = cost - new_cost
        cost = new_cost
        mu = mu / 10.0 if mu > MU_MIN * 10.0 else MU_MIN
        if improvement < tolerance * max(cost, 1.0):
            status = CONVERGED
            break
    stats[0], stats[1], stats[2], stats[3] = status, iteration, cost, mu


@dataclass
class SolveResult:
    status: int
    iterations: int
    cost: float

    @property
    def status_name(self) -> str:
        return STATUS_NAMES[self.status]

    @property
    def ok(self) -> bool:
        return self.status in (CONVERGED, MAX_ITERATIONS)


class IlqrSolver:
    """Preallocated workspace around the compiled solver; `U`, `X`, `K` persist between calls
    so the MPC can warm start."""

    def __init__(self, settings: OcpSettings, dynamics_params: np.ndarray,
                 cost_params: np.ndarray):
        n = settings.horizon
        self.settings = settings
        self.p = np.ascontiguousarray(dynamics_params, dtype=np.float64)
        self.c = np.ascontiguousarray(cost_params, dtype=np.float64)
        self.U = np.zeros(n)
        self.X = np.zeros((n + 1, 2))
        self.K = np.zeros((n, 2))
        self.kff = np.zeros(n)
        self._work_x = np.zeros((n + 1, 2))
        self._work_u = np.zeros(n)
        self._buffers = [np.zeros((n, 4)), np.zeros((n, 2)), np.zeros((n + 1, 2)),
                         np.zeros((n + 1, 2)), np.zeros(n), np.zeros(n)]
        self._buffers2 = [np.zeros_like(b) for b in self._buffers]
        self.stats = np.zeros(4)

    def solve(self, x0: tuple[float, float], ref_q: np.ndarray, ref_qd: np.ndarray,
              max_iterations: int) -> SolveResult:
        _solve(float(x0[0]), float(x0[1]), self.U, self.X, self.K, self.kff, self._work_x,
               self._work_u, *self._buffers, *self._buffers2, ref_q, ref_qd, self.p, self.c,
               max_iterations, self.settings.tolerance, self.stats)
        return SolveResult(int(self.stats[0]), int(self.stats[1]), float(self.stats[2]))
