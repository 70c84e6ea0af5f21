"""The position-tracking current loop used to run exciting trajectories: computed torque from
the nominal model plus PD, well enough to follow the double S-curves within a few mrad."""

import math
from dataclasses import dataclass

from model import dynamics
from model.parameters import ActuatorParameters

BANDWIDTH_HZ = 8.0  # closed-loop bandwidth of the PD part (assumed; far below the 1 kHz loop)
DAMPING = 0.9
FRICTION_SMOOTHING = 0.02  # rad/s: tanh(qd*/0.02) stands in for sign(qd*) in the feedforward


@dataclass(frozen=True)
class TrackingLaw:
    parameters: ActuatorParameters  # nominal model, payload included
    current_limit: float

    def current(self, position: float, velocity: float, reference: tuple[float, float, float]
                ) -> float:
        """Motor current for (q*, qd*, qdd*), clipped to the limit."""
        q_ref, qd_ref, qdd_ref = reference
        p = self.parameters
        w = 2.0 * math.pi * BANDWIDTH_HZ
        acceleration = qdd_ref + w * w * (q_ref - position) + 2 * DAMPING * w * (qd_ref - velocity)
        torque = (p.inertia * acceleration + dynamics.gravity_torque(position, p.packed())
                  + p.viscous_friction * qd_ref
                  + p.dry_friction * math.tanh(qd_ref / FRICTION_SMOOTHING) + p.torque_offset)
        return max(-self.current_limit, min(self.current_limit, torque / p.drive_gain))
