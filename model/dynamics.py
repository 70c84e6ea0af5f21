"""Forward dynamics of the paper's joint model, its analytic derivatives and an integrator.

All functions are pure and compiled (numba) so that the simulator and the iLQR hot loop call
the very same code. Parameters travel as one flat vector (`ActuatorParameters.packed()`):

    qdd = (drive_gain i - Fv qd - Fs sign(qd) - off - g (MY sin q + MX cos q)) / I
"""

import math

import numba
import numpy as np
from numba.extending import register_jitable

P_DRIVE_GAIN = 0
P_INERTIA = 1  # I = I_m + I_j (+ payload)
P_GRAVITY_MX = 2  # g MX
P_GRAVITY_MY = 3  # g MY
P_VISCOUS = 4  # Fv = Fvm + Fvj
P_DRY = 5  # Fs = Fsm + Fsj
P_OFFSET = 6  # off = off_m + off_j
N_PARAMS = 7


@register_jitable
def gravity_torque(q, p: np.ndarray):
    """g (MY sin q + MX cos q); works on scalars and numpy arrays alike."""
    return p[P_GRAVITY_MY] * np.sin(q) + p[P_GRAVITY_MX] * np.cos(q)


@register_jitable
def smooth_acceleration(q, qd, current, p: np.ndarray, friction_sharpness: float) -> tuple:
    """qdd with sign(qd) replaced by tanh(beta qd) (the paper's choice for a differentiable
    model), and its partial derivatives (dq, dqd, di): everything iLQR needs per step.

    Written with numpy ufuncs and registered as jitable: one source serves the vectorised
    numpy reference (arrays over the horizon) and, compiled into it, the scalar hot loop.
    """
    th = np.tanh(friction_sharpness * qd)
    inv_inertia = 1.0 / p[P_INERTIA]
    sin_q, cos_q = np.sin(q), np.cos(q)
    gravity = p[P_GRAVITY_MY] * sin_q + p[P_GRAVITY_MX] * cos_q
    torque = (p[P_DRIVE_GAIN] * current - p[P_VISCOUS] * qd - p[P_DRY] * th - p[P_OFFSET]
              - gravity)
    d_gravity = p[P_GRAVITY_MY] * cos_q - p[P_GRAVITY_MX] * sin_q
    d_friction = p[P_VISCOUS] + p[P_DRY] * friction_sharpness * (1.0 - th * th)
    return (torque * inv_inertia, -d_gravity * inv_inertia, -d_friction * inv_inertia,
            p[P_DRIVE_GAIN] * inv_inertia)


@numba.njit(cache=True, error_model="numpy")
def step(q: float, qd: float, current: float, p: np.ndarray, dt: float,
         substeps: int) -> tuple:
    """Advance (q, qd) by dt under a constant current, with set-valued dry friction.

    Each substep is semi-implicit: viscous friction by the trapezoidal rule, Coulomb friction
    as the implicit (Moreau) projection that either stops the joint exactly (stiction, when the
    dry friction can absorb the impulse) or removes at most Fs h. This neither chatters around
    qd = 0 nor injects energy, unlike explicit Euler on sign(qd) or a stiff tanh. Gravity is
    taken at the mid-step position (position Verlet).

    Returns q, qd, the mean acceleration of the last substep and the dry-friction torque it
    applied (the joint-torque sensor needs both).
    """
    h = dt / substeps
    inertia = p[P_INERTIA]
    damping = inertia + 0.5 * h * p[P_VISCOUS]
    undamping = inertia - 0.5 * h * p[P_VISCOUS]
    qdd = 0.0
    dry = 0.0
    for _ in range(substeps):
        q_mid = q + 0.5 * h * qd
        drive = p[P_DRIVE_GAIN] * current - p[P_OFFSET] - gravity_torque(q_mid, p)
        free_velocity = (undamping * qd + h * drive) / damping
        max_velocity_change = h * p[P_DRY] / damping
        if abs(free_velocity) <= max_velocity_change:
            new_velocity = 0.0
        else:
            new_velocity = free_velocity - math.copysign(max_velocity_change, free_velocity)
        dry = damping * (free_velocity - new_velocity) / h
        qdd = (new_velocity - qd) / h
        q = q_mid + 0.5 * h * new_velocity
        qd = new_velocity
    return q, qd, qdd, dry


@numba.njit(cache=True, error_model="numpy")
def simulate(q0: float, qd0: float, currents: np.ndarray, p: np.ndarray, dt: float,
             substeps: int) -> np.ndarray:
    """States after each period for a current held constant over each period; row k is the
    state at the end of period k (shape (len(currents), 2))."""
    out = np.empty((currents.shape[0], 2))
    q, qd = q0, qd0
    for k in range(currents.shape[0]):
        q, qd, _, _ = step(q, qd, currents[k], p, dt, substeps)
        out[k, 0] = q
        out[k, 1] = qd
    return out


def rest_position(p: np.ndarray) -> float:
    """The hanging equilibrium: gravity torque zero with positive stiffness, i.e. the angle at
    which MY sin q + MX cos q = 0 closest to q = 0."""
    return -math.atan2(p[P_GRAVITY_MX], p[P_GRAVITY_MY])
