"""`controller.messages.joint_view`: each value of a cycle lands in its field of State, Command
and SolverStats, and a value of the wrong type fails there, in the caller's thread."""

import numpy as np
import pytest

from controller import messages
from controller import workspace as ws
from driver.interface import Sample
from model.parameters import load_model

LIMITS = load_model().limits


def _header() -> list:
    header = np.zeros(ws.HEADER)
    header[ws.PLANNED_CURRENT] = 1.5
    header[ws.REFERENCE_POSITION], header[ws.REFERENCE_VELOCITY] = 0.25, -0.5
    header[ws.ITERATIONS], header[ws.ROLLOUTS], header[ws.COST] = 2, 3, 7.5
    return header.tolist()


def test_every_value_of_a_cycle_lands_in_its_field():
    sample = list(Sample(0.01, 0.1, 0.2, 0.3, 0.4, 0x1237))
    state, command, stats = messages.joint_view(0.01, sample, "OPERATION_ENABLED", 1.25,
                                                _header(), "converged", False, LIMITS, 12e-6)
    assert state == messages.State(t=0.01, position=0.1, velocity=0.2, motor_current=0.3,
                                   joint_torque=0.4, statusword=0x1237,
                                   drive_state="OPERATION_ENABLED")
    assert command == messages.Command(
        t=0.01, current=1.25, planned_current=1.5, reference_position=0.25,
        reference_velocity=-0.5, current_limit=LIMITS.current_max,
        position_min=LIMITS.position_min, position_max=LIMITS.position_max,
        saturated=True, fallback=False)
    assert stats == messages.SolverStats(t=0.01, solve_time_us=12.0, iterations=2, rollouts=3,
                                         status="converged", cost=7.5)
    # the safety net's command is a fallback, not a saturation
    _, command, _ = messages.joint_view(0.01, sample, "OPERATION_ENABLED", 1.25, _header(),
                                        "converged", True, LIMITS, 12e-6)
    assert command.fallback and not command.saturated


def test_a_value_of_the_wrong_type_fails_at_construction():
    sample = list(Sample(0.01, 0.1, 0.2, 0.3, 0.4, 0x1237))
    with pytest.raises(TypeError):
        messages.joint_view(0.01, sample, 7, 1.25, _header(), "converged", False, LIMITS, 1e-5)
