"""`controller.messages.joint_view`: each value of a cycle lands in its field of State, Command
and SolverStats, and a value of the wrong type fails there, in the caller's thread. The view's
and a robot's JointStates' compiled encoders write the bytes protobuf writes for the same
values."""

import math

import numpy as np
import pytest

from controller import messages
from controller import workspace as ws
from controller.ilqr import STATUS_NAMES
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


def _robot_cycle(rng: np.random.Generator, count: int) -> tuple:
    """A robot's cycle with the values an encoder may get wrong, as `_cycle`: zeros (written in
    a packed array, left out as t or solve time), -0.0 and NaN, iterations of several varint
    bytes, every solver status, the policy's own (long, non-ASCII) status names or none."""
    table = rng.normal(size=(count, len(Sample._fields))) * rng.choice(
        [0.0, 1.0, 1e-300, 1e300], size=(count, len(Sample._fields)))
    table[:, 1] = np.where(rng.random(count) < 0.2, -0.0, table[:, 1])
    table[:, 2] = np.where(rng.random(count) < 0.2, math.nan, table[:, 2])
    table[:, 0] = rng.choice([0.0, 0.25, -0.0])
    header = rng.normal(size=(count, ws.HEADER)) * rng.choice([0.0, 1.0], size=(count, ws.HEADER))
    header[:, ws.STATUS] = rng.integers(0, len(STATUS_NAMES), count)
    header[:, ws.ITERATIONS] = rng.choice([0, 2, 200, 70_000, 2**32 - 1], count)
    currents = rng.normal(size=count) * rng.choice([0.0, 1.0], size=count)
    fallback = rng.random(count) < 0.3
    status = (None if rng.random() < 0.5 else
              [str(rng.choice(["converged", "", "\u00e9" * 80, "z" * 3000]))
               for _ in range(count)])
    return table, header, currents, status, fallback, float(rng.choice([0.0, 12e-6, 1.5e-3]))


def test_a_robots_encoded_joint_states_are_the_bytes_protobuf_writes():
    """A robot's JointStates as a Zenoh publisher sends them, encoded in one compiled call,
    against the reference: `joint_states` serialised by protobuf, over 500 random cycles of
    robots of 2 to 40 joints with names of every length (one of them non-ASCII)."""
    rng = np.random.default_rng(11)
    for count in (2, 7, 32, 40):
        names = [f"joint_{j}" * int(rng.integers(1, 30)) for j in range(count)]
        names[0] = "\u00e9paule"
        drive_states = ("OPERATION_ENABLED",) * count
        encode = messages.JointStatesEncoder(names, drive_states)
        for _ in range(125):
            table, header, currents, status, fallback, decide_time = _robot_cycle(rng, count)
            t = float(table[0, 0])
            encoded = encode(t, table, currents, header, status, fallback, decide_time)
            named = status if status is not None else [
                STATUS_NAMES[int(code)] for code in header[:, ws.STATUS]]
            reference = messages.joint_states(t, names, table, drive_states, currents, header,
                                              named, fallback, decide_time)
            assert (encoded.kind, encoded.t) == (messages.JointStates, t)
            assert encoded.data == reference.SerializeToString()
            assert encoded.decoded().SerializeToString() == encoded.data


def test_the_joint_states_encoder_refuses_what_names_no_joint_or_no_status():
    encode = messages.JointStatesEncoder(["a", "b"], ("OPERATION_ENABLED",) * 2)
    table, header = np.zeros((2, len(Sample._fields))), np.zeros((2, ws.HEADER))
    with pytest.raises(ValueError, match=r"\(3, 3, 3, 3\) rows .* for 2 joints"):
        encode(0.0, np.zeros((3, len(Sample._fields))), np.zeros(3), np.zeros((3, ws.HEADER)),
               None, np.zeros(3, dtype=bool), 0.0)
    with pytest.raises(ValueError, match=r"\(2, 2, 1, 2\) rows"):  # one decision short
        encode(0.0, table, np.zeros(2), np.zeros((1, ws.HEADER)), None,
               np.zeros(2, dtype=bool), 0.0)
    header[1, ws.STATUS] = len(STATUS_NAMES)
    with pytest.raises(ValueError, match="names no status"):
        encode(0.0, table, np.zeros(2), header, None, np.zeros(2, dtype=bool), 0.0)
    with pytest.raises(ValueError, match="2 joints, 1 drive states"):
        messages.JointStatesEncoder(["a", "b"], ("OPERATION_ENABLED",))
    with pytest.raises(ValueError, match="no joints"):
        messages.JointStatesEncoder([], ())
