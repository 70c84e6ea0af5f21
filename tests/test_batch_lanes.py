"""The vectorised batch (joints in SIMD lanes, controller.lanes) against the scalar kernel and the
numpy reference: the same decisions to 1e-9 relative, joints in different modes in one tick,
joints whose line search rejects steps; and the error bounds of its own exp, tanh, sin, cos."""

from dataclasses import replace

import numba
import numpy as np
import pytest

from controller import ilqr_reference, lane_math, lanes
from controller import workspace as ws
from controller.benchmark import (
    TICK_BLOCKS,
    block_medians,
    measure,
    measure_joints,
    measure_threads,
)
from controller.ilqr import WARM_TRIALS
from controller.mpc import BatchMpc, JointProblem, Mpc, _lane_plan
from controller.problem import OcpSettings, pack_cost
from controller.reference import Setpoint, Sinusoid, reference_at
from model import dynamics
from model.parameters import Payload, load_model

MODEL = load_model()
DT = 1e-3
RELATIVE = 1e-9


@numba.njit(error_model="numpy")
def _lane_functions(x, out):
    """exp, tanh, sin and cos of lane_math over an array, in a loop the compiler vectorises
    (as in the kernel)."""
    for j in range(x.shape[0]):
        out[0, j] = lane_math.exp(x[j])
        out[1, j] = lane_math.tanh(x[j])
        out[2, j], out[3, j] = lane_math.sin_cos(x[j])


def ulps(computed: np.ndarray, exact: np.ndarray) -> float:
    """The largest error in units in the last place of the exact value."""
    return float(np.max(np.abs(computed - exact) / np.spacing(np.abs(exact))))


def lane_functions(x: np.ndarray) -> np.ndarray:
    out = np.empty((4, len(x)))
    _lane_functions(x, out)
    return out


def test_exp_is_within_two_ulp_over_the_double_range():
    rng = np.random.default_rng(1)
    x = np.concatenate([rng.uniform(-745.0, 709.7, 300_000), rng.uniform(-1.0, 1.0, 300_000),
                        rng.normal(0.0, 1e-6, 10_000), [0.0, -0.0, 709.78, -745.13]])
    assert ulps(lane_functions(x)[0], np.exp(x)) <= 2.0
    special = lane_functions(np.array([np.inf, -np.inf, np.nan, 710.0, -746.0, 1e308]))[0]
    assert special[0] == np.inf and special[1] == 0.0 and np.isnan(special[2])
    assert special[3] == np.inf and special[4] == 0.0 and special[5] == np.inf


def test_tanh_is_within_three_ulp_even_near_zero():
    rng = np.random.default_rng(2)
    x = np.concatenate([rng.uniform(-25.0, 25.0, 300_000), rng.uniform(-0.4, 0.4, 300_000),
                        rng.normal(0.0, 1e-9, 10_000), [1e-300, -1e-300]])
    assert ulps(lane_functions(x)[1], np.tanh(x)) <= 3.0
    special = lane_functions(np.array([np.inf, -np.inf, np.nan, 0.0]))[1]
    assert list(special[[0, 1, 3]]) == [1.0, -1.0, 0.0] and np.isnan(special[2])


def test_sin_and_cos_are_within_two_ulp_where_joints_are():
    rng = np.random.default_rng(3)
    x = np.concatenate([rng.uniform(-10.0, 10.0, 300_000), rng.uniform(-1e5, 1e5, 300_000)])
    out = lane_functions(x)
    assert ulps(out[2], np.sin(x)) <= 2.0 and ulps(out[3], np.cos(x)) <= 2.0
    quadrants = np.arange(-8, 9) * np.pi / 4  # the reduction's edges; zeros have no ulp scale
    out = lane_functions(quadrants)
    assert np.max(np.abs(out[2] - np.sin(quadrants))) <= 2.3e-16
    assert np.max(np.abs(out[3] - np.cos(quadrants))) <= 2.3e-16
    assert np.all(np.isnan(lane_functions(np.array([np.inf, -np.inf, np.nan]))[2:]))


def problems(count: int) -> list[JointProblem]:
    """Joints that differ in payload, weights and reference."""
    references = [Sinusoid(), Setpoint(-1.0), Sinusoid(center=-1.2, amplitude=0.5, frequency=0.5),
                  Setpoint(-2.0), Sinusoid(frequency=0.3)]
    return [JointProblem(MODEL, OcpSettings().with_weights(position=200.0 + 50.0 * (j % 3)),
                         Payload(float(j % 4), 0.01 * (j % 3), 0.05),
                         references[j % len(references)]) for j in range(count)]


