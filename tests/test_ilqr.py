"""The solver: compiled vs readable reference, convergence, warm-started ticks, safety net."""

import math

import numpy as np
import pytest

from controller import ilqr_reference
from controller.mpc import Mpc
from controller.problem import OcpSettings, pack_cost
from controller.reference import ReferenceError, Setpoint, Sinusoid, reference_at
from controller.safety import SafetyNet
from driver import Sample
from model import dynamics
from model.parameters import load_model

MODEL = load_model()
P = MODEL.parameters.packed()


def problem(settings=OcpSettings()):
    return settings, pack_cost(settings, MODEL.limits, P)


@pytest.mark.parametrize("reference", [Sinusoid(), Setpoint(-1.0)])
def test_compiled_solver_matches_the_numpy_reference(reference):
    settings, c = problem()
    t = np.arange(settings.horizon + 1) * settings.dt
    ref = np.stack(reference_at(reference.packed(), t), axis=1)
    mpc = Mpc(MODEL, settings, reference=reference)
    result = mpc.solve(-0.4, 0.0, 0.0, initial_current=0.0, max_iterations=100)
    plan = mpc.plan(0.0)
    X, U, cost, iterations, converged = ilqr_reference.solve((-0.4, 0.0), np.zeros(100), ref,
                                                            P, c, 100)
    assert result.status == "converged" and converged
    assert result.iterations == iterations
    assert result.cost == pytest.approx(cost, rel=1e-10)
    np.testing.assert_allclose(plan.current, U, atol=1e-9)
    np.testing.assert_allclose(np.stack((plan.position, plan.velocity), axis=1), X, atol=1e-12)


def test_cold_solve_converges_and_lowers_the_cost():
    mpc = Mpc(MODEL, reference=Setpoint(-1.0))
    first = mpc.solve(-0.4, 0.0, 0.0, initial_current=0.0, max_iterations=0)
    solved = mpc.solve(-0.4, 0.0, 0.0, initial_current=0.0, max_iterations=100)
    plan = mpc.plan(0.0)
    assert solved.status == "converged"
    assert solved.iterations < 30
    assert solved.cost < first.cost
    assert plan.current[0] < -3.0  # pulls hard down toward -1 rad, within the barrier
    assert np.all(np.abs(plan.current) < MODEL.limits.current_max)


def tick(mpc, position, velocity, t):
    """The MPC behind the loop's safety net, as the control loop runs it."""
    return SafetyNet(mpc).decide(Sample(t, position, velocity, 0.0, 0.0, 0))


def closed_loop(mpc, steps, q=-0.4, qd=0.0):
    """MPC on the exact model (no bus): returns positions and commands."""
    qs, us = [], []
    net = SafetyNet(mpc)
    for k in range(steps):
        r = net.decide(Sample(k * 1e-3, q, qd, 0.0, 0.0, 0))
        qs.append(q)
        us.append(r.current)
        q, qd, *_ = dynamics.step(q, qd, r.current, P, 1e-3, 20)
    return np.array(qs), np.array(us)


def test_warm_started_ticks_track_a_setpoint():
    mpc = Mpc(MODEL, reference=Setpoint(-1.2))
    qs, us = closed_loop(mpc, 1500)
    assert abs(qs[-1] + 1.2) < 0.02
    assert np.all(np.abs(us) <= MODEL.limits.current_max)
    hold = SafetyNet(mpc).hold_current(qs[-1])
    assert abs(us[-1] - hold) < 0.5  # dry friction allows a band around pure gravity holding


def test_reference_change_mid_run_is_followed():
    mpc = Mpc(MODEL, reference=Setpoint(-0.8))
    closed_loop(mpc, 300)
    mpc.set_reference(Setpoint(-1.5))
    qs, _ = closed_loop(mpc, 1500, q=-0.8)
    assert abs(qs[-1] + 1.5) < 0.03


@pytest.mark.parametrize("position,velocity,expected", [
    (math.nan, 0.0, 0.0),
    (-1.0, math.inf, 0.0),
])
def test_non_finite_state_gives_zero_current_and_a_fault(position, velocity, expected):
    mpc = Mpc(MODEL)
    result = tick(mpc, position, velocity, 0.0)
    assert result.current == expected
    assert "non-finite state" in result.fault


def test_out_of_range_state_holds_within_limits():
    mpc = Mpc(MODEL)
    result = tick(mpc, -3.5, 0.0, 0.0)
    assert "out of range" in result.fault
    assert abs(result.current) <= MODEL.limits.current_max
    assert result.current == pytest.approx(SafetyNet(mpc).hold_current(-3.5))


def test_diverging_solve_falls_back_to_holding():
    settings = OcpSettings().with_weights(position=1e308)  # the cost overflows to inf
    mpc = Mpc(MODEL, settings)
    result = tick(mpc, -1.0, 0.0, 0.0)
    assert not result.decision.ok
    assert result.fault.startswith(f"solver {result.decision.status}")
    assert result.current == pytest.approx(SafetyNet(mpc).hold_current(-1.0))


@pytest.mark.parametrize("reference,message", [
    (Setpoint(-5.0), "spans"),
    (Setpoint(math.nan), "expected a finite number"),
    (Sinusoid(frequency=3.0), "peak velocity"),
])
def test_infeasible_reference_is_refused_and_the_old_one_kept(reference, message):
    mpc = Mpc(MODEL, reference=Setpoint(-1.0))
    with pytest.raises(ReferenceError, match=message):
        mpc.set_reference(reference)
    assert mpc.reference == Setpoint(-1.0)


def test_settings_reject_bad_values():
    with pytest.raises(ValueError, match="horizon"):
        OcpSettings(horizon=1)
    with pytest.raises(ValueError, match="position must be finite and >= 0"):
        OcpSettings().with_weights(position=-1.0)
