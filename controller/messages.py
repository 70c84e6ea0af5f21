"""The telemetry messages of a control loop, built in one place as the protobuf messages of
`protocol.telemetry`: a misspelt field or a value of the wrong type fails here, in the caller's
thread (protobuf checks both at construction), not later in a publisher thread. Every
subscriber (an MCAP recording, a test) receives the same objects; a subscriber that only sends
bytes (actuatord's Zenoh publisher) gets a one-joint cycle's messages and its plans as their
wire bytes instead, encoded in one compiled call each (`JointViewEncoder`, `plan_bytes`):
protobuf's own bytes, which the tests hold them to.
"""

import functools
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numba
import numpy as np
from google.protobuf.descriptor import FieldDescriptor
from google.protobuf.message import Message

from controller import workspace as ws
from controller.ilqr import STATUS_NAMES
from controller.policy import PlanSnapshot
from driver.interface import (
    SAMPLE_JOINT_TORQUE,
    SAMPLE_MOTOR_CURRENT,
    SAMPLE_POSITION,
    SAMPLE_STATUSWORD,
    SAMPLE_T,
    SAMPLE_VELOCITY,
    Sample,
)
from model.parameters import Limits
from protocol import telemetry

State = telemetry.message_class("State")
Command = telemetry.message_class("Command")
SolverStats = telemetry.message_class("SolverStats")
Plan = telemetry.message_class("Plan")
Fault = telemetry.message_class("Fault")
LoopStats = telemetry.message_class("LoopStats")

JointStates = telemetry.message_class("JointStates")

_TOPICS = {telemetry.message_class(name): topic for topic, name in telemetry.TOPICS.items()}

Subscriber = Callable[[Message], None]


def topic_of(message: Message) -> str:
    """The key under the prefix ('state', 'command', ...) a message is published on."""
    return _TOPICS[type(message)]


def topic_of_kind(kind: type) -> str:
    """`topic_of` a message of class `kind` (an `Encoded` message's: its bytes name none)."""
    return _TOPICS[kind]


def joint_view(t: float, sample: list, drive_state: str, current: float, header: list,
               status: str, fallback: bool, limits: Limits, decide_time: float
               ) -> tuple[Message, Message, Message]:
    """One joint's cycle as its own State, Command and SolverStats, from the cycle's row of
    samples (`sample`: `driver.Sample` fields as a list) and the decision's header
    (`header`: a `controller.workspace` header as a list); `current` went out, `fallback`
    says the safety net chose it. Fields are set one by one, not as keyword arguments:
    protobuf checks each name and type the same way, and the three messages cost 2.0 us
    against 3.7 (every cycle, in the loop's thread)."""
    planned = header[ws.PLANNED_CURRENT]
    state = State()
    state.t = t
    state.position = sample[SAMPLE_POSITION]
    state.velocity = sample[SAMPLE_VELOCITY]
    state.motor_current = sample[SAMPLE_MOTOR_CURRENT]
    state.joint_torque = sample[SAMPLE_JOINT_TORQUE]
    state.statusword = int(sample[SAMPLE_STATUSWORD])
    state.drive_state = drive_state
    command = Command()
    command.t = t
    command.current = current
    command.planned_current = planned
    command.reference_position = header[ws.REFERENCE_POSITION]
    command.reference_velocity = header[ws.REFERENCE_VELOCITY]
    command.current_limit = limits.current_max
    command.position_min = limits.position_min
    command.position_max = limits.position_max
    command.saturated = not fallback and planned != current
    command.fallback = fallback
    stats = SolverStats()
    stats.t = t
    stats.solve_time_us = decide_time * 1e6
    stats.iterations = int(header[ws.ITERATIONS])
    stats.rollouts = int(header[ws.ROLLOUTS])
    stats.status = status
    stats.cost = header[ws.COST]
    return state, command, stats


def _key(message: type, name: str, kind: int, wire: int, repeated: bool = False) -> int:
    """The key of field `name` (protobuf type `kind`, wire type `wire`): one byte, as the
    compiled encoders write it."""
    field = message.DESCRIPTOR.fields_by_name[name]
    if field.type != kind or field.is_repeated != repeated:
        raise TypeError(f"{message.__name__}.{name} is not a{' repeated' * repeated} "
                        f"{field.type}")
    key = field.number << 3 | wire
    if key > 0x7F:
        raise TypeError(f"{message.__name__}.{name}'s key takes more than one byte")
    return key