def assert_same_decisions(lanes_decisions, scalar_decisions):
    """Equal status, iterations and rollouts; currents, references and costs to RELATIVE."""
    for vectorised, scalar in zip(lanes_decisions, scalar_decisions, strict=True):
        assert (vectorised.status, vectorised.iterations, vectorised.rollouts, vectorised.ok) == (
            scalar.status, scalar.iterations, scalar.rollouts, scalar.ok)
        for field in ("planned_current", "reference_position", "reference_velocity", "cost"):
            a, b = getattr(vectorised, field), getattr(scalar, field)
            assert a == pytest.approx(b, rel=RELATIVE, abs=1e-12), field


class Twins:
    """The same joints in a lanes batch and a scalar batch, each on its own exact models."""

    def __init__(self, count: int, threads: int = 1):
        self.lanes = BatchMpc(problems(count), kernel="lanes", threads=threads)
        self.scalar = BatchMpc(problems(count), kernel="scalar")
        self.parameters = [joint.packed_parameters for joint in self.lanes.joints]
        self.states = np.array([[-0.4 - 0.2 * (j % 5), 0.0] for j in range(count)])
        self.rollouts: list[list[int]] = []
        self.modes: list[list[int]] = []

    def tick(self, k: int, skip=(), disturb=()) -> list:
        """Tick both at cycle k (skipping and kicking the given joints), check they agree,
        then step the plants with the scalar decisions."""
        for batch in (self.lanes, self.scalar):
            for j in range(len(batch)):
                batch.prepare(batch.joints[j], *self.states[j])
            for j in skip:
                batch.skip(batch.joints[j])
        self.modes.append([joint.mode for joint in self.scalar.joints])
        self.lanes.run(k * DT)
        self.scalar.run(k * DT)
        decisions = [[batch.decision(joint) for joint in batch.joints]
                     for batch in (self.lanes, self.scalar)]
        ticked = [j for j in range(len(self.states)) if j not in skip]
        assert_same_decisions(*([d[j] for j in ticked] for d in decisions))
        self.rollouts.append([decisions[1][j].rollouts for j in ticked])
        for j in ticked:
            current = float(np.clip(decisions[1][j].planned_current, -6.0, 6.0))
            self.states[j] = dynamics.step(*self.states[j], current, self.parameters[j], DT,
                                           20)[:2]
            if j in disturb:
                self.states[j, 1] += 3.0  # a kick the warm start did not predict
        return decisions


def test_lane_decisions_equal_the_scalar_kernel_with_joints_in_every_mode():
    """Ten joints (two chunks of lanes, six empty lanes): cold, warm, resample (new reference
    or weights), a missed cycle, skipped joints, kicked joints whose line search backtracks."""
    twins = Twins(10)
    for k in range(120):
        skip = (3,) if 40 <= k < 43 else ((7, 8) if k == 60 else ())
        disturb = (2, 9) if k in (30, 80) else ()
        if k == 42:  # with joint 3 skipped: three modes in one tick
            for batch in (twins.lanes, twins.scalar):
                batch.joints[5].set_reference(Setpoint(-1.5))  # resample in the next tick
                batch.set_settings(batch.joints[6], batch.joints[6].settings.with_weights(
                    position=900.0))
        cycle = k + 1 if k >= 70 else k  # from cycle 70 on, one cycle was missed
        twins.tick(cycle, skip, disturb)
    modes = {mode for tick_modes in twins.modes for mode in tick_modes}
    assert {ws.COLD, ws.WARM, ws.RESAMPLE, ws.SKIP} <= modes
    mixed = [tick_modes for tick_modes in twins.modes if len(set(tick_modes)) >= 3]
    assert mixed, "no tick had joints in three modes at once"
    backtracked = [r for r in twins.rollouts if max(r) > 1 and min(r) == 1]
    assert backtracked, "no tick had one joint's line search reject a step while others took it"


def test_a_warm_step_that_diverges_falls_back_alike():
    """An impossible kick: the warm step's trials cost far more than its merit, the joint solves
    again from its controls; its neighbours in the lanes carry on."""
    twins = Twins(3)
    for k in range(20):
        twins.tick(k)
    twins.states[1] = [-0.4, 40.0]  # far beyond the velocity limit
    decisions = twins.tick(20)
    # the warm step's trials, then a simulation of the controls and a new line search
    assert decisions[1][1].rollouts > WARM_TRIALS + 1
    assert decisions[1][0].rollouts == 1 and decisions[1][2].rollouts == 1
    for k in range(21, 40):
        twins.tick(k)


