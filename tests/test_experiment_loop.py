"""Experiments (the recorder's trajectories) run in the control loop: the same typed messages,
the same safety net and the same reaction to a failing drive as the MPC."""

import math

from controller.messages import topic_of
from controller.safety import SafetyNet
from driver import Sample
from driver.clock import DriveClock
from driver.drive_group import single_joint
from model import dynamics
from model.parameters import load_model
from recorder.exciting import SlowSinusoid
from recorder.experiment import run_trajectory
from recorder.tracking import TrackingLaw, TrackingPolicy
from sim_bus.faults import Fault
from tests.conftest import virtual_pair

MODEL = load_model()
LAW = TrackingLaw(MODEL.parameters, MODEL.limits.current_max)
# the virtual drive's compiled physics loaded now: loading it inside the first SYNC would starve
# the (wall-clock) heartbeat on a busy machine
dynamics.step(0.0, 0.0, 0.0, MODEL.parameters.packed(), 1e-3, 1)


def record(duration: float, fault: Fault | None = None, at: float = 0.0):
    received = []
    with virtual_pair() as (sim, drive):
        drive.start()
        if fault is not None:
            sim.device.schedule(fault, at)
        report = run_trajectory(single_joint(drive), SlowSinusoid(duration=duration), LAW,
                                MODEL.limits,
                                [lambda message: received.append((topic_of(message), message))],
                                clock=DriveClock())
    return report, received


def test_a_trajectory_runs_to_its_end_through_the_loop():
    report, received = record(0.5)
    assert report.exit_code == 0 and report.reason == "the policy finished"
    states = [m for topic, m in received if topic == "state"]
    commands = [m for topic, m in received if topic == "command"]
    assert len(states) == len(commands) == report.cycles == 501  # t0 ... t0 + 0.5 s
    assert states[-1].t - states[0].t >= 0.5
    assert all(abs(c.current) <= c.current_limit == MODEL.limits.current_max for c in commands)
    assert not any(c.fallback for c in commands)
    assert abs(states[-1].position - commands[-1].reference_position) < 0.05  # it tracks


def test_a_drive_fault_stops_a_recording_with_a_fault_message():
    report, received = record(2.0, Fault.ENCODER_GLITCH, 0.3)
    assert report.exit_code == 1 and "encoder glitch" in report.reason
    faults = [m for topic, m in received if topic == "fault"]
    assert faults[-1].source == "drive" and "encoder glitch" in faults[-1].cause
    assert report.cycles < 400


def test_the_safety_net_guards_the_tracking_law():
    net = SafetyNet(TrackingPolicy(SlowSinusoid(), LAW, MODEL.limits))
    assert net.decide(Sample(0.0, -1.2, 0.0, 0.0, 0.0, 0)).fault is None
    unbelievable = net.decide(Sample(0.001, math.nan, 0.0, 0.0, 0.0, 0))
    assert unbelievable.current == 0.0 and "non-finite" in unbelievable.fault
    out_of_range = net.decide(Sample(0.002, 1.0, 0.0, 0.0, 0.0, 0))
    assert "out of range" in out_of_range.fault
    assert out_of_range.current == net.hold_current(1.0)