# --- one joint's view as its wire bytes -------------------------------------------------------
# The fields the compiled encoder writes, message by message, in the order it writes them:
# each message's fields by number, as protobuf writes them (checked here at import, so that a
# change of the schema fails loudly, not as bytes that differ from protobuf's own).
_VIEW_FIELDS = (
    (State, ("t", "position", "velocity", "motor_current", "joint_torque", "statusword",
             "drive_state")),
    (Command, ("t", "current", "planned_current", "reference_position", "reference_velocity",
               "current_limit", "position_min", "position_max", "saturated", "fallback")),
    (SolverStats, ("t", "solve_time_us", "iterations", "rollouts", "status", "cost")),
)
VIEW_CLASSES = tuple(kind for kind, _ in _VIEW_FIELDS)  # State, Command, SolverStats
# protobuf's wire types of the view's field types: 64-bit, varint, length-delimited
_WIRE_TYPES = {FieldDescriptor.TYPE_DOUBLE: 1, FieldDescriptor.TYPE_UINT32: 0,
               FieldDescriptor.TYPE_BOOL: 0, FieldDescriptor.TYPE_STRING: 2}


def _view_keys() -> np.ndarray:
    """Each written field's key, in the order the encoder writes them."""
    keys = []
    for kind, names in _VIEW_FIELDS:
        fields = sorted(kind.DESCRIPTOR.fields, key=lambda field: field.number)
        if tuple(field.name for field in fields) != names:
            raise TypeError(f"{kind.__name__}'s fields changed: the view's encoder writes "
                            f"{names}")
        keys += [_key(kind, field.name, field.type, _WIRE_TYPES[field.type])
                 for field in fields]
    return np.array(keys, dtype=np.int64)


_VIEW_KEYS = _view_keys()
# bytes an encoded view takes at most, its two strings apart: 16 doubles (9 bytes each: State's
# 5, Command's 8, SolverStats' 3), three uint32 (6), two bools (2), two string keys and lengths
# (6)
_VIEW_FIXED = 16 * 9 + 3 * 6 + 2 * 2 + 2 * 6


# The encoders keep the interpreter's lock (the solver's kernels release it): a microsecond's
# work gains nothing from releasing it, and a release in the middle of a real-time cycle hands
# the lock to whichever thread waits for it (the publisher's) until that thread lets go
_JIT = {"cache": True, "error_model": "numpy"}


@numba.njit(**_JIT)
def _put_varint(out, at, value):  # pragma: no cover - compiled
    while value > 0x7F:
        out[at] = value & 0x7F | 0x80
        value >>= 7
        at += 1
    out[at] = value
    return at + 1


@numba.njit(**_JIT)
def _put_double(out, at, key, value, scratch, raw):  # pragma: no cover - compiled
    """A double field, left out when its bits are all zero (proto3's default: protobuf writes
    -0.0 and NaN, not 0.0); little-endian, the wire's order and the host's here."""
    scratch[0] = value
    if raw[0] | raw[1] | raw[2] | raw[3] | raw[4] | raw[5] | raw[6] | raw[7] == 0:
        return at
    out[at] = key
    out[at + 1:at + 9] = raw
    return at + 9


@numba.njit(**_JIT)
def _put_uint(out, at, key, value):  # pragma: no cover - compiled
    """A uint32 (or bool) field, left out when 0."""
    value = value & 0xFFFFFFFF
    if value == 0:
        return at
    out[at] = key
    return _put_varint(out, at + 1, value)


@numba.njit(**_JIT)
def _put_string(out, at, key, text):  # pragma: no cover - compiled
    """A string field (`text` its UTF-8 bytes), left out when empty."""
    if text.shape[0] == 0:
        return at
    out[at] = key
    at = _put_varint(out, at + 1, text.shape[0])
    out[at:at + text.shape[0]] = text
    return at + text.shape[0]


