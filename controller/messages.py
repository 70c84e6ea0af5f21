"""The telemetry messages of a control loop, built in one place as the protobuf messages of
`protocol.telemetry`: a misspelt field or a value of the wrong type fails here, in the caller's
thread (protobuf checks both at construction), not later in a publisher thread. Every
subscriber (Zenoh, an MCAP recording, a test) receives the same objects.
"""

from collections.abc import Callable, Sequence

from google.protobuf.message import Message

from controller.policy import PlanSnapshot
from controller.safety import SafeCommand
from driver import Sample
from model.parameters import Limits
from protocol import telemetry

State = telemetry.message_class("State")
Command = telemetry.message_class("Command")
SolverStats = telemetry.message_class("SolverStats")
Plan = telemetry.message_class("Plan")
Fault = telemetry.message_class("Fault")
LoopStats = telemetry.message_class("LoopStats")

JointStates = telemetry.message_class("JointStates")

_TOPICS = {telemetry.message_class(name): topic
           for topic, name in (*telemetry.TOPICS.items(), *telemetry.ROBOT_TOPICS.items())}

Subscriber = Callable[[Message], None]


def topic_of(message: Message) -> str:
    """The key under the prefix ('state', 'command', ...) a message is published on."""
    return _TOPICS[type(message)]


def state(sample: Sample, drive_state: str) -> Message:
    return State(t=sample.t, position=sample.position, velocity=sample.velocity,
                 motor_current=sample.motor_current, joint_torque=sample.joint_torque,
                 statusword=sample.statusword, drive_state=drive_state)


def command(t: float, safe: SafeCommand, limits: Limits) -> Message:
    decision = safe.decision
    return Command(t=t, current=safe.current, planned_current=decision.planned_current,
                   reference_position=decision.reference_position,
                   reference_velocity=decision.reference_velocity,
                   current_limit=limits.current_max, position_min=limits.position_min,
                   position_max=limits.position_max, saturated=safe.saturated,
                   fallback=safe.fault is not None)


def solver_stats(t: float, safe: SafeCommand, decide_time: float) -> Message:
    decision = safe.decision
    return SolverStats(t=t, solve_time_us=decide_time * 1e6, iterations=decision.iterations,
                       rollouts=decision.rollouts, status=decision.status, cost=decision.cost)


def plan(snapshot: PlanSnapshot) -> Message:
    return Plan(t=snapshot.t, dt=snapshot.dt, position=snapshot.position.tolist(),
                velocity=snapshot.velocity.tolist(), current=snapshot.current.tolist(),
                reference_position=snapshot.reference_position.tolist())


def fault(t: float, source: str, cause: str, action: str) -> Message:
    return Fault(t=t, source=source, cause=cause, action=action)


def loop_stats(t: float, cycles: int, missed_cycles: int, jitter_p99_us: float,
               jitter_max_us: float, solve_median_us: float, solve_p99_us: float,
               solve_max_us: float, dropped_messages: int) -> Message:
    return LoopStats(t=t, cycles=cycles, missed_cycles=missed_cycles,
                     period_jitter_p99_us=jitter_p99_us, period_jitter_max_us=jitter_max_us,
                     solve_median_us=solve_median_us, solve_p99_us=solve_p99_us,
                     solve_max_us=solve_max_us, dropped_messages=dropped_messages)


def joint_states(t: float, names: Sequence[str], samples: Sequence[Sample],
                 drive_states: Sequence[str], commands: Sequence[SafeCommand],
                 decide_time: float) -> Message:
    """Every joint of one cycle, in the robot file's order."""
    return JointStates(
        t=t, name=names, position=[s.position for s in samples],
        velocity=[s.velocity for s in samples], effort=[s.joint_torque for s in samples],
        motor_current=[s.motor_current for s in samples], current=[c.current for c in commands],
        planned_current=[c.decision.planned_current for c in commands],
        reference_position=[c.decision.reference_position for c in commands],
        drive_state=drive_states, solver_status=[c.decision.status for c in commands],
        iterations=[c.decision.iterations for c in commands],
        fallback=[c.fault is not None for c in commands], solve_time_us=decide_time * 1e6)
