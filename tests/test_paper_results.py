"""The paper's simulation results, reproduced in lock-step on the virtual drive over CANopen
(deterministic: seeded sensor noise, each SYNC advances the physics one period)."""

import numpy as np
import pytest

from controller.loop import ControlLoop, LoopOptions
from controller.mpc import Mpc
from controller.problem import OcpSettings
from driver.clock import DriveClock
from driver.drive_group import single_joint
from model.parameters import Payload, load_model
from tests.conftest import virtual_pair

MODEL = load_model()
LIMIT = MODEL.limits.current_max
ONE_SWING = 5.0  # s: one period of the default 0.2 Hz sinusoid, down past -2.35 rad and back


def run(payload=Payload(), settings=OcpSettings(), duration=ONE_SWING):
    with virtual_pair(payload=payload) as (_, drive):
        drive.start()
        mpc = Mpc(MODEL, settings, payload)
        loop = ControlLoop(single_joint(drive), mpc,
                           LoopOptions(clock=DriveClock(), duration=duration,
                                       keep_history=True))
        report = loop.run()
    assert report.exit_code == 0, report.reason
    return {k: np.array(v) for k, v in report.history.items()}


@pytest.fixture(scope="module")
def unloaded():
    return run()


@pytest.fixture(scope="module")
def loaded():
    return run(Payload(30.0, 0.0, 0.05))


def test_sinusoid_past_the_limit_plateaus_before_it(unloaded):
    h = unloaded
    assert h["reference"].min() < -2.45  # the reference does cross the -2.35 rad limit
    assert h["position"].min() > MODEL.limits.position_min
    assert h["position"].min() < MODEL.limits.position_min + 0.2  # a plateau close to it
    # while the reference is below the limit the joint stays nearly still: a plateau
    below = h["reference"] < MODEL.limits.position_min
    assert np.ptp(h["position"][below]) < 0.05
    # away from the limit it tracks (after the first 0.3 s settling from rest)
    free = (h["t"] > 0.3) & (h["reference"] > -2.0)
    assert np.sqrt(np.mean((h["position"][free] - h["reference"][free]) ** 2)) < 0.02


def test_heavy_payload_current_plateaus_below_the_limit_and_tracking_degrades(unloaded,
                                                                              loaded):
    assert np.all(np.abs(loaded["current"]) <= LIMIT)
    peak = loaded["current"].min()
    assert -LIMIT < peak < -5.0  # the paper: a plateau around -5.6 A under the 6 A limit
    plateau = loaded["current"] < peak + 0.2
    assert plateau.sum() > 100  # held there for a while, not a spike
    settled = unloaded["t"] > 0.3  # after the initial pull from rest to the reference
    assert np.abs(unloaded["current"][settled]).max() < 3.5  # far from the limit without load

    def tracking(h):
        free = (h["t"] > 0.3) & (h["reference"] > MODEL.limits.position_min + 0.2)
        return np.sqrt(np.mean((h["position"][free] - h["reference"][free]) ** 2))

    assert tracking(loaded) > 2 * tracking(unloaded)


def test_without_the_current_barrier_the_solver_goes_past_the_limit(loaded):
    free = run(Payload(30.0, 0.0, 0.05), OcpSettings().with_weights(torque_barrier=0.0))
    assert free["planned_current"].min() < -LIMIT  # the paper's Fig. 8: past the limit
    assert np.all(np.abs(free["current"]) <= LIMIT)  # ... but never sent to the drive
    assert loaded["planned_current"].min() > -LIMIT
