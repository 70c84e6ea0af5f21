"""`controller.messages.joint_view`: each value of a cycle lands in its field of State, Command
and SolverStats, and a value of the wrong type fails there, in the caller's thread. The view's
compiled encoder writes the bytes protobuf writes for the same values."""

import math

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


def _cycle(rng: np.random.Generator) -> tuple:
    """A cycle's arrays and names with the values an encoder may get wrong: zeros (proto3
    leaves them out), -0.0 and NaN (it does not), multi-byte varints, long and non-ASCII
    strings, a saturated or a fallback command."""
    table = rng.normal(size=(1, len(Sample._fields))) * rng.choice([0.0, 1.0, 1e-300, 1e300],
                                                                   size=(1, 6))
    table[0, 1] = rng.choice([table[0, 1], -0.0, math.nan])
    table[0, 5] = rng.choice([0, 0x1237, 0x8000, 0xFFFF])
    header = rng.normal(size=(1, ws.HEADER)) * rng.choice([0.0, 1.0], size=(1, ws.HEADER))
    header[0, ws.ITERATIONS] = rng.choice([0, 2, 200, 70_000])
    header[0, ws.ROLLOUTS] = rng.choice([0, 3, 1 << 20])
    currents = np.array([rng.choice([0.0, 1.25, header[0, ws.PLANNED_CURRENT]])])
    drive_state = str(rng.choice(["OPERATION_ENABLED", "", "\u00e9" * 100]))
    # a status longer than the encoder's first buffer: it makes room
    status = str(rng.choice(["converged", "max_iterations", "", "x" * 300, "y" * 3000]))
    return (table, header, drive_state, currents, status, bool(rng.integers(2)),
            float(rng.choice([0.0, 12e-6])))


def test_the_encoded_view_is_the_bytes_protobuf_writes():
    """The one-joint view a Zenoh publisher sends, encoded in one compiled call, against the
    reference: `joint_view`'s messages serialised by protobuf, over 2000 random cycles."""
    encode = messages.JointViewEncoder(LIMITS)
    rng = np.random.default_rng(7)
    for _ in range(2000):
        table, header, drive_state, currents, status, fallback, decide_time = _cycle(rng)
        t = float(table[0, 0])
        encoded = encode(t, table, header, drive_state, currents, status, fallback, decide_time)
        reference = messages.joint_view(t, table[0].tolist(), drive_state, currents[0].item(),
                                        header[0].tolist(), status, fallback, LIMITS,
                                        decide_time)
        assert encoded.t == t
        assert encoded.parts() == tuple(m.SerializeToString() for m in reference)
        assert encoded.data == b"".join(encoded.parts())
        # parsed back, the same messages (compared as bytes: a NaN is not equal to itself)
        decoded = encoded.decoded()
        assert [type(m) for m in decoded] == [type(m) for m in reference]
        assert tuple(m.SerializeToString() for m in decoded) == encoded.parts()
        assert encoded.state().SerializeToString() == encoded.parts()[0]
