"""The speed of the MPC: tick and cold solve against a plain numpy iLQR, and the batched tick for
many joints. Library functions for the `bench` command.

Every figure comes from a closed loop on the exact model: the paper's sinusoid (crossing the
-2.35 rad limit) tracked with N = 100 steps of 1 ms unless said otherwise, the cold first solve
excluded from the tick figures.
"""

import time
from collections.abc import Callable

import numba
import numpy as np

from controller import ilqr_reference
from controller.mpc import BatchMpc, JointProblem, Mpc
from controller.problem import OcpSettings, pack_cost
from controller.reference import Sinusoid, reference_at
from driver import Sample
from model import dynamics
from model.dynamics import SUBSTEPS
from model.parameters import Payload, load_model

PAPER_TICK_US = 200.0  # paper: 100 steps of 1 ms on an i7-8850H laptop
JOINT_COUNTS = (7, 32)  # one TALOS arm, the whole robot


def _closed_loop_ticks(mpc: Mpc, ticks: int, dt: float) -> np.ndarray:
    """Tick times (us) of the warm-started MPC driving the exact model."""
    p = mpc.parameters.packed()
    packed = mpc.reference.packed()
    q, qd = packed[1] + packed[2], 0.0
    decision = mpc.tick(Sample(0.0, q, qd, 0.0, 0.0, 0))
    limit = mpc.limits.current_max
    times = np.empty(ticks)
    for k in range(ticks):
        current = min(max(decision.planned_current, -limit), limit)
        q, qd, *_ = dynamics.step(q, qd, current, p, dt, SUBSTEPS)
        sample = Sample((k + 1) * dt, q, qd, 0.0, 0.0, 0)
        start = time.perf_counter()
        decision = mpc.tick(sample)
        times[k] = time.perf_counter() - start
    return times * 1e6


def _numpy_ticks(settings: OcpSettings, ticks: int) -> np.ndarray:
    """The straightforward version: numpy iLQR, warm start shifted by one, one iteration
    (simulate, backward pass, line search) per tick, on the same closed loop."""
    model = load_model()
    p = model.parameters.packed()
    c = pack_cost(settings, model.limits, model.parameters.drive_gain)
    packed = Sinusoid().packed()
    n, dt = settings.horizon, settings.dt
    q, qd = packed[1] + packed[2], 0.0
    offsets = np.arange(n + 1) * dt
    U = np.full(n, 0.0)
    _, U, _, _, _ = ilqr_reference.solve((q, qd), U, np.stack(reference_at(packed, offsets), 1),
                                         p, c, settings.max_iterations)
    limit = model.limits.current_max
    times = np.empty(ticks)
    for k in range(ticks):
        q, qd, *_ = dynamics.step(q, qd, float(np.clip(U[0], -limit, limit)), p, dt, SUBSTEPS)
        start = time.perf_counter()
        U = np.concatenate((U[1:], U[-1:]))
        ref = np.stack(reference_at(packed, (k + 1) * dt + offsets), 1)
        _, U, _, _, _ = ilqr_reference.solve((q, qd), U, ref, p, c, 1)
        times[k] = time.perf_counter() - start
    return times * 1e6


def _cold_solve_ms(settings: OcpSettings, repeats: int) -> float:
    model = load_model()
    times = []
    for _ in range(repeats):
        mpc = Mpc(model, settings)
        packed = mpc.reference.packed()
        start = time.perf_counter()
        decision = mpc.tick(Sample(0.0, packed[1] + packed[2], 0.0, 0.0, 0.0, 0))
        times.append(time.perf_counter() - start)
        if decision.status != "converged":
            raise RuntimeError(f"cold solve did not converge: {decision}")
    return float(np.median(times) * 1e3)


def measure(settings: OcpSettings, ticks: int, numpy_ticks: int) -> dict:
    """One joint: tick median/p99/max, cold solve, and the numpy iLQR's tick for scale."""
    compiled = _closed_loop_ticks(Mpc(load_model(), settings), ticks, settings.dt)
    plain = _numpy_ticks(settings, numpy_ticks)
    median = float(np.median(compiled))
    return {
        "horizon": settings.horizon, "dt_ms": settings.dt * 1e3, "ticks": ticks,
        "tick_median_us": round(median, 2),
        "tick_p99_us": round(float(np.percentile(compiled, 99)), 2),
        "tick_max_us": round(float(np.max(compiled)), 2),
        "cold_solve_ms": round(_cold_solve_ms(settings, 20), 3),
        "numpy_tick_median_us": round(float(np.median(plain)), 1),
        "numpy_over_compiled": round(float(np.median(plain)) / median, 1),
    }


