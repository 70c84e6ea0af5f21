"""Readable numpy iLQR: the reference the compiled solver is checked against, and the
"straightforward numpy" baseline of `bench` (matrices per step, the way one writes it first).

Same problem, line search and action model as `controller.ilqr`: the discrete step and the
cost derivatives come from the same functions (`controller.action_model`), called here on
numpy arrays and scalars.
"""

import numpy as np

from controller import action_model
from controller.cost import control_box


def discrete_step(x: np.ndarray, u: float, p: np.ndarray, c: np.ndarray):
    """The action model's step as vectors: x+, A = dx+/dx, B = dx+/du."""
    s = action_model.discrete_step(x[0], x[1], u, p, c)
    return np.array([s.q, s.qd]), np.array([[s.a11, s.a12], [s.a21, s.a22]]), np.array([s.b1,
                                                                                         s.b2])


def trajectory_cost(X: np.ndarray, U: np.ndarray, ref: np.ndarray, c: np.ndarray) -> float:
    """Stage costs over the horizon (the terminal stage has no control) plus the terminal."""
    running = action_model.stage_cost(X[:-1, 0], X[:-1, 1], U, ref[:-1, 0], ref[:-1, 1], c).l
    terminal = action_model.terminal_cost(X[-1, 0], X[-1, 1], ref[-1, 0], ref[-1, 1], c).l
    return float(np.sum(running) + terminal)


def rollout(x0, U_base, X_base, K, kff, alpha, p, c):
    n = len(U_base)
    X = np.zeros((n + 1, 2))
    U = np.zeros(n)
    A = np.zeros((n, 2, 2))
    B = np.zeros((n, 2))
    X[0] = x0
    for k in range(n):
        U[k] = U_base[k] + alpha * kff[k] + K[k] @ (X[k] - X_base[k])
        X[k + 1], A[k], B[k] = discrete_step(X[k], U[k], p, c)
    return X, U, A, B


def backward(X, U, A, B, ref, c, mu):
    n = len(U)
    stage = action_model.stage_cost(X[:-1, 0], X[:-1, 1], U, ref[:-1, 0], ref[:-1, 1], c)
    lq, lqd, lqq, lqdqd, lu, luu = (stage.l_q, stage.l_qd, stage.l_qq, stage.l_qdqd, stage.l_u,
                                    stage.l_uu)
    terminal = action_model.terminal_cost(X[-1, 0], X[-1, 1], ref[-1, 0], ref[-1, 1], c)
    Vx = np.array([terminal.l_q, terminal.l_qd])
    Vxx = np.diag([terminal.l_qq, terminal.l_qdqd])
    K = np.zeros((n, 2))
    kff = np.zeros(n)
    dv = np.zeros(2)
    for k in range(n - 1, -1, -1):
        Qx = np.array([lq[k], lqd[k]]) + A[k].T @ Vx
        Qu = lu[k] + B[k] @ Vx
        Qxx = np.diag([lqq[k], lqdqd[k]]) + A[k].T @ Vxx @ A[k]
        Quu = luu[k] + B[k] @ Vxx @ B[k]
        Qux = B[k] @ Vxx @ A[k]
        Vreg = Vxx + mu * np.eye(2)
        Quu_r = luu[k] + B[k] @ Vreg @ B[k]
        if Quu_r <= 0:
            return None
        Qux_r = B[k] @ Vreg @ A[k]
        kff[k] = -Qu / Quu_r
        K[k] = -Qux_r / Quu_r
        box = control_box(c)
        if abs(U[k] + kff[k]) > box:  # step clamped to the control box, no feedback there
            kff[k] = np.sign(U[k] + kff[k]) * box - U[k]
            K[k] = 0.0
        Vx = Qx + K[k] * Quu * kff[k] + K[k] * Qu + Qux * kff[k]
        Vxx = Qxx + np.outer(K[k], K[k]) * Quu + np.outer(K[k], Qux) + np.outer(Qux, K[k])
        dv += [kff[k] * Qu, 0.5 * kff[k] ** 2 * Quu]
    return K, kff, dv


def solve(x0, U, ref, p, c, max_iterations, tolerance=1e-6):
    """iLQR from warm start U; returns (X, U, cost, iterations, converged)."""
    n = len(U)
    zeros_k, zeros_x = np.zeros((n, 2)), np.zeros((n + 1, 2))
    X, U, A, B = rollout(np.asarray(x0, float), U, zeros_x, zeros_k, np.zeros(n), 0.0, p, c)
    cost = trajectory_cost(X, U, ref, c)
    mu = 1e-8
    for iteration in range(1, max_iterations + 1):
        result = backward(X, U, A, B, ref, c, mu)
        if result is None:
            mu = max(mu * 10, 1e-6)
            continue
        K, kff, dv = result
        if -dv[0] < tolerance * max(cost, 1.0) * 1e-3:
            return X, U, cost, iteration, True
        alpha = 1.0
        for _ in range(10):
            Xn, Un, An, Bn = rollout(X[0], U, X, K, kff, alpha, p, c)
            new_cost = trajectory_cost(Xn, Un, ref, c)
            if np.isfinite(new_cost) and cost - new_cost > 1e-4 * -(alpha * dv[0]
                                                                   + alpha**2 * dv[1]):
                break
            alpha *= 0.5
        else:
            mu = max(mu * 10, 1e-6)
            continue
        improvement = cost - new_cost
        X, U, A, B, cost = Xn, Un, An, Bn, new_cost
        mu = mu / 10 if mu > 1e-7 else 1e-8
        if improvement < tolerance * max(cost, 1.0):
            return X, U, cost, iteration, True
    return X, U, cost, max_iterations, False
