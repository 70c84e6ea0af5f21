"""Stage cost of the paper's problem (eq. 14) with exact first and second derivatives.

    l = Qq (q - q*)^2 + Qv (qd - qd*)^2 + R u^2 + Wq Cs(q)^2 + Wv Cs(qd)^2 + P Cs(G u)^2
    Cs(c) = exp(alpha (c - c_max)) + exp(alpha (c_min - c))

The barrier Hessian 2 w (Cs'^2 + Cs Cs'') is positive, so it is used whole instead of the
Gauss-Newton part alone. Written with numpy ufuncs and registered as jitable: one source for
the vectorised reference and, compiled into it, for the hot loop. The `*_given` forms take the
exponentials from the caller, so the batched lane kernel can bring its own vectorised exp
(controller.lane_math) and still share this algebra.
"""

import numpy as np
from numba.extending import register_jitable

from controller.problem import (
    C_ALPHA_POSITION,
    C_ALPHA_TORQUE,
    C_ALPHA_VELOCITY,
    C_DRIVE_GAIN,
    C_E_POSITION_HIGH,
    C_E_POSITION_LOW,
    C_E_TORQUE_HIGH,
    C_E_TORQUE_LOW,
    C_E_VELOCITY_HIGH,
    C_E_VELOCITY_LOW,
    C_P_TORQUE,
    C_Q_POSITION,
    C_Q_VELOCITY,
    C_R_CURRENT,
    C_TORQUE_MAX,
    C_W_POSITION,
    C_W_VELOCITY,
)


@register_jitable
def barrier(value, sharpness, weight, exp_high, exp_low) -> tuple:
    """weight Cs(value)^2 and its first and second derivatives.

    One exp per call: exp(a (v - hi)) = exp(a v) exp_high and exp(a (lo - v)) = exp_low /
    exp(a v), with exp_high = exp(-a hi) and exp_low = exp(a lo) precomputed by pack_cost.
    Absurd iterates overflow to inf, which the solver's line search rejects.
    """
    return barrier_given(np.exp(sharpness * value), sharpness, weight, exp_high, exp_low)


@register_jitable
def barrier_given(e, sharpness, weight, exp_high, exp_low) -> tuple:
    """`barrier` from e = exp(sharpness value) computed by the caller: the batched lane kernel
    (controller.lanes) brings an exp the compiler vectorises, and the algebra stays here."""
    e_high = e * exp_high
    e_low = exp_low / e
    cs = e_high + e_low
    d_cs = sharpness * (e_high - e_low)
    return (weight * cs * cs, 2.0 * weight * cs * d_cs,
            2.0 * weight * (d_cs * d_cs + sharpness * sharpness * cs * cs))


@register_jitable
def state_cost(q, qd, q_ref, qd_ref, c: np.ndarray) -> tuple:
    """Tracking and state barriers: l, l_q, l_qd, l_qq, l_qdqd (no cross term)."""
    return state_cost_given(q, qd, q_ref, qd_ref, c, np.exp(c[C_ALPHA_POSITION] * q),
                            np.exp(c[C_ALPHA_VELOCITY] * qd))


@register_jitable
def state_cost_given(q, qd, q_ref, qd_ref, c, e_position, e_velocity) -> tuple:
    """`state_cost` from exp(alpha_q q) and exp(alpha_qd qd) computed by the caller."""
    eq, ev = q - q_ref, qd - qd_ref
    bq, bq_d, bq_dd = barrier_given(e_position, c[C_ALPHA_POSITION], c[C_W_POSITION],
                                    c[C_E_POSITION_HIGH], c[C_E_POSITION_LOW])
    bv, bv_d, bv_dd = barrier_given(e_velocity, c[C_ALPHA_VELOCITY], c[C_W_VELOCITY],
                                    c[C_E_VELOCITY_HIGH], c[C_E_VELOCITY_LOW])
    return (c[C_Q_POSITION] * eq * eq + c[C_Q_VELOCITY] * ev * ev + bq + bv,
            2.0 * c[C_Q_POSITION] * eq + bq_d,
            2.0 * c[C_Q_VELOCITY] * ev + bv_d,
            2.0 * c[C_Q_POSITION] + bq_dd,
            2.0 * c[C_Q_VELOCITY] + bv_dd)


@register_jitable
def control_cost(u, c: np.ndarray) -> tuple:
    """Effort and the motor-torque barrier on drive_gain x current: l, l_u, l_uu."""
    return control_cost_given(u, c, np.exp(c[C_ALPHA_TORQUE] * (c[C_DRIVE_GAIN] * u)))


@register_jitable
def control_cost_given(u, c, e_torque) -> tuple:
    """`control_cost` from exp(alpha_tau drive_gain u) computed by the caller."""
    gain = c[C_DRIVE_GAIN]
    bt, bt_d, bt_dd = barrier_given(e_torque, c[C_ALPHA_TORQUE], c[C_P_TORQUE],
                                    c[C_E_TORQUE_HIGH], c[C_E_TORQUE_LOW])
    return (c[C_R_CURRENT] * u * u + bt, 2.0 * c[C_R_CURRENT] * u + gain * bt_d,
            2.0 * c[C_R_CURRENT] + gain * gain * bt_dd)



BARRIER_REACH = 4.0  # alpha x overshoot where the solver's control box sits: Cs = e^4


@register_jitable
def control_box(c) -> float:
    """Half-width (A) of the box the solver keeps its control steps in: the current where the
    motor-torque barrier has risen to e^4, far outside where an optimum can sit.

    With the paper's tiny effort weight R, the quadratic model alone proposes steps of hundreds
    of amperes that the barrier's actual cost then rejects, and the line search crawls. Clamping
    each stage's step to this box (control-limited DDP, Tassa 2014) keeps the model honest. No
    box without the barrier."""
    if c[C_P_TORQUE] <= 0.0:
        return np.inf
    return (c[C_TORQUE_MAX] + BARRIER_REACH / c[C_ALPHA_TORQUE]) / c[C_DRIVE_GAIN]
