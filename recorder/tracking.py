"""The position-tracking current loop used to run exciting trajectories: computed torque from
the nominal model plus PD, well enough to follow the double S-curves within a few mrad."""

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from model import dynamics
from model.parameters import ActuatorParameters

BANDWIDTH_HZ = 8.0  # closed-loop bandwidth of the PD part (assumed; far below the 1 kHz loop)
DAMPING = 0.9
FRICTION_SMOOTHING = 0.02  # rad/s: tanh(qd*/0.02) stands in for sign(qd*) in the feedforward


@dataclass(frozen=True)
class TrackingLaw:
    parameters: ActuatorParameters  # nominal model, payload included
    current_limit: float

    def __post_init__(self) -> None:
        self.current(0.0, 0.0, (0.0, 0.0, 0.0))  # load the compiled model before the loop runs

    @cached_property
    def _packed(self) -> np.ndarray:
        return self.parameters.packed()

    def current(self, position: float, velocity: float, reference: tuple[float, float, float]
                ) -> float:
        """Motor current for (q*, qd*, qdd*), clipped to the limit: the model's motor torque
        for the PD-corrected acceleration at the measured position and the reference speed."""
        q_ref, qd_ref, qdd_ref = reference
        w = 2.0 * math.pi * BANDWIDTH_HZ
        acceleration = qdd_ref + w * w * (q_ref - position) + 2 * DAMPING * w * (qd_ref - velocity)
        torque, _ = dynamics.sample_inverse_dynamics(position, qd_ref, acceleration,
                                                     math.tanh(qd_ref / FRICTION_SMOOTHING),
                                                     self._packed)
        drive_gain = self.parameters.drive_gain
        return max(-self.current_limit, min(self.current_limit, float(torque) / drive_gain))
