"""What the control loop asks of whatever decides the command: the MPC, or the tracking law of
an identification experiment. The loop puts the same safety net around every policy
(`controller.safety`), so a recording is as safe as a controlled run."""

import math
from typing import NamedTuple, Protocol

import numpy as np

from driver import Sample
from model.parameters import ActuatorParameters, Limits


class Decision(NamedTuple):
    """One cycle's decision (a NamedTuple: built every millisecond, so kept cheap)."""

    planned_current: float  # A, what the policy asks for, before the safety net
    reference_position: float  # rad, the reference at the sample's time
    reference_velocity: float  # rad/s
    status: str  # the solver's status name, or the policy's own word for success
    ok: bool  # False: the policy failed; the safety net holds position instead
    iterations: int = 0  # solver iterations (0 for a policy without a solver)
    rollouts: int = 0  # trajectory simulations, line-search trials included
    cost: float = math.nan  # the objective the policy minimised, if any
    finished: bool = False  # the policy's job is done (an experiment's trajectory is over)


class PlanSnapshot(NamedTuple):
    """The predicted trajectory as it was when taken: copies, never the solver's buffers."""

    t: float  # s, time of the first point
    dt: float  # s between points
    position: np.ndarray  # rad, N + 1 points
    velocity: np.ndarray  # rad/s, N + 1 points
    current: np.ndarray  # A, N points
    reference_position: np.ndarray  # rad, N + 1 points


class Policy(Protocol):
    parameters: ActuatorParameters  # the policy's model, payload included (for holding)
    limits: Limits  # what the safety net enforces

    def tick(self, sample: Sample) -> Decision:
        """Decide the current for this sample (the state is finite and in range)."""

    def reference_at(self, t: float) -> tuple[float, float]:
        """(q*, qd*) at time t, for the cycles the safety net decides alone."""

    def reset(self) -> None:
        """The safety net skipped this policy for a cycle: start afresh at the next tick."""

    def plan(self, t: float) -> PlanSnapshot | None:
        """A copy of the predicted trajectory, or None for a policy that predicts nothing."""
