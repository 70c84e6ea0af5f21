"""Telemetry messages: one protobuf schema per message, the same bytes on Zenoh, in MCAP and
over the Foxglove bridge. The schema is data (below); `telemetry.proto` beside this file is
generated from it for people writing subscribers in other languages.

Key expressions live under a prefix, e.g. `actuators/elbow`:
    {prefix}/state       State        every control cycle
    {prefix}/command     Command      every control cycle
    {prefix}/plan        Plan         every `plan_every` cycles (predicted trajectory)
    {prefix}/solver      SolverStats  every control cycle
    {prefix}/fault       Fault        when something goes wrong (or a request is refused)
    {prefix}/loop_stats  LoopStats    once a second and at exit
    {prefix}/joints      JointStates  every control cycle, every joint (a robot of several
                                      joints: it replaces state, command, plan and solver)
    {prefix}/parameters  queryable: model parameters, limits and solver settings (JSON)
    {prefix}/joints/{name}/reference  queryable: set joint `name`'s reference, payload JSON;
                         reply {"ok", "reason"} (a robot of one joint also at
                         {prefix}/reference)
    {prefix}/joints/{name}/weights    queryable: set joint `name`'s cost weights, e.g.
                         {"position": 300}; same reply (one joint: also {prefix}/weights)
    {prefix}/audit       JSON line for every change request, accepted or refused
    {prefix}/alive       liveliness token of the actuatord publishing under the prefix: gone
                         when the process is (dashboards show it)
"""

import time
from functools import cache

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

PACKAGE = "actuator"
DOUBLE = descriptor_pb2.FieldDescriptorProto.TYPE_DOUBLE
UINT32 = descriptor_pb2.FieldDescriptorProto.TYPE_UINT32
UINT64 = descriptor_pb2.FieldDescriptorProto.TYPE_UINT64
BOOL = descriptor_pb2.FieldDescriptorProto.TYPE_BOOL
STRING = descriptor_pb2.FieldDescriptorProto.TYPE_STRING
REPEATED = "repeated"

