"""One path for a joint and a robot (issue 22 items 2 and 4): a robot's requests reach the joint
they name and no other, a robot of one publishes the single joint's own topics, and the loop's
rhythm on drive time is never late."""

import json

from controller.loop import ControlLoop, LoopOptions
from controller.mpc import BatchMpc, JointProblem
from controller.requests import Body, RequestHandler
from driver.clock import CycleClock, DriveClock
from model.parameters import Payload, load_model
from protocol import telemetry

MODEL = load_model()


class _Named:
    """Joints the loop is built on but never runs (requests queue up): names and a period."""

    names = ["shoulder", "elbow"]
    period = 1e-3


def body(data: bytes) -> Body:
    return Body(len(data), lambda: data)


def test_a_robots_weights_request_changes_the_joint_it_names_and_is_audited_as_its():
    batch = BatchMpc([JointProblem(MODEL), JointProblem(MODEL)])
    loop = ControlLoop(_Named(), batch, LoopOptions(clock=DriveClock()))
    audit: list[str] = []
    elbow = RequestHandler(loop, 1, MODEL, Payload(), audit.append)
    before = batch.joints[0].settings.weights
    assert elbow.set_weights(body(b'{"position": 400}'))["ok"]
    while loop._requests:  # what the loop runs at the start of its next cycle
        loop._requests.popleft()()
    assert batch.joints[1].settings.weights.position == 400.0
    assert batch.joints[0].settings.weights == before  # the other joint untouched
    record = json.loads(audit[-1])
    assert record["joint"] == "elbow" and record["request"] == "weights" and record["accepted"]


def test_a_robot_of_one_keeps_the_single_joint_topics_and_a_robot_publishes_joints():
    assert set(telemetry.topics(1)) == {"state", "command", "plan", "solver", "fault",
                                        "loop_stats"}
    assert set(telemetry.topics(7)) == {"joints", "fault", "loop_stats"}
    assert telemetry.key_expr("robots/talos", telemetry.joint_key("elbow", telemetry.WEIGHTS)
                              ) == "robots/talos/joints/elbow/weights"


def test_on_drive_time_a_cycle_is_never_late_and_the_period_never_jitters():
    clock = CycleClock(1e-3, DriveClock())
    for _ in range(100):
        assert clock.wait() == 0
        assert not clock.check_overrun()
    assert clock.missed_cycles == 0 and clock.jitter_us.max < 1e-6  # us: rounding only
    assert abs(clock.clock.now() - 0.1) < 1e-9  # a deadline waited for is drive time reached
