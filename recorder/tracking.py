"""The position-tracking current law used to run exciting trajectories: computed torque from
the nominal model plus PD, well enough to follow the double S-curves within a few mrad; and
the policy that runs it in the control loop."""

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Protocol

import numpy as np

from controller.policy import Decision
from driver import Sample
from model import dynamics
from model.parameters import ActuatorParameters, Limits


class Trajectory(Protocol):
    duration: float  # s

    def sample(self, t: float) -> tuple[float, float, float]:
        """(q*, qd*, qdd*) at time t from the start."""


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


class TrackingPolicy:
    """An experiment's trajectory tracked by the law above, as a policy of the control loop
    (so a recording runs inside the loop's safety net). Time starts at the first sample; the
    policy is finished at the sample where the trajectory's duration is reached."""

    def __init__(self, trajectory: Trajectory, law: TrackingLaw, limits: Limits):
        self.trajectory = trajectory
        self.law = law
        self.parameters = law.parameters
        self.limits = limits
        self.start: float | None = None  # drive time of the first sample

    def elapsed(self, t: float) -> float:
        if self.start is None:
            self.start = t
        return t - self.start

    def tick(self, sample: Sample) -> Decision:
        t = self.elapsed(sample.t)
        reference = self.trajectory.sample(t)
        current = self.law.current(sample.position, sample.velocity, reference)
        return Decision(current, reference[0], reference[1], "tracking", True,
                        finished=t >= self.trajectory.duration)

    def reference_at(self, t: float) -> tuple[float, float]:
        q_ref, qd_ref, _ = self.trajectory.sample(self.elapsed(t))
        return q_ref, qd_ref

    def reset(self) -> None:
        """Nothing to forget: the law has no memory."""

    def plan(self, t: float) -> None:
        return None