@pytest.mark.parametrize("kick,solves_anew", [(0.5, False), (1.0, True)])
def test_a_warm_tick_simulates_at_most_its_trials_unless_its_step_diverged(kick, solves_anew):
    """A small kick (0.5 rad/s): no trial passes the Armijo test, and the smallest one, close to
    its merit, is taken after WARM_TRIALS simulations, in both kernels alike (measured: the
    unbounded search took a fourth trial here). A larger one (1 rad/s) diverges and solves
    anew. No joint's warm tick simulates more than WARM_TRIALS times otherwise."""
    twins = Twins(3)
    for k in range(20):
        twins.tick(k)
    twins.states[1, 1] += kick
    kicked = twins.tick(20)[1][1]
    assert kicked.ok and kicked.status == "max_iterations"
    assert (kicked.rollouts > WARM_TRIALS + 1) is solves_anew, kicked.rollouts
    if not solves_anew:
        assert kicked.rollouts == WARM_TRIALS
    for k in range(21, 60):
        twins.tick(k)
    assert max(max(rollouts) for rollouts in twins.rollouts[21:]) <= WARM_TRIALS


def test_two_threads_decide_as_one():
    """Two threads share the chunks of lanes, each taking the next untaken one; which thread
    ticks a chunk changes from tick to tick, the decisions do not."""
    one, two = BatchMpc(problems(20), kernel="lanes", threads=1), BatchMpc(
        problems(20), kernel="lanes", threads=2)
    assert two.lane_threads() == 2 and one.lane_threads() == 1
    claims = two._lanes[-1]
    positions, velocities = np.linspace(-0.4, -1.8, 20), np.zeros(20)
    for k in range(30):
        first, second = (batch.tick(k * DT, positions, velocities) for batch in (one, two))
        assert first == second
        # every chunk ticked once, each taken by one thread and looked at by both
        assert claims[lanes.TICKED] == 3
        assert (two._lanes[-2][:, lanes.TAKEN] == 2).all()
        positions = positions - 1e-3 * np.array([d.planned_current for d in first])


@pytest.mark.parametrize("reference", [Sinusoid(), Setpoint(-1.0)])
def test_lane_cold_solve_matches_the_numpy_reference(reference):
    settings = OcpSettings()
    c = pack_cost(settings, MODEL.limits, MODEL.parameters.packed())
    t = np.arange(settings.horizon + 1) * settings.dt
    ref = np.stack(reference_at(reference.packed(), t), axis=1)
    mpc = Mpc(MODEL, settings, reference=reference, kernel="lanes")
    result = mpc.solve(-0.4, 0.0, 0.0, initial_current=0.0, max_iterations=100)
    plan = mpc.plan(0.0)
    X, U, cost, iterations, converged = ilqr_reference.solve(
        (-0.4, 0.0), np.zeros(100), ref, MODEL.parameters.packed(), c, 100)
    assert result.status == "converged" and converged
    assert result.iterations == iterations
    assert result.cost == pytest.approx(cost, rel=RELATIVE)
    np.testing.assert_allclose(plan.current, U, rtol=RELATIVE, atol=1e-9)
    np.testing.assert_allclose(np.stack((plan.position, plan.velocity), axis=1), X, atol=1e-12)


def test_the_plan_of_a_lane_joint_is_its_solution_in_order():
    """After many ticks (the ring has wrapped) the plan equals the scalar kernel's plan."""
    twins = Twins(9)
    for k in range(250):
        twins.tick(k)
    for j in (0, 8):
        vectorised, scalar = (batch.plan(batch.joints[j], 0.0) for batch in (twins.lanes,
                                                                              twins.scalar))
        for field in ("position", "velocity", "current", "reference_position"):
            np.testing.assert_allclose(getattr(vectorised, field), getattr(scalar, field),
                                       rtol=1e-7, atol=1e-9)


def test_the_compiled_plan_gather_is_numpys():
    """`_lane_plan` (the plan's one compiled gather) equals numpy's fancy indexing of the
    lanes' buffers, for every lane and ring position (the numpy expression is the reference)."""
    twins = Twins(9)
    for k in range(30):
        twins.tick(k)
    batch = twins.lanes
    trajectories, gains, *_ = batch._lanes
    width = lanes.width(len(batch))
    for j in (0, 8):
        chunk, lane = divmod(j, width)
        for which in (0, 1):
            for order in batch._ring_orders[[0, 7, batch.horizon]]:
                out = np.empty((4, len(order)))
                _lane_plan(trajectories, gains, which, chunk, lane, order, out)
                solution = trajectories[which, chunk, :, :, lane][order]
                np.testing.assert_array_equal(out[0], solution[:, lanes.Q])
                np.testing.assert_array_equal(out[1], solution[:, lanes.QD])
                np.testing.assert_array_equal(out[2], solution[:, lanes.U])
                np.testing.assert_array_equal(out[3],
                                              gains[chunk, :, lanes.REFERENCE_Q, lane][order])


def test_a_skipped_lane_joint_keeps_its_row():
    """Only its mode is written (cold next); its stored solution is not its plan any more."""
    batch = BatchMpc(problems(2), kernel="lanes")
    first, second = batch.joints
    batch.tick(0.0, [-0.4, -0.4], [0.0, 0.0])
    kept_row = second.row.copy()
    batch.prepare(first, -0.4, 0.0)
    batch.skip(second)
    batch.run(DT)
    untouched = np.arange(len(kept_row)) != ws.MODE
    assert np.array_equal(second.row[untouched], kept_row[untouched])
    assert second.mode == ws.COLD
    assert batch.decision(first).ok


