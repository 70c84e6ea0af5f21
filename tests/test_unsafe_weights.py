"""Weights the controller cannot keep safe are refused, over Zenoh and on the command line,
as references beyond the limits are (issue 28 item 6): {"position": 1e6} and
{"position_barrier": 0} faulted the drive within 2.3 s. The bound (position <= position_barrier
x alpha / (2 x 0.5 rad)) is shown to be where safety ends: at the bound the joint holds against
a setpoint 0.5 rad beyond its lower limit, at twice the bound it leaves the drive's window."""

import json

import pytest

from commands.actuatord import main
from controller.loop import ControlLoop, LoopOptions
from controller.mpc import Mpc
from controller.problem import OcpSettings, UnsafeWeights
from controller.requests import Body, RequestHandler
from driver.clock import DriveClock
from driver.drive_group import single_joint
from model.parameters import Payload, load_model
from tests.conftest import virtual_pair

MODEL = load_model()
BEYOND_LOWER = '{"kind": "setpoint", "position": -2.85}'  # 0.5 rad past the elbow's -2.35


def body(data: bytes) -> Body:
    return Body(len(data), lambda: data)


@pytest.fixture
def handler():
    """A request handler on a loop that is built but not run, and its audit lines."""
    mpc = Mpc(MODEL)
    with virtual_pair() as (_, drive):
        audit: list[str] = []
        loop = ControlLoop(single_joint(drive), mpc, LoopOptions(clock=DriveClock()))
        yield RequestHandler(loop, 0, MODEL, Payload(), audit.append), audit, loop


@pytest.mark.parametrize("weights,needle", [
    ({"position": 1e6}, "expected position <= position_barrier x 10 / 1 = 1000"),
    ({"position_barrier": 0}, "position_barrier 0: expected > 0"),
    ({"position_barrier": 1}, "expected position <= position_barrier x 10 / 1 = 10"),
])
def test_unsafe_weights_are_refused_over_zenoh(handler, weights, needle):
    handler, audit, loop = handler
    answer = handler.set_weights(body(json.dumps(weights).encode()))
    assert answer["ok"] is False and needle in answer["reason"], answer
    assert json.loads(audit[-1])["accepted"] is False
    while loop._requests:  # what the loop would run at its next cycle
        loop._requests.popleft()()
    assert handler.joint.settings.weights == OcpSettings().weights  # unchanged


def test_safe_changes_are_accepted_and_a_pair_unsafe_together_is_not_applied(handler):
    handler, audit, loop = handler
    assert handler.set_weights(body(b'{"position": 1000}'))["ok"]
    assert handler.set_weights(body(b'{"position_barrier": 50}'))["ok"]  # each safe alone
    while loop._requests:
        loop._requests.popleft()()
    weights = handler.joint.settings.weights
    assert weights.position == 1000 and weights.position_barrier == 100  # the second held back
    assert handler.set_weights(body(b'{"position": 10000, "position_barrier": 1000}'))["ok"]


def test_the_rule_scales_with_the_barrier():
    OcpSettings().with_weights(position=1000).check_weights()
    OcpSettings().with_weights(position=1e5, position_barrier=1e4).check_weights()
    with pytest.raises(UnsafeWeights):
        OcpSettings().with_weights(position=1001).check_weights()


@pytest.mark.parametrize("weight", ["position=1e6", "position_barrier=0"])
def test_unsafe_weights_are_refused_on_the_command_line(capsys, weight):
    code = main(["--sim", "--weight", weight, "--no-multicast-scouting"])
    out, err = capsys.readouterr()
    assert code == 2 and len(err.strip().splitlines()) == 1 and "--weight" in err, err
    assert "enabled" not in out


@pytest.mark.parametrize("position,holds", [(1000, True), (2000, False)])
def test_the_bound_is_where_the_joint_stops_holding(capsys, monkeypatch, position, holds):
    """Lock-step on the embedded drive, a setpoint 0.5 rad beyond the lower limit: the joint
    settles inside the limit at the bound; at twice it, past the window (the check relaxed)."""
    argv = ["--sim", "--lockstep", "--duration", "3", "--weight", f"position={position}",
            "--reference", BEYOND_LOWER, "--no-multicast-scouting"]
    if holds:
        assert main(argv) == 0, capsys.readouterr()
        return
    monkeypatch.setattr(OcpSettings, "check_weights", lambda self: None)
    code = main(argv)
    out, err = capsys.readouterr()
    assert code == 1 and "drive left operation enabled" in out + err, (out, err)
