"""The safety net between any policy and the drive.

A state the sensors cannot have measured (non-finite) gives zero current: nothing is known, so
nothing is pushed. A state outside what the joint can reach, or a failed policy, holds the
position against gravity. Every command is clipped to the current limit. The policy is not
asked at all while the state is unbelievable, and is told to start afresh after.
"""

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from controller import ilqr
from controller.ilqr import STATUS_NAMES
from controller.policy import Decision, Policy
from driver import Sample
from model import dynamics
from model.parameters import ActuatorParameters, Limits

STATE_MARGIN = 0.5  # rad beyond the position limits where the state is still believed
VELOCITY_MARGIN = 2.0  # x velocity_max: faster than that is a sensor fault, not motion
NOT_FINITE = STATUS_NAMES[ilqr.NOT_FINITE]  # status of a cycle decided without the policy


def holding_current(position: float, parameters: ActuatorParameters, packed, limit: float
                    ) -> float:
    """Current that balances gravity and the torque offset at `position`, within +-limit.
    `packed` is parameters.packed(), passed in so a 1 kHz caller packs once."""
    torque = dynamics.gravity_torque(position, packed) + parameters.torque_offset
    return float(min(max(torque / parameters.drive_gain, -limit), limit))


class SafeCommand(NamedTuple):
    """What goes to the drive, the decision it came from, and why the net overrode it."""

    current: float  # A, within the current limit
    decision: Decision
    fault: str | None  # None when the policy's command went out (clipped at most)

    @property
    def saturated(self) -> bool:
        return self.fault is None and self.decision.planned_current != self.current


class SafetyNet:
    def __init__(self, policy: Policy):
        self.policy = policy
        self.limits = policy.limits
        self._parameters = policy.parameters
        self._packed = policy.parameters.packed()

    def hold_current(self, position: float) -> float:
        return holding_current(position, self._parameters, self._packed,
                               self.limits.current_max)

    def decide(self, sample: Sample) -> SafeCommand:
        screened = self.screen(sample)
        if screened is not None:
            return screened
        return self.check(sample, self.policy.tick(sample))

    def screen(self, sample: Sample) -> SafeCommand | None:
        """The command for a sample the policy must not see (unbelievable state), else None.
        Split from `check` so a batch of joints can screen each, tick the rest together
        (`controller.robot_loop`), then check each decision."""
        position, velocity = sample.position, sample.velocity
        why = state_fault(position, velocity, self.limits)
        if why is None:
            return None
        self.policy.reset()
        q_ref, qd_ref = self.policy.reference_at(sample.t)
        finite = math.isfinite(position) and math.isfinite(velocity)
        return SafeCommand(self.hold_current(position) if finite else 0.0,
                           Decision(math.nan, q_ref, qd_ref, NOT_FINITE, False,
                                    cost=math.inf), why)

    def check(self, sample: Sample, decision: Decision) -> SafeCommand:
        """The policy's decision as it may go out: held if it failed, clipped to the limit."""
        planned = decision.planned_current
        if not decision.ok or not math.isfinite(planned):
            return SafeCommand(self.hold_current(sample.position), decision,
                               f"solver {decision.status}: holding position")
        limit = self.limits.current_max
        return SafeCommand(min(max(planned, -limit), limit), decision, None)


def state_fault(position: float, velocity: float, limits: Limits) -> str | None:
    """Why the measured state cannot be believed, or None."""
    if not (math.isfinite(position) and math.isfinite(velocity)):
        return f"non-finite state (q={position}, qd={velocity}): zero current"
    if not (limits.position_min - STATE_MARGIN <= position
            <= limits.position_max + STATE_MARGIN) or abs(velocity) > (
            VELOCITY_MARGIN * limits.velocity_max):
        return (f"state out of range (q={position:.3f} rad, qd={velocity:.3f} rad/s): "
                "holding position")
    return None


class BatchSafety:
    """`SafetyNet`'s rules over a batch of joints at once, on arrays (one numpy operation per
    rule, whatever the number of joints): what the robot's cycle runs every millisecond. The
    per-joint net stays the reference (a test holds the two equal) and names what went wrong
    for the rare joint the batch screens out."""

    def __init__(self, parameters: Sequence[ActuatorParameters], limits: Sequence[Limits]):
        packed = np.array([p.packed() for p in parameters])
        self._gravity_my = packed[:, dynamics.P_GRAVITY_MY].copy()
        self._gravity_mx = packed[:, dynamics.P_GRAVITY_MX].copy()
        self._torque_offset = np.array([p.torque_offset for p in parameters])
        self._drive_gain = np.array([p.drive_gain for p in parameters])
        self.current_max = np.array([lim.current_max for lim in limits])
        self._current_low = -self.current_max
        self._position_low = np.array([lim.position_min - STATE_MARGIN for lim in limits])
        self._position_high = np.array([lim.position_max + STATE_MARGIN for lim in limits])
        self._velocity_high = np.array([VELOCITY_MARGIN * lim.velocity_max for lim in limits])

    def screen_limits(self) -> np.ndarray:
        """Rows over the joints: the lowest and highest believable position (rad) and the
        highest believable speed (rad/s), as `believed` applies them (one array for a compiled
        cycle: each array argument costs a compiled call about 0.1 us)."""
        return np.array([self._position_low, self._position_high, self._velocity_high])

    def hold_currents(self, positions: np.ndarray) -> np.ndarray:
        """`holding_current` of every joint (A), within its limit (`positions`: one per joint
        of the batch, in its order)."""
        torque = (self._gravity_my * np.sin(positions) + self._gravity_mx * np.cos(positions)
                  + self._torque_offset)
        return np.clip(torque / self._drive_gain, -self.current_max, self.current_max)

    def believed(self, positions: np.ndarray, velocities: np.ndarray) -> np.ndarray:
        """Per joint: the state is one the policy may see (`state_fault` gives None). A NaN
        compares False without a warning (numpy >= 1.24), so no `errstate` (a context
        manager cost 5 us a cycle, a third of the MPC tick)."""
        return ((positions >= self._position_low) & (positions <= self._position_high)
                & (np.abs(velocities) <= self._velocity_high))

    def screened_currents(self, positions: np.ndarray, velocities: np.ndarray) -> np.ndarray:
        """What `screen` commands for each joint (meaningful where not `believed`): hold the
        position, or zero current where the state is not finite."""
        finite = np.isfinite(positions) & np.isfinite(velocities)
        return np.where(finite, self.hold_currents(np.where(finite, positions, 0.0)), 0.0)

    def clipped(self, currents: np.ndarray) -> np.ndarray:
        """Each joint's current within its limit (np.clip's wrapper costs 3x this)."""
        return np.minimum(np.maximum(currents, self._current_low), self.current_max)

    def checked_currents(self, positions: np.ndarray, planned: np.ndarray, ok: np.ndarray
                         ) -> np.ndarray:
        """What `check` commands: the planned current clipped to the limit where the policy
        succeeded with a finite current, else the holding current."""
        usable = ok & np.isfinite(planned)
        if usable.all():  # every cycle but a rare one: no holding current to work out
            return self.clipped(planned)
        return np.where(usable, self.clipped(np.where(usable, planned, 0.0)),
                        self.hold_currents(positions))