@numba.njit(**_JIT)
def _encode_view(out, keys, table, header, currents, decide_time, limits, fallback,
                 drive_state, status):  # pragma: no cover - compiled
    """Joint 0's State, Command and SolverStats one after the other into `out`, as `joint_view`
    builds them and protobuf serialises them; the end of each (-1s: `out` too small)."""
    if out.shape[0] < _VIEW_FIXED + drive_state.shape[0] + status.shape[0]:
        return -1, -1, -1
    scratch = np.empty(1)
    raw = scratch.view(np.uint8)
    t, current, planned = table[0, SAMPLE_T], currents[0], header[0, ws.PLANNED_CURRENT]
    at = _put_double(out, 0, keys[0], t, scratch, raw)
    at = _put_double(out, at, keys[1], table[0, SAMPLE_POSITION], scratch, raw)
    at = _put_double(out, at, keys[2], table[0, SAMPLE_VELOCITY], scratch, raw)
    at = _put_double(out, at, keys[3], table[0, SAMPLE_MOTOR_CURRENT], scratch, raw)
    at = _put_double(out, at, keys[4], table[0, SAMPLE_JOINT_TORQUE], scratch, raw)
    at = _put_uint(out, at, keys[5], np.int64(table[0, SAMPLE_STATUSWORD]))
    state_end = at = _put_string(out, at, keys[6], drive_state)
    at = _put_double(out, at, keys[7], t, scratch, raw)
    at = _put_double(out, at, keys[8], current, scratch, raw)
    at = _put_double(out, at, keys[9], planned, scratch, raw)
    at = _put_double(out, at, keys[10], header[0, ws.REFERENCE_POSITION], scratch, raw)
    at = _put_double(out, at, keys[11], header[0, ws.REFERENCE_VELOCITY], scratch, raw)
    at = _put_double(out, at, keys[12], limits[0], scratch, raw)
    at = _put_double(out, at, keys[13], limits[1], scratch, raw)
    at = _put_double(out, at, keys[14], limits[2], scratch, raw)
    at = _put_uint(out, at, keys[15], np.int64(not fallback and planned != current))
    command_end = at = _put_uint(out, at, keys[16], np.int64(fallback))
    at = _put_double(out, at, keys[17], t, scratch, raw)
    at = _put_double(out, at, keys[18], decide_time * 1e6, scratch, raw)
    at = _put_uint(out, at, keys[19], np.int64(header[0, ws.ITERATIONS]))
    at = _put_uint(out, at, keys[20], np.int64(header[0, ws.ROLLOUTS]))
    at = _put_string(out, at, keys[21], status)
    at = _put_double(out, at, keys[22], header[0, ws.COST], scratch, raw)
    return state_end, command_end, at


@functools.lru_cache(maxsize=64)  # drive state and solver status names: a handful
def _utf8(text: str) -> np.ndarray:
    return np.frombuffer(text.encode(), dtype=np.uint8).copy()


class EncodedJointView(NamedTuple):
    """One joint's cycle as the wire bytes of its State, Command and SolverStats, one after the
    other in `data`, each ending at its `ends`: what a publisher sends anyway, without the
    three protobuf messages (see `JointViewEncoder`). `t`: the cycle's drive time."""

    t: float
    data: bytes
    ends: tuple[int, int, int]

    def parts(self) -> tuple[bytes, bytes, bytes]:
        """The State's, the Command's and the SolverStats' bytes."""
        state_end, command_end, end = self.ends
        data = self.data
        return data[:state_end], data[state_end:command_end], data[command_end:end]

    def state(self) -> Message:
        """The State alone, parsed (what `/joint_states` is made of)."""
        return State.FromString(self.data[:self.ends[0]])

    def decoded(self) -> tuple[Message, Message, Message]:
        """The State, Command and SolverStats (parsed: for a reader, not for the cycle)."""
        return tuple(kind.FromString(part)
                     for kind, part in zip(VIEW_CLASSES, self.parts(), strict=True))


# a subscriber that sends bytes: it takes a one-joint view as `EncodedJointView`, its Plan and
# a robot's JointStates as `Encoded`, every other message as itself
WireSubscriber = Callable[["Message | EncodedJointView | Encoded"], None]


