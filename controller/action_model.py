"""The action model of the paper's problem: one discrete step of the joint and its cost, with
the derivatives iLQR needs (an "action model" as in Crocoddyl: calc and calcDiff of a stage).

Semi-implicit Euler at dt on the model's smooth dynamics (tanh(beta qd) for dry friction):

    qd+ = qd + dt a(q, qd, u),    q+ = q + dt qd+

Registered as jitable and written with numpy ufuncs, so one source serves the compiled solver
(`controller.ilqr`, scalars in registers) and the readable numpy reference
(`controller.ilqr_reference`). The results are named tuples: numba keeps them in registers, and
no caller reads a derivative by position.
"""

from typing import NamedTuple

from numba.extending import register_jitable

from controller.cost import control_cost, control_cost_given, state_cost, state_cost_given
from controller.problem import C_DT, C_FRICTION_SHARPNESS
from model.dynamics import smooth_acceleration


class Step(NamedTuple):
    """The next state and the Jacobians A = dx+/dx (row-major a11 a12 a21 a22), B = dx+/du."""

    q: float
    qd: float
    a11: float
    a12: float
    a21: float
    a22: float
    b1: float
    b2: float


class StageCost(NamedTuple):
    """l(x, u) and its derivatives; the stage cost has no x-x or x-u cross terms."""

    l: float  # noqa: E741 - the optimal-control literature's name for the stage cost
    l_q: float
    l_qd: float
    l_qq: float
    l_qdqd: float
    l_u: float
    l_uu: float


class TerminalCost(NamedTuple):
    l: float  # noqa: E741
    l_q: float
    l_qd: float
    l_qq: float
    l_qdqd: float


@register_jitable
def discrete_step(q, qd, u, p, c) -> Step:
    """x+ and its Jacobians under current u, held over one step c[C_DT]."""
    a, a_q, a_qd, a_u = smooth_acceleration(q, qd, u, p, c[C_FRICTION_SHARPNESS])
    return step_given(q, qd, c[C_DT], a, a_q, a_qd, a_u)


@register_jitable
def step_given(q, qd, dt, a, a_q, a_qd, a_u) -> Step:
    """The semi-implicit Euler step and its Jacobians from the acceleration and its partial
    derivatives (the batched lane kernel computes those with its vectorised maths)."""
    qd_next = qd + dt * a
    return Step(q + dt * qd_next, qd_next, 1.0 + dt * dt * a_q, dt + dt * dt * a_qd, dt * a_q,
                1.0 + dt * a_qd, dt * dt * a_u, dt * a_u)


@register_jitable
def stage_cost(q, qd, u, q_ref, qd_ref, c) -> StageCost:
    ls, ls_q, ls_qd, ls_qq, ls_qdqd = state_cost(q, qd, q_ref, qd_ref, c)
    lc, lc_u, lc_uu = control_cost(u, c)
    return StageCost(ls + lc, ls_q, ls_qd, ls_qq, ls_qdqd, lc_u, lc_uu)


@register_jitable
def stage_cost_given(q, qd, u, q_ref, qd_ref, c, e_position, e_velocity, e_torque) -> StageCost:
    """`stage_cost` from the barriers' exponentials computed by the caller (controller.cost)."""
    ls, ls_q, ls_qd, ls_qq, ls_qdqd = state_cost_given(q, qd, q_ref, qd_ref, c, e_position,
                                                       e_velocity)
    lc, lc_u, lc_uu = control_cost_given(u, c, e_torque)
    return StageCost(ls + lc, ls_q, ls_qd, ls_qq, ls_qdqd, lc_u, lc_uu)


@register_jitable
def terminal_cost_given(q, qd, q_ref, qd_ref, c, e_position, e_velocity) -> TerminalCost:
    ls, ls_q, ls_qd, ls_qq, ls_qdqd = state_cost_given(q, qd, q_ref, qd_ref, c, e_position,
                                                       e_velocity)
    return TerminalCost(ls, ls_q, ls_qd, ls_qq, ls_qdqd)


@register_jitable
def terminal_cost(q, qd, q_ref, qd_ref, c) -> TerminalCost:
    ls, ls_q, ls_qd, ls_qq, ls_qdqd = state_cost(q, qd, q_ref, qd_ref, c)
    return TerminalCost(ls, ls_q, ls_qd, ls_qq, ls_qdqd)