@numba.njit(cache=True)
def _step_plants(states, currents, parameters, dt):
    """Advance every joint's exact model one period under its current (in place)."""
    for j in range(states.shape[0]):
        q, qd, _, _, _ = dynamics.step(states[j, 0], states[j, 1], currents[j], parameters[j],
                                       dt, SUBSTEPS)
        states[j, 0] = q
        states[j, 1] = qd


def joint_problems(joints: int, settings: OcpSettings = OcpSettings()) -> list[JointProblem]:
    """`joints` independent elbow-like problems, each with its own payload and reference (the
    values only make the joints differ: assumed, not a robot's)."""
    model = load_model()
    return [JointProblem(model, settings, Payload(float(j % 4), 0.0, 0.05),
                         Sinusoid(frequency=0.2 * (1.0 + 0.02 * (j % 8)))) for j in range(joints)]


def measure_joints(joints: int, ticks: int, settings: OcpSettings = OcpSettings()) -> dict:
    """The batched MPC of `joints` joints in one compiled call per cycle, each on its exact
    model in closed loop: tick median and p99 (us), the cold first solve excluded."""
    batch = BatchMpc(joint_problems(joints, settings))
    parameters = np.stack([joint.packed_parameters for joint in batch.joints])
    limits = np.array([joint.limits.current_max for joint in batch.joints])
    states = np.array([[p.reference.packed()[1] + p.reference.packed()[2], 0.0]
                       for p in (joint.problem for joint in batch.joints)])
    decisions = batch.tick(0.0, states[:, 0], states[:, 1])
    dt = settings.dt
    times = np.empty(ticks)
    for k in range(ticks):
        currents = np.clip([d.planned_current for d in decisions], -limits, limits)
        _step_plants(states, currents, parameters, dt)
        start = time.perf_counter()
        decisions = batch.tick((k + 1) * dt, states[:, 0], states[:, 1])
        times[k] = time.perf_counter() - start
    failed = sum(not d.ok for d in decisions)
    if failed:
        raise RuntimeError(f"{failed} of {joints} joints' solves failed in the batch bench")
    times *= 1e6
    return {"ticks": ticks, "tick_median_us": round(float(np.median(times)), 2),
            "tick_p99_us": round(float(np.percentile(times, 99)), 2),
            "threads": numba.get_num_threads()}


def run(ticks: int = 20_000, numpy_ticks: int = 300, joint_ticks: int = 5_000,
        progress: Callable[[str], None] = lambda stage: None) -> dict:
    """Everything `bench --json` prints: the paper's N = 100 at 1 ms, the paper's robot setting
    (N = 5 at 3.3 ms) under `paper_robot`, and the batched MPC under `joints`. `progress` is
    told each stage as it starts (the whole run takes a quarter of a minute or more)."""
    stages = 2 + len(JOINT_COUNTS)
    progress(f"[1/{stages}] MPC N = 100 at 1 ms: {ticks} ticks, {numpy_ticks} of numpy iLQR")
    result = measure(OcpSettings(), ticks, numpy_ticks)
    result["paper_tick_us"] = PAPER_TICK_US
    result["speedup_over_paper"] = round(PAPER_TICK_US / result["tick_median_us"], 1)
    progress(f"[2/{stages}] MPC N = 5 at 3.3 ms (the paper's robot setting)")
    result["paper_robot"] = measure(OcpSettings(horizon=5, dt=3.3e-3), ticks, numpy_ticks)
    result["joints"] = {}
    for stage, joints in enumerate(JOINT_COUNTS, start=3):
        progress(f"[{stage}/{stages}] batched MPC of {joints} joints: {joint_ticks} ticks")
        result["joints"][str(joints)] = measure_joints(joints, joint_ticks)
    return result
