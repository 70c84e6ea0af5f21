"""Forward dynamics of the paper's joint model, with the optional effects of `model.effects`,
their analytic derivatives and an integrator.

All functions are pure and compiled (numba) so that the simulator and the iLQR hot loop call
the very same code. Parameters travel as one flat vector (`ActuatorParameters.packed()`):

    qdd = (drive_gain i - Fv qd - F(q, qd) sign(qd) - off - G(q) - R(q)) / I
    G(q) = g (MY sin q + MX cos q)                                  gravity
    F(q, qd) = Fs + E exp(-(qd / vs)^2) + mu |G(q)|                 dry friction: Coulomb,
                                                                    Stribeck, load-dependent
    R(q) = a sin(w q) + b cos(w q)                                  position ripple

With the effect parameters at zero (the default) this is the paper's model exactly.
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
P_STRIBECK_EXTRA = 7  # E: breakaway minus Coulomb friction (N.m)
P_STRIBECK_VELOCITY = 8  # vs (rad/s)
P_RIPPLE_SIN = 9  # a (N.m)
P_RIPPLE_COS = 10  # b (N.m)
P_RIPPLE_WAVENUMBER = 11  # w = 2 pi x cycles per rad
P_LOAD_FRICTION = 12  # mu: dry friction per N.m of gravity load
N_PARAMS = 13
LOAD_SMOOTHING = 0.05  # N.m: |G| ~ sqrt(G^2 + 0.05^2) keeps the derivative finite at G = 0


@register_jitable
def gravity_torque(q, p: np.ndarray):
    """g (MY sin q + MX cos q); works on scalars and numpy arrays alike."""
    return p[P_GRAVITY_MY] * np.sin(q) + p[P_GRAVITY_MX] * np.cos(q)


@register_jitable
def ripple_torque(q, p: np.ndarray):
    w = p[P_RIPPLE_WAVENUMBER]
    return p[P_RIPPLE_SIN] * np.sin(w * q) + p[P_RIPPLE_COS] * np.cos(w * q)


@register_jitable
def dry_friction_level(q, qd, p: np.ndarray):
    """F(q, qd) >= 0: the dry friction's magnitude (Coulomb, Stribeck and load parts)."""
    level = p[P_DRY] + 0.0 * qd
    if p[P_STRIBECK_EXTRA] != 0.0:
        level = level + p[P_STRIBECK_EXTRA] * np.exp(-(qd / p[P_STRIBECK_VELOCITY]) ** 2)
    if p[P_LOAD_FRICTION] != 0.0:
        level = level + p[P_LOAD_FRICTION] * np.abs(gravity_torque(q, p))
    return level


@register_jitable
def smooth_acceleration(q, qd, current, p: np.ndarray, friction_sharpness: float) -> tuple:
    """qdd with sign(qd) replaced by tanh(beta qd) (the paper's choice for a differentiable
    model), and its partial derivatives (dq, dqd, di): everything iLQR needs per step.

    Written with numpy ufuncs and registered as jitable: one source serves the vectorised
    numpy reference (arrays over the horizon) and, compiled into it, the scalar hot loop.
    Effects whose parameters are zero cost nothing.
    """
    th = np.tanh(friction_sharpness * qd)
    inv_inertia = 1.0 / p[P_INERTIA]
    sin_q, cos_q = np.sin(q), np.cos(q)
    gravity = p[P_GRAVITY_MY] * sin_q + p[P_GRAVITY_MX] * cos_q
    d_gravity = p[P_GRAVITY_MY] * cos_q - p[P_GRAVITY_MX] * sin_q
    level = p[P_DRY] + 0.0 * qd
    d_level_dqd = 0.0 * qd
    d_level_dq = 0.0 * q
    if p[P_STRIBECK_EXTRA] != 0.0:
        vs = p[P_STRIBECK_VELOCITY]
        bump = p[P_STRIBECK_EXTRA] * np.exp(-(qd / vs) ** 2)
        level = level + bump
        d_level_dqd = d_level_dqd - 2.0 * qd / (vs * vs) * bump
    if p[P_LOAD_FRICTION] != 0.0:
        smooth_abs = np.sqrt(gravity * gravity + LOAD_SMOOTHING**2)
        level = level + p[P_LOAD_FRICTION] * smooth_abs
        d_level_dq = d_level_dq + p[P_LOAD_FRICTION] * gravity * d_gravity / smooth_abs
    ripple = 0.0 * q
    d_ripple = 0.0 * q
    if p[P_RIPPLE_SIN] != 0.0 or p[P_RIPPLE_COS] != 0.0:
        w = p[P_RIPPLE_WAVENUMBER]
        ripple = p[P_RIPPLE_SIN] * np.sin(w * q) + p[P_RIPPLE_COS] * np.cos(w * q)
        d_ripple = w * (p[P_RIPPLE_SIN] * np.cos(w * q) - p[P_RIPPLE_COS] * np.sin(w * q))
    torque = (p[P_DRIVE_GAIN] * current - p[P_VISCOUS] * qd - level * th - p[P_OFFSET]
              - gravity - ripple)
    d_friction = (p[P_VISCOUS] + level * friction_sharpness * (1.0 - th * th)
                  + d_level_dqd * th)
    return (torque * inv_inertia, -(d_gravity + d_ripple + d_level_dq * th) * inv_inertia,
            -d_friction * inv_inertia, p[P_DRIVE_GAIN] * inv_inertia)