class JointViewEncoder:
    """`joint_view`'s three messages as their wire bytes in one compiled call, for a loop's
    subscribers that send bytes (a Zenoh publisher): building the messages and serialising
    them cost 4.6 us a cycle against 2.0 this way (200 000 calls of each in a loop), the
    largest cost of a one-joint cycle after the MPC and the drives. The bytes are protobuf's
    own for the same values, field for field (a test holds them to `joint_view` +
    `SerializeToString`); doubles are written in the host's byte order, the wire's
    little-endian on every host numba compiles for here (x86-64, AArch64)."""

    def __init__(self, limits: Limits):
        self._out = np.empty(1024, dtype=np.uint8)  # the loop's own: one thread writes it
        self._limits = np.array([limits.current_max, limits.position_min, limits.position_max])

    def __call__(self, t: float, table: np.ndarray, header: np.ndarray, drive_state: str,
                 currents: np.ndarray, status: str, fallback: bool, decide_time: float
                 ) -> EncodedJointView:
        """Joint 0 of the cycle's arrays: `table` the samples (rows of `driver.Sample`
        fields), `header` the decisions' headers (`controller.workspace`), `currents` what
        went out, `fallback` whether the safety net chose it."""
        drive_state_bytes, status_bytes = _utf8(drive_state), _utf8(status)
        out = self._out
        ends = _encode_view(out, _VIEW_KEYS, table, header, currents, decide_time,
                            self._limits, fallback, drive_state_bytes, status_bytes)
        if ends[2] < 0:  # long names: room for them, once
            out = self._out = np.empty(2 * (_VIEW_FIXED + len(drive_state_bytes)
                                            + len(status_bytes)), dtype=np.uint8)
            ends = _encode_view(out, _VIEW_KEYS, table, header, currents, decide_time,
                                self._limits, fallback, drive_state_bytes, status_bytes)
        return EncodedJointView(t, out[:ends[2]].tobytes(), ends)

    def load(self) -> None:
        """Its compiled code and `plan_bytes`' loaded now, on scratch values, not in a loop's
        first cycles: loading them from numba's cache there held the cycle 15-20 ms (in real
        time, one joint across two processes: 14-23 cycles missed as "publish back-pressure"
        in every start)."""
        empty = np.zeros(0)
        self(0.0, np.zeros((1, len(Sample._fields))), np.zeros((1, ws.HEADER)), "", np.zeros(1),
             "", False, 0.0)
        plan_bytes(PlanSnapshot(0.0, 0.0, empty, empty, empty, empty))


# a Plan's fields as protobuf writes them, by number: t and dt, then the snapshot's arrays
_PLAN_FIELDS = ("t", "dt", "position", "velocity", "current", "reference_position")
if tuple(field.name for field in sorted(Plan.DESCRIPTOR.fields, key=lambda f: f.number)) != (
        _PLAN_FIELDS):
    raise TypeError(f"Plan's fields changed: `plan_bytes` writes {_PLAN_FIELDS}")
_PLAN_KEYS = np.array([_key(Plan, name, FieldDescriptor.TYPE_DOUBLE, 1) for name in ("t", "dt")]
                      + [_key(Plan, name, FieldDescriptor.TYPE_DOUBLE, 2, repeated=True)
                         for name in _PLAN_FIELDS[2:]], dtype=np.int64)
_PLAN_FIXED = 2 * 9 + 4 * 11  # bytes: t and dt, each array's key and length (varint)


@numba.njit(**_JIT)
def _put_packed(out, at, key, values):  # pragma: no cover - compiled
    """A repeated double in protobuf's packed encoding: key, byte length, the values as
    little-endian doubles (`values`: contiguous float64); left out when empty."""
    size = 8 * values.shape[0]
    if size == 0:
        return at
    out[at] = key
    at = _put_varint(out, at + 1, size)
    out[at:at + size] = values.view(np.uint8)
    return at + size


@numba.njit(**_JIT)
def _encode_plan(out, keys, t, dt, position, velocity, current,
                 reference_position):  # pragma: no cover - compiled
    """A Plan's fields one after the other into `out` (at least `_PLAN_FIXED` bytes and 8 a
    point): its end."""
    scratch = np.empty(1)
    raw = scratch.view(np.uint8)
    at = _put_double(out, 0, keys[0], t, scratch, raw)
    at = _put_double(out, at, keys[1], dt, scratch, raw)
    at = _put_packed(out, at, keys[2], position)
    at = _put_packed(out, at, keys[3], velocity)
    at = _put_packed(out, at, keys[4], current)
    return _put_packed(out, at, keys[5], reference_position)


