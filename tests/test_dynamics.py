import math

import numpy as np
import pytest

from model import dynamics
from model.dynamics import SUBSTEPS
from model.parameters import GRAVITY, load_model
from protocol.objects import INCREMENTS_PER_RAD

P = load_model().parameters.packed()
DT = 1e-3


def energy(q, qd, p):
    """Kinetic plus gravitational energy; d/dt of the potential is the model's gravity torque."""
    potential = -p[dynamics.P_GRAVITY_MY] * math.cos(q) + p[dynamics.P_GRAVITY_MX] * math.sin(q)
    return 0.5 * p[dynamics.P_INERTIA] * qd**2 + potential


def test_stiction_holds_exactly_without_chatter():
    # net static torque below the dry friction: the joint must not move at all
    q0 = -1.0
    hold = (dynamics.gravity_torque(q0, P) + P[dynamics.P_OFFSET]) / P[dynamics.P_DRIVE_GAIN]
    current = hold + 0.5 * P[dynamics.P_DRY] / P[dynamics.P_DRIVE_GAIN]
    states = dynamics.simulate(q0, 0.0, np.full(2000, current), P, DT, 10)
    assert np.all(states[:, 1] == 0.0)
    assert np.all(states[:, 0] == q0)


def test_free_swing_never_gains_energy_and_comes_to_rest():
    p = P.copy()
    p[dynamics.P_OFFSET] = 0.0  # no external work: energy must only go down
    q, qd = -1.5, 0.0
    e = energy(q, qd, p)
    for _ in range(10000):
        q, qd, *_ = dynamics.step(q, qd, 0.0, p, DT, 10)
        e_next = energy(q, qd, p)
        assert e_next <= e + 1e-9
        e = e_next
    assert qd == 0.0
    assert abs(dynamics.gravity_torque(q, p)) <= p[dynamics.P_DRY] + 1e-9


def test_twenty_substeps_agree_with_a_thousand_within_one_encoder_count():
    currents = -1.5 + 0.8 * np.sin(np.arange(3000) * DT * 2 * math.pi)
    coarse = dynamics.simulate(-0.1, 0.0, currents, P, DT, SUBSTEPS)
    fine = dynamics.simulate(-0.1, 0.0, currents, P, DT, 1000)
    assert np.max(np.abs(coarse[:, 0] - fine[:, 0])) < 1.0 / INCREMENTS_PER_RAD


WITH_EFFECTS = load_model().parameters.with_effect(
    "stribeck", {"breakaway_friction": 1.0, "velocity": 0.05}).with_effect(
    "position_ripple", {"amplitude": 0.5, "spatial_frequency": 3.0, "phase": 0.4}).with_effect(
    "load_dependent_friction", {"coefficient": 0.05}).with_effect(
    "friction_ripple", {"amplitude": 0.3, "spatial_frequency": 5.0, "phase": 1.1}).packed()


@pytest.mark.parametrize("p", [P, WITH_EFFECTS], ids=["paper", "all library effects"])
def test_smooth_model_derivatives_match_finite_differences(p):
    beta, eps = 1000.0, 1e-7
    for q, qd, i in [(-1.0, 0.3, 1.2), (-2.0, -0.001, -3.0), (-0.3, 0.0, 0.5)]:
        a, da_dq, da_dqd, da_di = dynamics.smooth_acceleration(q, qd, i, p, beta)
        fd = [(dynamics.smooth_acceleration(q + eps * e[0], qd + eps * e[1], i + eps * e[2], p,
                                            beta)[0] - a) / eps for e in np.eye(3)]
        assert [da_dq, da_dqd, da_di] == pytest.approx(fd, rel=1e-4, abs=1e-3)


def test_stribeck_breakaway_holds_what_coulomb_friction_alone_would_not():
    q0 = -1.0
    hold = (dynamics.gravity_torque(q0, P) + P[dynamics.P_OFFSET]) / P[dynamics.P_DRIVE_GAIN]
    push = hold + 1.5 * P[dynamics.P_DRY] / P[dynamics.P_DRIVE_GAIN]  # 1.5 x Coulomb
    plain = dynamics.simulate(q0, 0.0, np.full(200, push), P, DT, SUBSTEPS)
    only_stribeck = load_model().parameters.with_effect(
        "stribeck", {"breakaway_friction": 1.0, "velocity": 0.05}).packed()
    stribeck = dynamics.simulate(q0, 0.0, np.full(200, push), only_stribeck, DT, SUBSTEPS)
    assert plain[-1, 0] != q0  # Coulomb alone lets go
    assert stribeck[-1, 0] == q0  # the breakaway level (2.5 N.m) holds


def test_rest_position_balances_gravity():
    q = dynamics.rest_position(P)
    assert dynamics.gravity_torque(q, P) == pytest.approx(0.0, abs=1e-12)
    assert -0.2 < q < 0.0
    assert P[dynamics.P_GRAVITY_MY] == pytest.approx(GRAVITY * 1.1)
