"""The robot's cycle screens and checks every joint at once on arrays (`BatchSafety`); the
per-joint `SafetyNet` is the reference, as the numpy iLQR is for the compiled one: the two
give the same command for every joint, believed states, states out of range, non-finite
states, failed and non-finite decisions alike."""

import math
from pathlib import Path

import numpy as np

from controller.policy import Decision
from controller.safety import BatchSafety, SafetyNet
from driver import Sample
from driver.clock import DriveClock
from model.parameters import load_model

REPO = Path(__file__).resolve().parent.parent
# the elbow and every TALOS joint model: gravity, offsets, limits and gains that differ
MODELS = [load_model()] + [load_model(path)
                           for path in sorted((REPO / "robots" / "models").glob("*.toml"))]


class _Policy:
    """Just what the net asks of a policy besides `tick`."""

    def __init__(self, model):
        self.parameters, self.limits = model.parameters, model.limits

    def reset(self) -> None:
        pass

    def reference_at(self, t: float) -> tuple[float, float]:
        return 0.0, 0.0


def test_the_batch_net_commands_what_each_joints_net_commands():
    rng = np.random.default_rng(7)
    models = [MODELS[k % len(MODELS)] for k in range(32)]
    nets = [SafetyNet(_Policy(model)) for model in models]
    batch = BatchSafety([m.parameters for m in models], [m.limits for m in models])
    for _ in range(200):
        low = np.array([m.limits.position_min for m in models])
        high = np.array([m.limits.position_max for m in models])
        positions = rng.uniform(low - 1.0, high + 1.0)  # some out of range
        velocities = rng.normal(0.0, 4.0, 32)
        positions[rng.random(32) < 0.05] = math.nan
        velocities[rng.random(32) < 0.05] = math.inf
        planned = rng.normal(0.0, 20.0, 32)  # some beyond the limits
        planned[rng.random(32) < 0.05] = math.nan
        ok = rng.random(32) < 0.9
        believed = batch.believed(positions, velocities)
        screened = batch.screened_currents(positions, velocities)
        checked = batch.checked_currents(positions, planned, ok)
        for j, net in enumerate(nets):
            sample = Sample(0.0, positions[j], velocities[j], 0.0, 0.0, 0x27)
            reference = net.screen(sample)
            assert believed[j] == (reference is None)
            if reference is not None:
                assert math.isclose(screened[j], reference.current, rel_tol=1e-12,
                                    abs_tol=1e-12), (j, screened[j], reference)
                continue
            decision = Decision(planned[j], 0.0, 0.0, "converged" if ok[j] else "failed",
                                bool(ok[j]))
            expected = net.check(sample, decision).current
            assert math.isclose(checked[j], expected, rel_tol=1e-12, abs_tol=1e-12), (
                j, checked[j], expected)


class _TwoJoints:
    """Two elbows at rest whose second one reports an impossible velocity at cycle 3."""

    names = ["left", "right"]

    def __init__(self):
        self.cycle = 0
        self.commands: list[np.ndarray] = []

    def sync(self) -> np.ndarray:
        self.cycle += 1
        rest = MODELS[0].limits.position_min + 0.5
        velocity = 1e3 if self.cycle == 3 else 0.0
        return np.array([[self.cycle * 1e-3, rest, 0.0, 0.0, 0.0, 0x0237],
                         [self.cycle * 1e-3, rest, velocity, 0.0, 0.0, 0x0237]])

    def command_currents(self, currents) -> None:
        self.commands.append(np.array(currents, dtype=float))

    def warnings(self) -> list[str]:
        return []

    def clock_trim(self) -> float:
        return 0.0


def test_a_joint_screened_out_of_the_batch_is_held_and_named_the_others_ticked():
    from controller.loop import ControlLoop, LoopOptions
    from controller.mpc import BatchMpc, JointProblem

    faults = []
    joints = _TwoJoints()
    batch = BatchMpc([JointProblem(MODELS[0]), JointProblem(MODELS[0])])
    loop = ControlLoop(joints, batch, LoopOptions(clock=DriveClock(), duration=5e-3),
                     [lambda m: faults.append(m) if type(m).__name__ == "Fault" else None])
    report = loop.run()
    assert report.exit_code == 0 and report.fallbacks == 1
    [fault] = [f for f in faults if "right" in f.cause]
    assert "state out of range" in fault.cause
    net = SafetyNet(_Policy(MODELS[0]))
    held = net.hold_current(MODELS[0].limits.position_min + 0.5)
    _, right = joints.commands[2]
    assert math.isclose(right, held, rel_tol=1e-12)  # the net's holding current
    # the screened joint skipped that tick and came back: every other cycle decided by the MPC
    assert all(np.isfinite(c).all() for c in joints.commands) and len(joints.commands) == 5
