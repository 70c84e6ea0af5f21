"""The batched MPC: J joints in one compiled call give each joint exactly what it gets alone,
a skipped joint is left alone, and the plan handed to telemetry is a copy."""

from pathlib import Path

import numpy as np
import pytest

from controller import workspace
from controller.mpc import BatchMpc, JointProblem, Mpc
from controller.problem import OcpSettings, resolvable_friction_sharpness
from controller.reference import Setpoint, Sinusoid
from driver import Sample
from model import dynamics
from model.parameters import Payload, load_model

MODEL = load_model()
DT = 1e-3


def problems() -> list[JointProblem]:
    """Four joints that differ in payload, weights and reference."""
    return [JointProblem(MODEL),
            JointProblem(MODEL, payload=Payload(10.0, 0.0, 0.05), reference=Setpoint(-1.0)),
            JointProblem(MODEL, OcpSettings().with_weights(position=200.0),
                         reference=Sinusoid(center=-1.2, amplitude=0.5, frequency=0.5)),
            JointProblem(MODEL, payload=Payload(3.0, 0.02, 0.0), reference=Setpoint(-2.0))]


def closed_loop(tick, parameters, steps):
    """Every joint on its exact model; tick(t, positions, velocities) -> decisions."""
    states = np.array([[-0.4, 0.0]] * len(parameters))
    history = []
    for k in range(steps):
        decisions = tick(k * DT, states[:, 0], states[:, 1])
        history.append(decisions)
        for j, decision in enumerate(decisions):
            current = float(np.clip(decision.planned_current, -6.0, 6.0))
            states[j] = dynamics.step(states[j, 0], states[j, 1], current, parameters[j], DT,
                                      20)[:2]
    return history


def test_a_batch_decides_for_each_joint_exactly_what_it_decides_alone():
    batch = BatchMpc(problems())
    alone = [Mpc(p.model, p.settings, p.payload, p.reference) for p in problems()]
    parameters = [joint.packed_parameters for joint in batch.joints]

    def one_by_one(t, positions, velocities):
        return [mpc.tick(Sample(t, q, qd, 0.0, 0.0, 0))
                for mpc, q, qd in zip(alone, positions, velocities, strict=True)]

    together = closed_loop(batch.tick, parameters, 300)
    separately = closed_loop(one_by_one, parameters, 300)
    assert together == separately  # bit for bit, every field of every decision
    currents = np.array([[d.planned_current for d in ds] for ds in together])
    assert len({round(c, 3) for c in currents[-1]}) == 4  # the joints really differ
    assert all(d.ok for d in together[-1])


def test_a_skipped_joint_is_left_untouched_and_starts_cold_after():
    batch = BatchMpc(problems()[:2])
    first, second = batch.joints
    batch.tick(0.0, [-0.4, -0.4], [0.0, 0.0])
    kept = second.row.copy()
    batch.prepare(first, -0.4, 0.0)
    batch.skip(second)
    batch.run(DT)
    untouched = np.arange(len(kept)) != workspace.MODE  # only its mode was written
    assert np.array_equal(second.row[untouched], kept[untouched])
    assert batch.decision(first).ok
    batch.prepare(second, -0.4, 0.0)
    batch.run(2 * DT)
    assert batch.decision(second).status == "converged"  # a cold solve to convergence


def test_the_plan_is_a_snapshot_not_the_solver_buffers():
    mpc = Mpc(MODEL, reference=Setpoint(-1.0))
    mpc.tick(Sample(0.0, -0.4, 0.0, 0.0, 0.0, 0))
    plan = mpc.plan(0.0)
    before = plan.current.copy(), plan.position.copy()
    for k in range(1, 20):
        mpc.tick(Sample(k * DT, -0.4 - 0.001 * k, -0.5, 0.0, 0.0, 0))
    assert np.array_equal(plan.current, before[0]) and np.array_equal(plan.position, before[1])
    assert not np.array_equal(mpc.plan(19 * DT).current, plan.current)
    assert len(plan.position) == 101 and len(plan.current) == 100


def test_a_new_horizon_rebuilds_the_batch_cold():
    mpc = Mpc(MODEL, reference=Setpoint(-1.0))
    mpc.tick(Sample(0.0, -0.4, 0.0, 0.0, 0.0, 0))
    mpc.set_settings(OcpSettings(horizon=50))
    decision = mpc.tick(Sample(DT, -0.4, 0.0, 0.0, 0.0, 0))
    assert decision.status == "converged" and len(mpc.plan(DT).current) == 50


def test_joints_need_one_horizon():
    with pytest.raises(ValueError, match="same horizon"):
        BatchMpc([JointProblem(MODEL), JointProblem(MODEL, OcpSettings(horizon=50))])


WRIST = load_model(Path(__file__).parent.parent / "robots" / "models" / "talos_wrist.toml")


def test_a_friction_the_step_cannot_resolve_is_softened_a_stable_one_kept():
    """TALOS's wrist at beta 1000 and 1 ms: dt (Fv + beta Fs) / I = 2.001, an unstable
    discrete model; the solver's beta is the one-step stop (dt k = 1). The paper's elbow
    (dt k = 1.92) keeps the paper's beta."""
    settings = OcpSettings()
    wrist = WRIST.parameters.packed()
    p = dynamics
    stiffness = (wrist[p.P_VISCOUS] + 1000.0 * wrist[p.P_DRY]) / wrist[p.P_INERTIA]
    assert settings.dt * stiffness > 2.0  # the case this is about
    beta = resolvable_friction_sharpness(settings, wrist)
    assert settings.dt * (wrist[p.P_VISCOUS] + beta * wrist[p.P_DRY]) == pytest.approx(
        wrist[p.P_INERTIA])
    assert resolvable_friction_sharpness(settings, MODEL.parameters.packed()) == 1000.0


def test_the_wrist_tracks_with_one_simulation_most_ticks():
    """Closed loop on the wrist's exact model, past the approach (0.6 s): the warm tick's line
    search accepts its first or second trial in nearly every tick. Measured: every one of
    those 1400 ticks took one simulation; with the unstable friction step (beta 1000 at 1 ms)
    25 % took more than two, 13 % failing their warm line search and solving anew (12 to 14
    simulations)."""
    batch = BatchMpc([JointProblem(WRIST, reference=Sinusoid(0.0, 1.255, 0.19))])
    history = closed_loop(batch.tick, [WRIST.parameters.packed()], 2000)
    rollouts = np.array([decisions[0].rollouts for decisions in history[600:]])
    assert all(decisions[0].ok for decisions in history)
    assert np.mean(rollouts > 2) < 0.05, np.bincount(rollouts)


def test_the_reports_give_the_friction_sharpness_the_solver_uses_beside_the_set_one():
    """A wrist set to the paper's beta is solved with the softened one: the parameters
    reports say both, the batch's row and the problem alike, so a user reading 1000 is not
    misled about what the MPC models."""
    problem = JointProblem(WRIST, OcpSettings())
    batch = BatchMpc([problem])
    solved = resolvable_friction_sharpness(problem.settings, WRIST.parameters.packed())
    assert solved < problem.settings.friction_sharpness == 1000.0
    assert problem.friction_sharpness_solved == batch.joints[0].friction_sharpness_solved
    assert batch.joints[0].friction_sharpness_solved == pytest.approx(solved)