def plan_bytes(snapshot: PlanSnapshot) -> bytes:
    """The snapshot as a Plan's wire bytes, those protobuf writes (a test holds them to it),
    in one compiled call: given lists, protobuf converts every element in turn (15 us for a
    100-step horizon), and the arrays' bytes joined in Python took 10 us in the loop's
    thread, every `plan_every` cycles. A Zenoh publisher sends these bytes as they are."""
    # contiguous float64 (no copy for the MPC's snapshots; a policy's may be strided)
    arrays = [np.ascontiguousarray(values, dtype=np.float64) for values in snapshot[2:]]
    out = np.empty(_PLAN_FIXED + 8 * sum(len(values) for values in arrays), dtype=np.uint8)
    end = _encode_plan(out, _PLAN_KEYS, snapshot.t, snapshot.dt, *arrays)
    return out[:end].tobytes()


def plan(snapshot: PlanSnapshot) -> Message:
    """The snapshot as a Plan message (parsed from `plan_bytes` in one call)."""
    return Plan.FromString(plan_bytes(snapshot))


# --- a robot's cycle as one JointStates' wire bytes --------------------------------------------
_STATES_FIELDS = ("t", "name", "position", "velocity", "effort", "motor_current", "current",
                  "planned_current", "reference_position", "drive_state", "solver_status",
                  "iterations", "fallback", "solve_time_us")
if tuple(field.name for field in sorted(JointStates.DESCRIPTOR.fields,
                                        key=lambda f: f.number)) != _STATES_FIELDS:
    raise TypeError(f"JointStates' fields changed: `JointStatesEncoder` writes {_STATES_FIELDS}")
_DOUBLE, _UINT32, _BOOL = (FieldDescriptor.TYPE_DOUBLE, FieldDescriptor.TYPE_UINT32,
                           FieldDescriptor.TYPE_BOOL)
# the keys in field order: t, the seven packed double arrays, iterations, fallback,
# solve_time_us (the three string fields are copied in as protobuf writes them, `_strings`)
_STATES_KEYS = np.array(
    [_key(JointStates, "t", _DOUBLE, 1)]
    + [_key(JointStates, name, _DOUBLE, 2, repeated=True) for name in _STATES_FIELDS[2:9]]
    + [_key(JointStates, "iterations", _UINT32, 2, repeated=True),
       _key(JointStates, "fallback", _BOOL, 2, repeated=True),
       _key(JointStates, "solve_time_us", _DOUBLE, 1)], dtype=np.int64)
# the sample's and the header's columns of the packed arrays, in field order (the commanded
# currents, an array of their own, come between them)
_STATES_TABLE_COLUMNS = np.array([SAMPLE_POSITION, SAMPLE_VELOCITY, SAMPLE_JOINT_TORQUE,
                                  SAMPLE_MOTOR_CURRENT])
_STATES_HEADER_COLUMNS = np.array([ws.PLANNED_CURRENT, ws.REFERENCE_POSITION])


def _strings(field: str, texts: Sequence[str]) -> np.ndarray:
    """JointStates' repeated string `field` holding `texts`, as protobuf writes it (every
    element its key, length and UTF-8 bytes): the bytes the encoder copies in."""
    return _as_array(JointStates(**{field: texts}).SerializeToString())


def _as_array(data: bytes) -> np.ndarray:
    return np.frombuffer(data, dtype=np.uint8).copy()


@numba.njit(**_JIT)
def _put_packed_column(out, at, key, values, column):  # pragma: no cover - compiled
    """Column `column` of `values` (rows of doubles) as a packed repeated double: key, byte
    length, each value's 8 bytes (zeros too: a packed array writes every element)."""
    count = values.shape[0]
    out[at] = key
    at = _put_varint(out, at + 1, 8 * count)
    scratch = np.empty(1)
    raw = scratch.view(np.uint8)
    for j in range(count):
        scratch[0] = values[j, column]
        for byte in range(8):
            out[at + byte] = raw[byte]
        at += 8
    return at


