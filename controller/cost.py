"""Stage cost of the paper's problem (eq. 14) with exact first and second derivatives.

    l = Qq (q - q*)^2 + Qv (qd - qd*)^2 + R u^2 + Wq Cs(q)^2 + Wv Cs(qd)^2 + P Cs(G u)^2
    Cs(c) = exp(alpha (c - c_max)) + exp(alpha (c_min - c))

The barrier Hessian 2 w (Cs'^2 + Cs Cs'') is positive, so it is used whole instead of the
Gauss-Newton part alone. Written with numpy ufuncs and registered as jitable: one source for
the vectorised reference and, compiled into it, for the hot loop.
"""

import numpy as np
from numba.extending import register_jitable

from controller.problem import (
    C_ALPHA_POSITION,
    C_ALPHA_TORQUE,
    C_ALPHA_VELOCITY,
    C_DRIVE_GAIN,
    C_P_TORQUE,
    C_POSITION_MAX,
    C_POSITION_MIN,
    C_Q_POSITION,
    C_Q_VELOCITY,
    C_R_CURRENT,
    C_TORQUE_MAX,
    C_VELOCITY_MAX,
    C_W_POSITION,
    C_W_VELOCITY,
)

EXPONENT_CAP = 200.0  # keeps exp() finite for absurd iterates; exp(200)^2 ~ 1e173


@register_jitable
def barrier(value, lower, upper, sharpness, weight) -> tuple:
    """weight Cs(value)^2 and its first and second derivatives."""
    e_high = np.exp(np.minimum(sharpness * (value - upper), EXPONENT_CAP))
    e_low = np.exp(np.minimum(sharpness * (lower - value), EXPONENT_CAP))
    cs = e_high + e_low
    d_cs = sharpness * (e_high - e_low)
    return (weight * cs * cs, 2.0 * weight * cs * d_cs,
            2.0 * weight * (d_cs * d_cs + sharpness * sharpness * cs * cs))


@register_jitable
def state_cost(q, qd, q_ref, qd_ref, c: np.ndarray) -> tuple:
    """Tracking and state barriers: l, l_q, l_qd, l_qq, l_qdqd (no cross term)."""
    eq, ev = q - q_ref, qd - qd_ref
    bq, bq_d, bq_dd = barrier(q, c[C_POSITION_MIN], c[C_POSITION_MAX], c[C_ALPHA_POSITION],
                              c[C_W_POSITION])
    bv, bv_d, bv_dd = barrier(qd, -c[C_VELOCITY_MAX], c[C_VELOCITY_MAX], c[C_ALPHA_VELOCITY],
                              c[C_W_VELOCITY])
    return (c[C_Q_POSITION] * eq * eq + c[C_Q_VELOCITY] * ev * ev + bq + bv,
            2.0 * c[C_Q_POSITION] * eq + bq_d,
            2.0 * c[C_Q_VELOCITY] * ev + bv_d,
            2.0 * c[C_Q_POSITION] + bq_dd,
            2.0 * c[C_Q_VELOCITY] + bv_dd)


@register_jitable
def control_cost(u, c: np.ndarray) -> tuple:
    """Effort and the motor-torque barrier on drive_gain x current: l, l_u, l_uu."""
    gain = c[C_DRIVE_GAIN]
    bt, bt_d, bt_dd = barrier(gain * u, -c[C_TORQUE_MAX], c[C_TORQUE_MAX], c[C_ALPHA_TORQUE],
                              c[C_P_TORQUE])
    return (c[C_R_CURRENT] * u * u + bt, 2.0 * c[C_R_CURRENT] * u + gain * bt_d,
            2.0 * c[C_R_CURRENT] + gain * gain * bt_dd)

