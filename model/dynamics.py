"""The joint's physics, once: forward dynamics (smooth for the optimiser, set-valued for the
integrator) and inverse dynamics, with the effects of `model.effects`.

    I qdd = drive_gain (i - L(i)) - Fv qd - F(q, qd) sign(qd) - off - G(q) - T(q, qd)
    G(q) = g (MY sin q + MX cos q)                                  gravity (payload included)
    F(q, qd) = Fs + the effects' dry-friction levels                 dry friction magnitude
    T(q, qd) = the effects' torques                                  e.g. position ripple
    L(i) = the drive-side effects' current losses                    e.g. saturation
    joint torque (sensor) = I_j qdd + G(q) + Fvj qd + Fsj sign(qd) + off_j

With no effect enabled this is the paper's model exactly. All functions are pure and written
with numpy ufuncs; the ones registered as jitable are compiled into the simulator and the iLQR
hot loop and also run vectorised on numpy arrays (the numpy iLQR reference, identification,
model-gap), so every user runs the same code. Parameters travel as one flat vector
(`ActuatorParameters.packed()`) whose layout is below: the base model, then one block per
effect of the registry (`model.effects.PHYSICS`, in its order), then the joint side.
"""

import math
from pathlib import Path

import numba
import numpy as np
from numba.extending import register_jitable

from model import effects
from model.compiled_cache import drop_stale
from model.effects import DRIVE, PHYSICS, TIME_DEPENDENT, TRANSMISSION

# compiled code that chained an older registry (other slots, other terms) must not load
drop_stale(Path(__file__).parent / "__pycache__", "dynamics.*.nb[ic]",
           [Path(effects.__file__)], "dynamics.effects.sha256")

# 50 us integration substeps at the 1 ms drive period: within one encoder count of 1000
# substeps (tests/test_dynamics.py); every simulation of the joint uses it.
SUBSTEPS = 20

P_DRIVE_GAIN = 0
P_INERTIA = 1  # I = I_m + I_j (+ payload)
P_GRAVITY_MX = 2  # g MX
P_GRAVITY_MY = 3  # g MY
P_VISCOUS = 4  # Fv = Fvm + Fvj
P_DRY = 5  # Fs = Fsm + Fsj
P_OFFSET = 6  # off = off_m + off_j
EFFECT_OFFSET: dict[str, int] = {}  # effect name -> first slot of its block
_slot = P_OFFSET + 1
for _effect in PHYSICS:
    EFFECT_OFFSET[_effect.name] = _slot
    _slot += _effect.slots
# the joint side of the torque sensor (only the inverse dynamics read them)
P_LINK_INERTIA = _slot  # I_j (+ payload)
P_VISCOUS_JOINT = _slot + 1  # Fvj
P_DRY_JOINT = _slot + 2  # Fsj
P_OFFSET_JOINT = _slot + 3  # off_j
N_PARAMS = _slot + 4


def _chain(blocks: list) -> object:
    """One jitable function summing the terms of the given (term, first slot) pairs. Built by
    closures at import time, so the compiled code calls each effect's term directly (numba
    inlines them) and no loop over effect objects runs per step."""
    if not blocks:
        @register_jitable
        def nothing(q, qd, p, coulomb, gravity, d_gravity):
            zero = 0.0 * q + 0.0 * qd
            return zero, zero, zero, zero, zero, zero

        return nothing
    (term, k), rest = blocks[0], _chain(blocks[1:])

    @register_jitable
    def chained(q, qd, p, coulomb, gravity, d_gravity):
        a = term(q, qd, p, k, coulomb, gravity, d_gravity)
        b = rest(q, qd, p, coulomb, gravity, d_gravity)
        return a[0] + b[0], a[1] + b[1], a[2] + b[2], a[3] + b[3], a[4] + b[4], a[5] + b[5]

    return chained


def _chain_losses(blocks: list) -> object:
    """One jitable function summing the current losses of the drive-side effects' (term,
    first slot) pairs, built like `_chain`."""
    if not blocks:
        @register_jitable
        def nothing(current, p):
            return 0.0 * current, 0.0 * current

        return nothing
    (term, k), rest = blocks[0], _chain_losses(blocks[1:])

    @register_jitable
    def chained(current, p):
        a = term(current, p, k)
        b = rest(current, p)
        return a[0] + b[0], a[1] + b[1]

    return chained


# (level, d level/dq, d level/dqd, torque, d torque/dq, d torque/dqd) of every transmission
# effect, and (loss, d loss/di) of every drive-side one
effect_terms = _chain([(effect.term, EFFECT_OFFSET[effect.name]) for effect in TRANSMISSION])
current_losses = _chain_losses([(effect.current_term, EFFECT_OFFSET[effect.name])
                                for effect in DRIVE])


@register_jitable
def motor_torque(current, p: np.ndarray):
    """The torque a current makes at joint level, drive_gain (i - L(i)): what the inverse
    dynamics' motor torque is compared with. Works on scalars and numpy arrays alike."""
    loss, _ = current_losses(current, p)
    return p[P_DRIVE_GAIN] * (current - loss)


def drifts(p: np.ndarray) -> bool:
    """Whether these packed parameters carry an effect that changes with elapsed time."""
    return any(p[EFFECT_OFFSET[effect.name]] != 0.0 for effect in TIME_DEPENDENT)


def at_elapsed(p: np.ndarray, elapsed: float) -> np.ndarray:
    """The packed parameters `elapsed` seconds after the start (a copy; the same when nothing
    drifts). Time-dependent effects are set here, outside the compiled code, which treats
    them as constant over a step or a prediction horizon."""
    if not drifts(p):
        return p
    out = p.copy()
    for effect in TIME_DEPENDENT:
        k = EFFECT_OFFSET[effect.name]
        effect.at_elapsed(out[k:k + effect.slots], elapsed)
    return out


