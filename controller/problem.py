"""The paper's optimal control problem as data: horizon, weights, barrier sharpness, limits.

Defaults follow the paper (eq. 14-15, section II-B) where readable; each says where it is from.
"""

from dataclasses import dataclass, field, replace

import numpy as np

from controller.reference import REFERENCE_MARGIN
from model.dynamics import P_DRIVE_GAIN, P_DRY, P_INERTIA, P_VISCOUS
from model.parameters import Limits

# Indices of the packed cost vector the compiled solver reads.
C_Q_POSITION = 0
C_Q_VELOCITY = 1
C_R_CURRENT = 2
C_W_POSITION = 3
C_W_VELOCITY = 4
C_P_TORQUE = 5
C_ALPHA_POSITION = 6
C_ALPHA_VELOCITY = 7
C_ALPHA_TORQUE = 8
C_POSITION_MIN = 9
C_POSITION_MAX = 10
C_VELOCITY_MAX = 11
C_TORQUE_MAX = 12
C_DRIVE_GAIN = 13
C_FRICTION_SHARPNESS = 14
C_DT = 15
# exp(-alpha upper) and exp(alpha lower) of each barrier, precomputed (see controller.cost)
C_E_POSITION_HIGH = 16
C_E_POSITION_LOW = 17
C_E_VELOCITY_HIGH = 18
C_E_VELOCITY_LOW = 19
C_E_TORQUE_HIGH = 20
C_E_TORQUE_LOW = 21
N_COST = 22


@dataclass(frozen=True)
class Weights:
    position: float = 400.0  # Q_qq, paper eq. 15
    velocity: float = 0.01  # Q_vv, paper eq. 15
    current: float = 1e-4  # R, paper eq. 15
    # W_qq: unreadable in the paper's OCR; 100 (as P) keeps the plateau ~0.1 rad inside the
    # limit for a reference 0.15 rad beyond it, as in the paper's Fig. 5.
    position_barrier: float = 100.0
    velocity_barrier: float = 0.01  # W_vv, paper notes
    torque_barrier: float = 100.0  # P, paper eq. 15


@dataclass(frozen=True)
class Sharpness:
    """alpha of each exponential barrier: how steep the wall is (paper, after eq. 23)."""

    position: float = 10.0  # 1/rad
    velocity: float = 1.0  # s/rad
    torque: float = 0.5  # 1/(N.m), on motor torque drive_gain x current


# The tick grows linearly with the horizon (bench: 17 us median at 100 steps on this 2-core
# machine), so 1000 steps take about a fifth of a 1 ms period: more cannot keep the rhythm.
MAX_HORIZON = 1000


class ResolutionError(ValueError):
    """A step the controller cannot keep safe; `quantity` is "dt" (the iLQR step) or "period"
    (the control period), so a command can name its own option."""

    def __init__(self, quantity: str, message: str):
        super().__init__(message)
        self.quantity = quantity


class UnsafeWeights(ValueError):
    """Weights with which the controller would pull the joint past its limits."""


@dataclass(frozen=True)
class OcpSettings:
    horizon: int = 100  # steps; the paper's 100 ms window at 1 ms
    dt: float = 1e-3  # s
    weights: Weights = field(default_factory=Weights)
    sharpness: Sharpness = field(default_factory=Sharpness)
    friction_sharpness: float = 1000.0  # beta in tanh(beta qd), paper section II-C
    max_iterations: int = 100  # cold solve
    tick_iterations: int = 1  # warm-started MPC tick (real-time iteration)
    tolerance: float = 1e-6  # relative cost decrease that counts as converged

    def __post_init__(self) -> None:
        if not 2 <= self.horizon <= MAX_HORIZON:
            raise ValueError(f"horizon must be 2..{MAX_HORIZON} steps (the tick grows with the "
                             f"horizon and must fit in the control period), got {self.horizon}")
        if not 0 < self.dt <= 0.1:
            raise ValueError(f"dt must be in (0, 0.1] s, got {self.dt}")
        for group in (self.weights, self.sharpness):
            for name, value in vars(group).items():
                if not np.isfinite(value) or value < 0:
                    raise ValueError(f"{name} must be finite and >= 0, got {value}")

    def with_weights(self, **changes: float) -> "OcpSettings":
        return replace(self, weights=replace(self.weights, **changes))

    def check_weights(self) -> None:
        """Refuse weights the controller cannot keep safe. The position barrier is what keeps
        the joint inside its limits, so it must be on; and a reference may lie up to
        REFERENCE_MARGIN beyond a limit, where the tracking cost pulls with 2 Q d and the
        barrier at the limit pushes back with W alpha: the cost's minimum stays inside the
        limit only while 2 Q d <= W alpha. Measured on the elbow (--sim, a setpoint 0.5 rad
        beyond the lower limit): Q = 1000 = W alpha / (2 d) held, 2000 left the drive's
        position window, and {"position": 1e6} or {"position_barrier": 0} faulted the drive
        within 2.3 s on the default sinusoid. Raises UnsafeWeights naming the weights."""
        w, alpha = self.weights, self.sharpness.position
        if not w.position_barrier > 0:
            raise UnsafeWeights(f"position_barrier {w.position_barrier:g}: expected > 0 (it "
                                "keeps the joint inside its position limits)")
        most = w.position_barrier * alpha / (2 * REFERENCE_MARGIN)
        if w.position > most:
            raise UnsafeWeights(
                f"position {w.position:g} with position_barrier {w.position_barrier:g}: a "
                f"reference {REFERENCE_MARGIN:g} rad beyond a limit would pull the joint past "
                f"it; expected position <= position_barrier x {alpha:g} / "
                f"{2 * REFERENCE_MARGIN:g} = {most:g} (or a larger position_barrier)")

    def check_resolution(self, velocity_max: float, period: float) -> None:
        """Refuse a step the controller cannot keep safe: at the velocity limit (rad/s), one
        iLQR step or one control period (s) may move the joint at most half the position
        barrier's width 1/alpha (over which the barrier grows by e), so the wall is felt at
        least two steps before it. A coarser plan hops over the limit without the cost
        seeing it; a longer period leaves the joint that far unwatched. At the defaults
        (1/alpha = 0.1 rad, 5 rad/s) 100 ms and 20 ms steps drove the joint through the
        drive's position window (EMCY 0x8612); 10 ms held. Raises ResolutionError."""
        alpha = self.sharpness.position
        longest = 0.5 / (alpha * velocity_max)  # s
        for quantity, step in (("dt", self.dt), ("period", period)):
            if step > longest:
                raise ResolutionError(quantity, (
                    f"at the velocity limit {velocity_max:g} rad/s the joint moves "
                    f"{velocity_max * step:.3g} rad per step, more than half the position "
                    f"barrier's width 1/alpha = {1 / alpha:g} rad; expected at most "
                    f"{longest * 1e3:g} ms"))