EFFECT_TABLES = {
    "stribeck": {"breakaway_friction": 0.3, "velocity": 0.05},
    "position_ripple": {"amplitude": 0.2, "spatial_frequency": 6.5, "phase": 0.3},
    "load_dependent_friction": {"coefficient": 0.08},
    "friction_ripple": {"amplitude": 0.1, "spatial_frequency": 9.0, "phase": 0.0},
    "torque_constant_saturation": {"coefficient": 0.06, "knee_current": 1.5},
    "smooth_reversal": {"velocity": 0.02},
    "warm_up_friction": {"excess_friction": 0.2, "time_constant": 30.0},
}


def with_effects(names) -> JointProblem:
    parameters = MODEL.parameters
    for name in names:
        parameters = parameters.with_effect(name, EFFECT_TABLES[name])
    return JointProblem(replace(MODEL, parameters=parameters))


def test_joints_with_extra_effects_run_in_lanes_and_decide_as_the_scalar_kernel():
    """Every effect of the registry, one joint each, one joint with all of them and two
    without, in one lanes batch: each decides what the scalar kernel decides (1e-9
    relative) over a closed loop from cold; the joints without an effect decide bit for bit
    what they decide in a batch where no joint has one."""
    names = list(EFFECT_TABLES)
    chosen = [with_effects([name]) for name in names] + [with_effects(names)]
    chosen += [JointProblem(MODEL), JointProblem(MODEL, reference=Setpoint(-1.0))]
    lanes, scalar = (BatchMpc(chosen, kernel=kernel) for kernel in ("lanes", "scalar"))
    plain = BatchMpc(chosen[-2:], kernel="lanes")
    assert lanes.kernel == "lanes" and BatchMpc(chosen[:1]).kernel == "lanes"
    parameters = [joint.packed_parameters for joint in lanes.joints]
    states = np.array([[-0.4 - 0.1 * (j % 5), 0.0] for j in range(len(chosen))])
    for k in range(60):
        decisions = [batch.tick(k * DT, states[:, 0], states[:, 1]) for batch in (lanes, scalar)]
        assert_same_decisions(*decisions)
        assert all(d.ok for d in decisions[1])
        assert plain.tick(k * DT, states[-2:, 0], states[-2:, 1]) == decisions[0][-2:]
        for j, decision in enumerate(decisions[1]):
            current = float(np.clip(decision.planned_current, -6.0, 6.0))
            states[j] = dynamics.step(*states[j], current, parameters[j], DT, 20)[:2]
    # the effects count: from one state, the joint with all of them plans another current
    both = BatchMpc([chosen[len(names)], chosen[-2]], kernel="lanes")
    loaded, bare = both.tick(0.0, [-0.5, -0.5], [0.0, 0.0])
    assert abs(loaded.planned_current - bare.planned_current) > 1e-3


def test_the_bench_reports_both_kernels_on_one_and_two_threads():
    """`bench --json`'s batched figures: the vectorised and the scalar kernel on one and two
    threads in the same run, how many threads took the lanes' chunks (one per chunk at most),
    and two threads' tick against one thread's."""
    both, few = measure_threads(9, 4), measure_joints(7, 4, 2)
    assert set(both) == {"threads_1", "threads_2"}
    one, two = both["threads_1"], both["threads_2"]
    assert (one["lane_threads"], two["lane_threads"], few["lane_threads"]) == (1, 2, 1)
    assert two["vectorised_over_1_thread"] == round(
        two["vectorised_median_us"] / one["vectorised_median_us"], 3)
    for result in (one, two, few):
        assert result["ticks"] == 4
        assert 0 < result["vectorised_median_us"] <= result["vectorised_p99_us"]
        assert 0 < result["scalar_median_us"] <= result["scalar_p99_us"]


def test_the_benchmark_gives_the_tick_along_the_run_so_a_host_that_moved_shows():
    # a host whose CPU slowed half-way through: the run's median alone would hide it
    steady_then_slow = np.concatenate((np.full(1000, 12.6), np.full(1000, 18.9)))
    assert block_medians(steady_then_slow) == [12.6] * 5 + [18.9] * 5
    assert block_medians(np.array([3.0, 1.0, 2.0])) == [3.0, 1.0, 2.0]  # fewer than blocks
    figures = measure(OcpSettings(horizon=20), 40, 2)
    assert len(figures["tick_block_medians_us"]) == TICK_BLOCKS
    assert all(0 < tick <= figures["tick_max_us"] for tick in figures["tick_block_medians_us"])