@register_jitable
def gravity_torque(q, p: np.ndarray):
    """g (MY sin q + MX cos q); works on scalars and numpy arrays alike."""
    return p[P_GRAVITY_MY] * np.sin(q) + p[P_GRAVITY_MX] * np.cos(q)


@register_jitable
def gravity_and_slope(q, p: np.ndarray) -> tuple:
    sin_q, cos_q = np.sin(q), np.cos(q)
    return (p[P_GRAVITY_MY] * sin_q + p[P_GRAVITY_MX] * cos_q,
            p[P_GRAVITY_MY] * cos_q - p[P_GRAVITY_MX] * sin_q)


@register_jitable
def smooth_acceleration(q, qd, current, p: np.ndarray, friction_sharpness: float) -> tuple:
    """qdd with sign(qd) replaced by tanh(beta qd) (the paper's choice for a differentiable
    model), and its partial derivatives (dq, dqd, di): everything iLQR needs per step.
    Effects whose parameters are zero cost one comparison each."""
    th = np.tanh(friction_sharpness * qd)
    inv_inertia = 1.0 / p[P_INERTIA]
    gravity, d_gravity = gravity_and_slope(q, p)
    level, level_q, level_qd, extra, extra_q, extra_qd = effect_terms(
        q, qd, p, p[P_DRY], gravity, d_gravity)
    level = level + p[P_DRY]
    loss, d_loss = current_losses(current, p)
    torque = (p[P_DRIVE_GAIN] * (current - loss) - p[P_VISCOUS] * qd - level * th - p[P_OFFSET]
              - gravity - extra)
    d_friction = (p[P_VISCOUS] + level * friction_sharpness * (1.0 - th * th)
                  + level_qd * th + extra_qd)
    return (torque * inv_inertia, -(d_gravity + extra_q + level_q * th) * inv_inertia,
            -d_friction * inv_inertia, p[P_DRIVE_GAIN] * (1.0 - d_loss) * inv_inertia)


@register_jitable
def inverse_dynamics(q, qd, qdd, direction, p: np.ndarray) -> tuple:
    """(motor torque, joint torque) that produce the motion (q, qd, qdd): the motor torque is
    what the current must make (`motor_torque`), the joint torque what the torque sensor sees (the
    link-side share of inertia and friction; gravity and payload in full). `direction` is the
    dry friction's: sign(qd) while sliding, the held share of the level when stuck (the
    integrator's dry / level), or a filtered sign where the signals are filtered. Runs
    vectorised on numpy arrays (recordings); `sample_inverse_dynamics` is the same function
    compiled for one sample (every drive cycle)."""
    gravity, d_gravity = gravity_and_slope(q, p)
    level, _, _, extra, _, _ = effect_terms(q, qd, p, p[P_DRY], gravity, d_gravity)
    motor = (p[P_INERTIA] * qdd + gravity + p[P_VISCOUS] * qd + (p[P_DRY] + level) * direction
             + p[P_OFFSET] + extra)
    joint = (p[P_LINK_INERTIA] * qdd + gravity + p[P_VISCOUS_JOINT] * qd
             + p[P_DRY_JOINT] * direction + p[P_OFFSET_JOINT])
    return motor, joint


# the same function compiled for scalars: 1-2 us per call instead of ~25 us of numpy on floats
sample_inverse_dynamics = numba.njit(cache=True, error_model="numpy")(inverse_dynamics)


@numba.njit(cache=True, error_model="numpy")
def step(q: float, qd: float, current: float, p: np.ndarray, dt: float,
         substeps: int) -> tuple:
    """Advance (q, qd) by dt under a constant current, with set-valued dry friction.

    Each substep is semi-implicit: viscous friction by the trapezoidal rule, dry friction as the
    implicit (Moreau) projection that either stops the joint exactly (stiction, when the dry
    friction can absorb the impulse) or removes at most F h. This neither chatters around qd = 0
    nor injects energy, unlike explicit Euler on sign(qd) or a stiff tanh. Gravity, the
    effects' torques and the friction level are taken at the mid-step position (position
    Verlet), the level at the substep's starting speed (at rest: the breakaway level) and never
    below zero (a magnitude).

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
    made = motor_torque(current, p)
    for _ in range(substeps):
        q_mid = q + 0.5 * h * qd
        gravity, d_gravity = gravity_and_slope(q_mid, p)
        extra_level, _, _, extra, _, _ = effect_terms(q_mid, qd, p, p[P_DRY], gravity,
                                                      d_gravity)
        level = max(p[P_DRY] + extra_level, 0.0)
        drive = made - p[P_OFFSET] - gravity - extra
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
def step_sensed(q: float, qd: float, current: float, p_motion: np.ndarray, p: np.ndarray,
                dt: float, substeps: int) -> tuple:
    """`step` under `p_motion` (the joint's parameters, or with a holding brake's friction
    added), then the joint torque of its last substep under `p` (the inverse dynamics' joint
    side): what a drive's cycle needs, in one compiled call instead of two. Sliding, the
    joint carries its own Coulomb part (Fsj); stuck, its share of the holding friction (the
    direction is the share of the level in use).

    Returns q, qd, the dry-friction torque and its level (the next call's state), and the
    joint torque."""
    q, qd, qdd, dry, level = step(q, qd, current, p_motion, dt, substeps)
    direction = dry / level if level > 0 else 0.0
    _, joint = inverse_dynamics(q, qd, qdd, direction, p)
    return q, qd, dry, level, joint


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