@numba.njit(cache=True, error_model="numpy")
def step(q: float, qd: float, current: float, p: np.ndarray, dt: float,
         substeps: int) -> tuple:
    """Advance (q, qd) by dt under a constant current, with set-valued dry friction.

    Each substep is semi-implicit: viscous friction by the trapezoidal rule, dry friction as the
    implicit (Moreau) projection that either stops the joint exactly (stiction, when the dry
    friction can absorb the impulse) or removes at most F h. This neither chatters around qd = 0
    nor injects energy, unlike explicit Euler on sign(qd) or a stiff tanh. Gravity, ripple and
    the friction level are taken at the mid-step position (position Verlet), the level at the
    substep's starting speed (at rest: the breakaway level).

    Returns q, qd, the acceleration and the dry-friction torque of the last substep, and the
    friction level it was bounded by (the joint-torque sensor needs them).
    """
    h = dt / substeps
    inertia = p[P_INERTIA]
    damping = inertia + 0.5 * h * p[P_VISCOUS]
    undamping = inertia - 0.5 * h * p[P_VISCOUS]
    qdd = 0.0
    dry = 0.0
    level = p[P_DRY]
    for _ in range(substeps):
        q_mid = q + 0.5 * h * qd
        drive = (p[P_DRIVE_GAIN] * current - p[P_OFFSET] - gravity_torque(q_mid, p)
                 - ripple_torque(q_mid, p))
        level = dry_friction_level(q_mid, qd, p)
        free_velocity = (undamping * qd + h * drive) / damping
        max_velocity_change = h * level / damping
        if abs(free_velocity) <= max_velocity_change:
            new_velocity = 0.0
        else:
            new_velocity = free_velocity - math.copysign(max_velocity_change, free_velocity)
        dry = damping * (free_velocity - new_velocity) / h
        qdd = (new_velocity - qd) / h
        q = q_mid + 0.5 * h * new_velocity
        qd = new_velocity
    return q, qd, qdd, dry, level


@numba.njit(cache=True, error_model="numpy")
def simulate(q0: float, qd0: float, currents: np.ndarray, p: np.ndarray, dt: float,
             substeps: int) -> np.ndarray:
    """States after each period for a current held constant over each period; row k is the
    state at the end of period k (shape (len(currents), 2))."""
    out = np.empty((currents.shape[0], 2))
    q, qd = q0, qd0
    for k in range(currents.shape[0]):
        q, qd, _, _, _ = step(q, qd, currents[k], p, dt, substeps)
        out[k, 0] = q
        out[k, 1] = qd
    return out


def rest_position(p: np.ndarray) -> float:
    """The hanging equilibrium: gravity torque zero with positive stiffness, i.e. the angle at
    which MY sin q + MX cos q = 0 closest to q = 0."""
    return -math.atan2(p[P_GRAVITY_MX], p[P_GRAVITY_MY])