# message -> [(field, type, unit or meaning)], field numbers in order from 1.
SCHEMAS: dict[str, list[tuple]] = {
    "State": [
        ("t", DOUBLE, "s, drive time (SYNC count x period)"),
        ("position", DOUBLE, "rad"),
        ("velocity", DOUBLE, "rad/s"),
        ("motor_current", DOUBLE, "A"),
        ("joint_torque", DOUBLE, "N.m, torque-sensor reading"),
        ("statusword", UINT32, "CiA 402 statusword"),
        ("drive_state", STRING, "CiA 402 state name"),
    ],
    "Command": [
        ("t", DOUBLE, "s"),
        ("current", DOUBLE, "A, sent to the drive"),
        ("planned_current", DOUBLE, "A, what the solver asked for"),
        ("reference_position", DOUBLE, "rad"),
        ("reference_velocity", DOUBLE, "rad/s"),
        ("current_limit", DOUBLE, "A"),
        ("position_min", DOUBLE, "rad"),
        ("position_max", DOUBLE, "rad"),
        ("saturated", BOOL, "the command was clipped to the current limit"),
        ("fallback", BOOL, "the safety net replaced the solver's command"),
    ],
    "Plan": [
        ("t", DOUBLE, "s, time of the first point"),
        ("dt", DOUBLE, "s between points"),
        ("position", DOUBLE, "rad", REPEATED),
        ("velocity", DOUBLE, "rad/s", REPEATED),
        ("current", DOUBLE, "A", REPEATED),
        ("reference_position", DOUBLE, "rad", REPEATED),
    ],
    "SolverStats": [
        ("t", DOUBLE, "s"),
        ("solve_time_us", DOUBLE, "us, wall time of the MPC tick"),
        ("iterations", UINT32, "iLQR iterations"),
        ("rollouts", UINT32, "trajectory simulations incl. line-search trials"),
        ("status", STRING, "converged | max_iterations | line_search_failed | not_finite"),
        ("cost", DOUBLE, "objective value"),
    ],
    "Fault": [
        ("t", DOUBLE, "s"),
        ("source", STRING, "drive | controller | solver | request"),
        ("cause", STRING, "what happened"),
        ("action", STRING, "what was done about it"),
    ],
    # every joint of a robot in one message per cycle (actuatord --robot); the first three
    # repeated fields are named as ROS's sensor_msgs/JointState and foxglove's joint states
    "JointStates": [
        ("t", DOUBLE, "s, drive time of the cycle (every joint sampled in it)"),
        ("name", STRING, "joint names, in the robot file's order", REPEATED),
        ("position", DOUBLE, "rad", REPEATED),
        ("velocity", DOUBLE, "rad/s", REPEATED),
        ("effort", DOUBLE, "N.m, joint torque-sensor reading", REPEATED),
        ("motor_current", DOUBLE, "A, measured", REPEATED),
        ("current", DOUBLE, "A, commanded (after the safety net)", REPEATED),
        ("planned_current", DOUBLE, "A, what the solver asked for", REPEATED),
        ("reference_position", DOUBLE, "rad", REPEATED),
        ("drive_state", STRING, "CiA 402 state name", REPEATED),
        ("solver_status", STRING, "converged | max_iterations | ... per joint", REPEATED),
        ("iterations", UINT32, "iLQR iterations per joint", REPEATED),
        ("fallback", BOOL, "the safety net replaced the solver's command", REPEATED),
        ("solve_time_us", DOUBLE, "us, wall time of the batched MPC tick (all joints)"),
    ],
    "LoopStats": [
        ("t", DOUBLE, "s"),
        ("cycles", UINT64, "control cycles run"),
        ("missed_cycles", UINT64, "cycles whose work overran the period"),
        ("period_jitter_p99_us", DOUBLE,
         "us, |actual - nominal period|, since the last LoopStats (the last: the run's)"),
        ("period_jitter_max_us", DOUBLE, "us, over the run"),
        ("solve_median_us", DOUBLE, "us, since the last LoopStats (the last: the run's)"),
        ("solve_p99_us", DOUBLE, "us, since the last LoopStats (the last: the run's)"),
        ("solve_max_us", DOUBLE, "us, over the run"),
        ("dropped_messages", UINT64, "telemetry messages dropped (publisher queue full)"),
    ],
}

# every topic a control loop publishes on, and its message: the one set for one joint and for a
# robot. A robot publishes every joint in one `joints` message a cycle; a robot of one joint
# keeps the single joint's own view instead (state, command, plan, solver), which dashboards,
# recordings and their layouts read. `fault` and `loop_stats` either way (`topics`).
TOPICS = {"state": "State", "command": "Command", "plan": "Plan", "solver": "SolverStats",
          "joints": "JointStates", "fault": "Fault", "loop_stats": "LoopStats"}
JOINT_VIEW = ("state", "command", "plan", "solver")
ROBOT_VIEW = ("joints",)


def topics(joints: int) -> dict[str, str]:
    """The topics (and their messages) a robot of `joints` joints publishes on."""
    view = JOINT_VIEW if joints == 1 else ROBOT_VIEW
    return {topic: name for topic, name in TOPICS.items()
            if topic in view or topic in ("fault", "loop_stats")}


# the audit lines (JSON, controller.requests.audit_line) as a named JSON schema, so viewers
# show `actuator.Audit` rather than a generated name
AUDIT_SCHEMA_NAME = f"{PACKAGE}.Audit"
AUDIT_SCHEMA = {
    "title": AUDIT_SCHEMA_NAME, "type": "object",
    "description": "one change request to actuatord, accepted or refused, at most 1 KiB",
    "properties": {
        "time": {"type": "string", "description": "UTC, ISO 8601, when it was handled"},
        "t": {"type": "number", "description": "s, drive time"},
        "request": {"type": "string", "description": "reference | weights | parameters"},
        "joint": {"type": "string", "description": "the joint the request was for"},
        "payload_bytes": {"type": "integer", "description": "size of the request body"},
        "payload": {"type": "string", "description": "the body, quoted as far as fits"},
        "accepted": {"type": "boolean"},
        "reason": {"type": "string", "description": "why it was refused (empty if not)"}}}
