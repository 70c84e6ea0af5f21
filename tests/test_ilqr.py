"""The solver: compiled vs readable reference, convergence, warm-started ticks, safety net."""

import math

import numpy as np
import pytest

from controller import ilqr_reference
from controller.ilqr import COLD, CONVERGED, IlqrSolver
from controller.mpc import Mpc
from controller.problem import OcpSettings, pack_cost
from controller.reference import ReferenceError, Setpoint, Sinusoid, reference_at
from model import dynamics
from model.parameters import load_model

MODEL = load_model()
P = MODEL.parameters.packed()


def problem(settings=OcpSettings()):
    return settings, pack_cost(settings, MODEL.limits, MODEL.parameters.drive_gain)


@pytest.mark.parametrize("reference", [Sinusoid(), Setpoint(-1.0)])
def test_compiled_solver_matches_the_numpy_reference(reference):
    settings, c = problem()
    reference = reference.packed()
    t = np.arange(settings.horizon + 1) * settings.dt
    ref = np.stack(reference_at(reference, t), axis=1)
    solver = IlqrSolver(settings, P, c)
    result = solver.tick((-0.4, 0.0), 0.0, reference, COLD, 0.0, 100)
    X, U, cost, iterations, converged = ilqr_reference.solve((-0.4, 0.0), np.zeros(100), ref,
                                                            P, c, 100)
    assert result.status == CONVERGED and converged
    assert result.iterations == iterations
    assert result.cost == pytest.approx(cost, rel=1e-10)
    np.testing.assert_allclose(solver.U, U, atol=1e-9)
    np.testing.assert_allclose(solver.X, X, atol=1e-12)


def test_cold_solve_converges_and_lowers_the_cost():
    settings, c = problem()
    solver = IlqrSolver(settings, P, c)
    first = solver.tick((-0.4, 0.0), 0.0, Setpoint(-1.0).packed(), COLD, 0.0, 0)
    solved = solver.tick((-0.4, 0.0), 0.0, Setpoint(-1.0).packed(), COLD, 0.0, 100)
    assert solved.status == CONVERGED
    assert solved.iterations < 30
    assert solved.cost < first.cost
    assert solver.U[0] < -3.0  # pulls hard down toward -1 rad, within the barrier
    assert np.all(np.abs(solver.U) < MODEL.limits.current_max)


def closed_loop(mpc, steps, q=-0.4, qd=0.0):
    """MPC on the exact model (no bus): returns positions and commands."""
    qs, us = [], []
    for k in range(steps):
        r = mpc.tick(q, qd, k * 1e-3)
        qs.append(q)
        us.append(r.current)
        q, qd, *_ = dynamics.step(q, qd, r.current, P, 1e-3, 20)
    return np.array(qs), np.array(us)


def test_warm_started_ticks_track_a_setpoint():
    mpc = Mpc(MODEL, reference=Setpoint(-1.2))
    qs, us = closed_loop(mpc, 1500)
    assert abs(qs[-1] + 1.2) < 0.02
    assert np.all(np.abs(us) <= MODEL.limits.current_max)
    hold = mpc.hold_current(qs[-1])
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
    result = mpc.tick(position, velocity, 0.0)
    assert result.current == expected
    assert "non-finite state" in result.fault


def test_out_of_range_state_holds_within_limits():
    mpc = Mpc(MODEL)
    result = mpc.tick(-3.5, 0.0, 0.0)
    assert "out of range" in result.fault
    assert abs(result.current) <= MODEL.limits.current_max
    assert result.current == pytest.approx(mpc.hold_current(-3.5))


def test_diverging_solve_falls_back_to_holding():
    settings = OcpSettings().with_weights(position=1e308)  # the cost overflows to inf
    mpc = Mpc(MODEL, settings)
    result = mpc.tick(-1.0, 0.0, 0.0)
    assert not result.solve.ok
    assert result.fault.startswith(f"solver {result.solve.status_name}")
    assert result.current == pytest.approx(mpc.hold_current(-1.0))


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