@numba.njit(**_JIT)
def _varint_size(value):  # pragma: no cover - compiled
    size = 1
    while value > 0x7F:
        value >>= 7
        size += 1
    return size


@numba.njit(**_JIT)
def _encode_joint_states(out, keys, table_columns, header_columns, t, names, table, currents,
                         header, drive_states, status_by_code, status_at, status_given,
                         fallback, decide_time):  # pragma: no cover - compiled
    """A JointStates' fields in field order into `out` (`JointStatesEncoder` sizes it): the
    string fields' elements pre-encoded (`names`, `drive_states`; the solver status either
    `status_given` or, when that is empty, each joint's code's element in `status_by_code`,
    which starts at `status_at[code]`); its end."""
    count = table.shape[0]
    scratch = np.empty(1)
    raw = scratch.view(np.uint8)
    at = _put_double(out, 0, keys[0], t, scratch, raw)
    out[at:at + names.shape[0]] = names
    at += names.shape[0]
    for n in range(4):  # position, velocity, effort, motor_current
        at = _put_packed_column(out, at, keys[1 + n], table, table_columns[n])
    at = _put_packed_column(out, at, keys[5], currents.reshape(count, 1), 0)
    for n in range(2):  # planned_current, reference_position
        at = _put_packed_column(out, at, keys[6 + n], header, header_columns[n])
    out[at:at + drive_states.shape[0]] = drive_states
    at += drive_states.shape[0]
    if status_given.shape[0] > 0:
        out[at:at + status_given.shape[0]] = status_given
        at += status_given.shape[0]
    else:
        for j in range(count):
            code = np.int64(header[j, ws.STATUS])
            if code < 0 or code >= status_at.shape[0] - 1:
                raise ValueError("a solver status code that names no status")
            start, stop = status_at[code], status_at[code + 1]
            out[at:at + stop - start] = status_by_code[start:stop]
            at += stop - start
    size = 0
    for j in range(count):
        size += _varint_size(np.int64(header[j, ws.ITERATIONS]) & 0xFFFFFFFF)
    out[at] = keys[8]
    at = _put_varint(out, at + 1, size)
    for j in range(count):
        at = _put_varint(out, at, np.int64(header[j, ws.ITERATIONS]) & 0xFFFFFFFF)
    out[at] = keys[9]
    at = _put_varint(out, at + 1, count)
    for j in range(count):
        out[at] = 1 if fallback[j] else 0
        at += 1
    return _put_double(out, at, keys[10], decide_time * 1e6, scratch, raw)