PARAMETERS = "parameters"
REFERENCE = "reference"
WEIGHTS = "weights"
JOINTS = "joints"
AUDIT = "audit"
LIVELINESS = "alive"
DEFAULT_PREFIX = "actuators/elbow"


class TimeBase:
    """The run's time base: the wall clock (ns since the Unix epoch) at drive time 0, fixed at
    the first message stamped and advanced by drive time (`t`) from then on. Stamps on it keep
    the drive's rate and the experiment's duration however fast a lock-step run goes, and read
    as dates, not as 1970 plus a few seconds."""

    def __init__(self, epoch_ns: int | None = None):
        self.epoch_ns = epoch_ns

    def stamp(self, t: float) -> int:
        """ns since the Unix epoch of drive time `t` (s)."""
        drive_ns = int(round(t * 1e9))
        if self.epoch_ns is None:
            self.epoch_ns = time.time_ns() - drive_ns
        return self.epoch_ns + drive_ns


def key_expr(prefix: str, topic: str) -> str:
    return f"{prefix.rstrip('/')}/{topic}"


def joint_key(joint: str, request: str) -> str:
    """The key under the prefix of one joint's request queryable, e.g. joints/elbow/weights."""
    return f"{JOINTS}/{joint}/{request}"


@cache
def file_descriptor() -> descriptor_pb2.FileDescriptorProto:
    proto = descriptor_pb2.FileDescriptorProto(name="actuator/telemetry.proto", package=PACKAGE,
                                               syntax="proto3")
    for name, fields in SCHEMAS.items():
        message = proto.message_type.add(name=name)
        for number, spec in enumerate(fields, start=1):
            label = (descriptor_pb2.FieldDescriptorProto.LABEL_REPEATED
                     if len(spec) > 3 and spec[3] == REPEATED
                     else descriptor_pb2.FieldDescriptorProto.LABEL_OPTIONAL)
            message.field.add(name=spec[0], number=number, type=spec[1], label=label)
    return proto


@cache
def _pool() -> descriptor_pool.DescriptorPool:
    pool = descriptor_pool.DescriptorPool()
    pool.Add(file_descriptor())
    return pool


@cache
def message_class(name: str) -> type:
    """The protobuf class of a message, e.g. message_class('State')."""
    return message_factory.GetMessageClass(_pool().FindMessageTypeByName(f"{PACKAGE}.{name}"))


def schema_name(name: str) -> str:
    return f"{PACKAGE}.{name}"


def file_descriptor_set() -> bytes:
    """What MCAP and Foxglove want as a protobuf schema's data."""
    return descriptor_pb2.FileDescriptorSet(file=[file_descriptor()]).SerializeToString()


def proto_text() -> str:
    """The schema as a .proto file (the shipped telemetry.proto is exactly this)."""
    names = {DOUBLE: "double", UINT32: "uint32", UINT64: "uint64", BOOL: "bool",
             STRING: "string"}
    lines = ["// Generated from protocol/telemetry.py: the telemetry of actuatord.",
             'syntax = "proto3";', f"package {PACKAGE};", ""]
    for name, fields in SCHEMAS.items():
        lines.append(f"message {name} {{")
        for number, spec in enumerate(fields, start=1):
            prefix = "repeated " if len(spec) > 3 and spec[3] == REPEATED else ""
            lines.append(f"  {prefix}{names[spec[1]]} {spec[0]} = {number};  // {spec[2]}")
        lines.append("}")
        lines.append("")
    return "\n".join(lines)


def decode(name: str, data: bytes):
    """Parse bytes of message `name`; raises google.protobuf.message.DecodeError if malformed."""
    message = message_class(name)()
    message.ParseFromString(data)
    return message