def resolvable_friction_sharpness(settings: OcpSettings, parameters: np.ndarray) -> float:
    """The beta of tanh(beta qd) the solver models the joint's dry friction with: the
    settings' one, unless the step cannot resolve it. Near qd = 0 the smoothed friction acts
    as a damping k = (Fv + beta Fs) / I, and the semi-implicit Euler step multiplies a velocity
    by 1 - dt k: from dt k >= 2 on the predicted velocity rings with a growing amplitude (the
    discrete model is unstable) and the line search rejects the steps built on it. There beta
    becomes the sharpest value that stops the joint in one step without reversing it,
    dt k = 1, which is what real dry friction does. Measured on talos_32 (wrists, grippers and
    head at dt k = 2.001 with beta 1000, the legs and the elbow at 1.90-1.93): with beta as
    set, a failed warm line search (12 to 16 simulations) in 46 % of a wrist's ticks and a
    32-joint tick of 340 us median; with the cap 1.0 to 1.6 simulations per joint-tick and
    83 us. A stable beta is kept as set (the paper's elbow: 1000 at 1 ms, dt k = 1.92)."""
    beta = settings.friction_sharpness
    dry, viscous, inertia = parameters[P_DRY], parameters[P_VISCOUS], parameters[P_INERTIA]
    if dry <= 0.0 or settings.dt * (viscous + beta * dry) < 2.0 * inertia:
        return beta
    return max((inertia / settings.dt - viscous) / dry, 0.0)


def pack_cost(settings: OcpSettings, limits: Limits, parameters: np.ndarray) -> np.ndarray:
    """The flat vector the compiled cost and solver take, for a joint whose packed dynamics
    parameters (model.dynamics layout, payload included) are `parameters`."""
    drive_gain = parameters[P_DRIVE_GAIN]
    c = np.zeros(N_COST)
    w, s = settings.weights, settings.sharpness
    c[C_Q_POSITION], c[C_Q_VELOCITY], c[C_R_CURRENT] = w.position, w.velocity, w.current
    c[C_W_POSITION], c[C_W_VELOCITY] = w.position_barrier, w.velocity_barrier
    c[C_P_TORQUE] = w.torque_barrier
    c[C_ALPHA_POSITION], c[C_ALPHA_VELOCITY], c[C_ALPHA_TORQUE] = (s.position, s.velocity,
                                                                    s.torque)
    c[C_POSITION_MIN], c[C_POSITION_MAX] = limits.position_min, limits.position_max
    c[C_VELOCITY_MAX] = limits.velocity_max
    c[C_TORQUE_MAX] = drive_gain * limits.current_max
    c[C_DRIVE_GAIN] = drive_gain
    c[C_FRICTION_SHARPNESS] = resolvable_friction_sharpness(settings, parameters)
    c[C_DT] = settings.dt
    for high, low, alpha, upper, lower in (
            (C_E_POSITION_HIGH, C_E_POSITION_LOW, s.position, limits.position_max,
             limits.position_min),
            (C_E_VELOCITY_HIGH, C_E_VELOCITY_LOW, s.velocity, limits.velocity_max,
             -limits.velocity_max),
            (C_E_TORQUE_HIGH, C_E_TORQUE_LOW, s.torque, c[C_TORQUE_MAX], -c[C_TORQUE_MAX])):
        c[high] = np.exp(-alpha * upper)
        c[low] = np.exp(alpha * lower)
    return c