class JointStatesEncoder:
    """`joint_states`' message as its wire bytes in one compiled call, for a robot loop's
    subscribers that send bytes (a Zenoh publisher): building the message from the arrays'
    lists cost 19 us a cycle for talos_arm's 7 joints and 32 us for talos_32's in the loop's
    thread (`actuatord --sim --lockstep --robot`, `joint_states` timed in the run), and
    serialising it cost more in the publisher's. The joints' names and drive states are
    encoded once; a status the policy names (not the solver's codes) per call. The bytes are
    protobuf's own for the same values (a test holds them to `joint_states` +
    `SerializeToString`)."""

    def __init__(self, names: Sequence[str], drive_states: Sequence[str]):
        self._count = len(names)
        if not names:  # proto3 would leave every empty array out; the encoder writes them
            raise ValueError("a robot of no joints")
        if len(drive_states) != self._count:
            raise ValueError(f"{self._count} joints, {len(drive_states)} drive states")
        self._names = _strings("name", names)
        self._drive_states = _strings("drive_state", drive_states)
        by_code = [_strings("solver_status", [name]) for name in STATUS_NAMES]
        self._status_by_code = np.concatenate(by_code)
        self._status_at = np.cumsum([0] + [len(field) for field in by_code])
        self._longest_status = max(len(field) for field in by_code)
        self._none = np.zeros(0, dtype=np.uint8)
        # every field's bytes at most but the policy's own status names: t and solve time (9
        # each), seven double arrays (key, length, 8 a joint), iterations (key, length, 5 a
        # joint), fallback (key, length, 1 a joint)
        self._fixed = (self._names.shape[0] + self._drive_states.shape[0] + 2 * 9
                       + 7 * (6 + 8 * self._count) + (6 + 5 * self._count)
                       + (6 + self._count))
        self._out = np.empty(self._fixed + self._longest_status * self._count, dtype=np.uint8)

    def __call__(self, t: float, table: np.ndarray, currents: np.ndarray, header: np.ndarray,
                 status: Sequence[str] | None, fallback: np.ndarray, decide_time: float
                 ) -> "Encoded":
        """The cycle's arrays as `joint_states` takes them; `status` None: the solver's
        codes' names (the header's)."""
        # the compiled call reads as many rows of each as there are joints, unchecked
        rows = (table.shape[0], currents.shape[0], header.shape[0], fallback.shape[0])
        if rows != (self._count,) * 4:
            raise ValueError(f"{rows} rows of samples, currents, decisions and fallbacks for "
                             f"{self._count} joints")
        given = (self._none if status is None
                 else _strings("solver_status", status))
        out = self._out
        if out.shape[0] < self._fixed + given.shape[0]:  # long names: room for them, once
            out = self._out = np.empty(2 * (self._fixed + given.shape[0]), dtype=np.uint8)
        end = _encode_joint_states(out, _STATES_KEYS, _STATES_TABLE_COLUMNS,
                                   _STATES_HEADER_COLUMNS, t, self._names,
                                   np.ascontiguousarray(table, dtype=np.float64),
                                   np.ascontiguousarray(currents, dtype=np.float64),
                                   np.ascontiguousarray(header, dtype=np.float64),
                                   self._drive_states, self._status_by_code, self._status_at,
                                   given, np.ascontiguousarray(fallback, dtype=np.bool_),
                                   decide_time)
        return Encoded(JointStates, t, out[:end].tobytes())

    def load(self) -> None:
        """Its compiled code loaded now, on scratch values (see `JointViewEncoder.load`)."""
        count = self._count
        self(0.0, np.zeros((count, len(Sample._fields))), np.zeros(count),
             np.zeros((count, ws.HEADER)), None, np.zeros(count, dtype=bool), 0.0)


class Encoded(NamedTuple):
    """A telemetry message of class `kind` as its wire bytes, for subscribers that send
    bytes (`WireSubscriber`); `t`: its drive time."""

    kind: type
    t: float
    data: bytes

    def decoded(self) -> Message:
        return self.kind.FromString(self.data)


def fault(t: float, source: str, cause: str, action: str) -> Message:
    return Fault(t=t, source=source, cause=cause, action=action)


def loop_stats(t: float, cycles: int, missed_cycles: int, jitter_p99_us: float,
               jitter_max_us: float, solve_median_us: float, solve_p99_us: float,
               solve_max_us: float, dropped_messages: int) -> Message:
    return LoopStats(t=t, cycles=cycles, missed_cycles=missed_cycles,
                     period_jitter_p99_us=jitter_p99_us, period_jitter_max_us=jitter_max_us,
                     solve_median_us=solve_median_us, solve_p99_us=solve_p99_us,
                     solve_max_us=solve_max_us, dropped_messages=dropped_messages)


def joint_states(t: float, names: Sequence[str], table: np.ndarray,
                 drive_states: Sequence[str], currents: np.ndarray, header: np.ndarray,
                 status: Sequence[str], fallback: np.ndarray, decide_time: float) -> Message:
    """Every joint of one cycle, in the robot file's order, from the cycle's arrays: `table`
    the samples (rows of `driver.Sample` fields), `header` the MPC rows' headers
    (`controller.workspace`), `currents` what went out, `fallback` where the net overrode."""
    return JointStates(
        t=t, name=names, position=table[:, SAMPLE_POSITION].tolist(),
        velocity=table[:, SAMPLE_VELOCITY].tolist(),
        effort=table[:, SAMPLE_JOINT_TORQUE].tolist(),
        motor_current=table[:, SAMPLE_MOTOR_CURRENT].tolist(), current=currents.tolist(),
        planned_current=header[:, ws.PLANNED_CURRENT].tolist(),
        reference_position=header[:, ws.REFERENCE_POSITION].tolist(),
        drive_state=drive_states, solver_status=status,
        iterations=header[:, ws.ITERATIONS].astype(np.int64).tolist(),
        fallback=fallback.tolist(), solve_time_us=decide_time * 1e6)
