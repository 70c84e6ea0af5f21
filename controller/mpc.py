"""Receding-horizon use of the iLQR: warm start shifted by one step, one (or a few) solver
iterations per tick, and the safety net between the solver and the drive."""

import math
import time
from typing import NamedTuple

import numpy as np

from controller.ilqr import COLD, NOT_FINITE, RESAMPLE, WARM, IlqrSolver, SolveResult
from controller.problem import OcpSettings, pack_cost
from controller.reference import Reference, Sinusoid, check_reference, reference_at
from model import dynamics
from model.parameters import ActuatorModel, Payload

STATE_MARGIN = 0.5  # rad beyond the position limits where the state is still believed


class TickResult(NamedTuple):
    """What one MPC tick decided (a NamedTuple: built every millisecond, so kept cheap)."""

    current: float  # A, the command to send (within the current limit)
    planned_current: float  # A, what the solver asked for before the safety net
    reference_position: float
    reference_velocity: float
    solve: SolveResult
    solve_time: float  # s
    fault: str | None  # why the safety net overrode the solver, if it did

    @property
    def saturated(self) -> bool:
        return self.fault is None and self.planned_current != self.current


class Mpc:
    """The paper's controller: iLQR with exponential barriers, run at every control period."""

    def __init__(self, model: ActuatorModel, settings: OcpSettings = OcpSettings(),
                 payload: Payload = Payload(), reference: Reference = Sinusoid()):
        self.model = model
        self._mode = COLD
        self.settings = settings
        self.payload = payload
        self.parameters = model.parameters.with_payload(payload)
        self.limits = model.limits
        self.set_reference(reference)
        self.solver = IlqrSolver(settings, self.parameters.packed(),
                                 pack_cost(settings, model.limits, self.parameters.drive_gain))
        # load the compiled code now, not in the first control cycle
        middle = 0.5 * (self.limits.position_min + self.limits.position_max)
        self.solver.tick((middle, 0.0), 0.0, self._reference_packed, COLD, 0.0, 1)

    def set_reference(self, reference: Reference) -> None:
        check_reference(reference, self.limits)
        self.reference = reference
        self._reference_packed = reference.packed()
        if self._mode == WARM:
            self._mode = RESAMPLE

    def set_settings(self, settings: OcpSettings) -> None:
        """New weights or sharpness; horizon and dt changes rebuild the solver (cold start)."""
        if (settings.horizon, settings.dt) != (self.settings.horizon, self.settings.dt):
            self.__init__(self.model, settings, self.payload, self.reference)
            return
        self.settings = settings
        self.solver.settings = settings
        self.solver.c[:] = pack_cost(settings, self.limits, self.parameters.drive_gain)
        if self._mode == WARM:
            self._mode = RESAMPLE  # the stored derivatives belong to the old weights

    def hold_current(self, position: float) -> float:
        """Current that balances gravity and offset at `position`, within the limit."""
        p = self.parameters
        torque = dynamics.gravity_torque(position, self.solver.p) + p.torque_offset
        return float(np.clip(torque / p.drive_gain, -self.limits.current_max,
                             self.limits.current_max))

    def tick(self, position: float, velocity: float, t: float) -> TickResult:
        start = time.perf_counter()
        state_fault = self._state_fault(position, velocity)
        if state_fault is not None:
            self._mode = COLD
            ref_q, ref_qd = reference_at(self._reference_packed, t)
            finite = math.isfinite(position) and math.isfinite(velocity)
            safe = self.hold_current(position) if finite else 0.0
            return TickResult(safe, math.nan, ref_q, ref_qd, SolveResult(NOT_FINITE, 0, math.inf),
                              time.perf_counter() - start, state_fault)
        mode = self._mode
        result = self.solver.tick(
            (position, velocity), t, self._reference_packed, mode,
            self.hold_current(position) if mode == COLD else 0.0,
            self.settings.max_iterations if mode == COLD else self.settings.tick_iterations)
        planned = float(self.solver.U[0])
        elapsed = time.perf_counter() - start
        ref_q = float(self.solver.reference_position[0])
        ref_qd = float(self.solver.reference_velocity[0])
        if not result.ok or not math.isfinite(planned):
            self._mode = COLD
            return TickResult(self.hold_current(position), planned, ref_q, ref_qd, result,
                              elapsed, f"solver {result.status_name}: holding position")
        self._mode = WARM
        limit = self.limits.current_max
        return TickResult(min(max(planned, -limit), limit), planned, ref_q, ref_qd, result,
                          elapsed, None)

    def _state_fault(self, position: float, velocity: float) -> str | None:
        if not (math.isfinite(position) and math.isfinite(velocity)):
            return f"non-finite state (q={position}, qd={velocity}): zero current"
        low = self.limits.position_min - STATE_MARGIN
        high = self.limits.position_max + STATE_MARGIN
        if not low <= position <= high or abs(velocity) > 2 * self.limits.velocity_max:
            return (f"state out of range (q={position:.3f} rad, qd={velocity:.3f} rad/s): "
                    "holding position")
        return None
