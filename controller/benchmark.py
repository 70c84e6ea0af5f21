"""The speed of the MPC: tick and cold solve against a plain numpy iLQR, and the batched tick for
many joints, vectorised and scalar. Library functions for the `bench` command.

Every figure comes from a closed loop on the exact model: the paper's sinusoid (crossing the
-2.35 rad limit) tracked with N = 100 steps of 1 ms unless said otherwise, the cold first solve
excluded from the tick figures.
"""

import os
import time
from collections.abc import Callable

import numba
import numpy as np

from controller import ilqr_reference
from controller.lanes import default_threads
from controller.mpc import BatchMpc, JointProblem, Mpc
from controller.problem import OcpSettings, pack_cost
from controller.reference import Sinusoid, reference_at
from driver import Sample
from driver.host_floor import host_steal_s
from model import dynamics
from model.dynamics import SUBSTEPS
from model.parameters import Payload, load_model

PAPER_TICK_US = 200.0  # paper: 100 steps of 1 ms on an i7-8850H laptop
# consecutive blocks of the tick run whose medians `measure` gives beside the run's: on a
# virtual machine the host's neighbours move a CPU's speed within seconds (three `bench` runs
# in a row here: tick medians 18.9, 12.6 and 18.9 us), and the run's median alone hides
# whether the figure came from a steady host
TICK_BLOCKS = 10
JOINT_COUNTS = (1, 7, 32)  # one joint, one TALOS arm, the whole robot
THREAD_COUNTS = (1, 2)


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


def block_medians(times: np.ndarray, blocks: int = TICK_BLOCKS) -> list[float]:
    """The medians of `blocks` consecutive blocks of `times` (as equal as they split; one a
    value when there are fewer), rounded to 0.01: the host's speed along the run."""
    return [round(float(np.median(block)), 2)
            for block in np.array_split(times, min(blocks, len(times)))]


def _numpy_ticks(settings: OcpSettings, ticks: int) -> np.ndarray:
    """The straightforward version: numpy iLQR, warm start shifted by one, one iteration
    (simulate, backward pass, line search) per tick, on the same closed loop."""
    model = load_model()
    p = model.parameters.packed()
    c = pack_cost(settings, model.limits, p)
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
    """One joint: tick median/p99/max, the medians of TICK_BLOCKS consecutive blocks of the
    ticks (fewer with fewer ticks), cold solve, and the numpy iLQR's tick for scale."""
    compiled = _closed_loop_ticks(Mpc(load_model(), settings), ticks, settings.dt)
    plain = _numpy_ticks(settings, numpy_ticks)
    median = float(np.median(compiled))
    return {
        "horizon": settings.horizon, "dt_ms": settings.dt * 1e3, "ticks": ticks,
        "tick_median_us": round(median, 2),
        "tick_block_medians_us": block_medians(compiled),
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


class _ClosedLoop:
    """A batch of joints, each on its exact model, ticked one cycle at a time from `start`
    (positions; at rest)."""

    def __init__(self, problems: list[JointProblem], start: np.ndarray, kernel: str,
                 threads: int):
        self.batch = BatchMpc(problems, kernel, threads)
        self.parameters = np.stack([joint.packed_parameters for joint in self.batch.joints])
        self.limits = np.array([joint.limits.current_max for joint in self.batch.joints])
        self.states = np.stack([start, np.zeros(len(problems))], axis=1)
        self.dt = problems[0].settings.dt
        self.cycle = 0
        self.decisions = self.batch.tick(0.0, self.states[:, 0], self.states[:, 1])

    def ticks(self, count: int) -> np.ndarray:
        """The next `count` ticks' durations (us)."""
        times = np.empty(count)
        for k in range(count):
            currents = np.clip([d.planned_current for d in self.decisions], -self.limits,
                               self.limits)
            _step_plants(self.states, currents, self.parameters, self.dt)
            self.cycle += 1
            start = time.perf_counter()
            self.decisions = self.batch.tick(self.cycle * self.dt, self.states[:, 0],
                                             self.states[:, 1])
            times[k] = time.perf_counter() - start
        failed = sum(not d.ok for d in self.decisions)
        if failed:
            raise RuntimeError(f"{failed} of {len(self.decisions)} joints' solves failed in the "
                               "batch bench")
        return times * 1e6


def reference_starts(problems: list[JointProblem]) -> np.ndarray:
    """Each joint at its reference's value at t = 0 (a sinusoid's centre plus amplitude)."""
    return np.array([p.reference.packed()[1] + p.reference.packed()[2] for p in problems])


def measure_joints(joints: int, ticks: int, threads: int,
                   settings: OcpSettings = OcpSettings(),
                   problems: tuple[list[JointProblem], np.ndarray] | None = None) -> dict:
    """`measure_threads` on one thread count: that count's figures."""
    return measure_threads(joints, ticks, (threads,), settings, problems)[f"threads_{threads}"]


def measure_threads(joints: int, ticks: int, thread_counts: tuple[int, ...] = THREAD_COUNTS,
                    settings: OcpSettings = OcpSettings(),
                    problems: tuple[list[JointProblem], np.ndarray] | None = None) -> dict:
    """The batched MPC of `joints` joints in one compiled call per cycle, each joint on its exact
    model in closed loop, with the vectorised kernel (joints in SIMD lanes) and the scalar one
    (joint after joint), on each of `thread_counts` threads (those that share the vectorised
    kernel's chunks, and numba's thread count for both): tick median and p99 (us) under
    `threads_<count>`, the cold first solve excluded. All of them run in alternating blocks of
    ticks, so a change in the host's load hits each alike: on a shared host the ratios (two
    threads against one, vectorised against scalar) are the figures to trust. The problems
    are `joint_problems` from their references' start unless `problems` gives them with their
    start positions (a robot's: `robot.bench.robot_problems`)."""
    if problems is None:
        chosen = joint_problems(joints, settings)
        problems = chosen, reference_starts(chosen)
    previous = numba.get_num_threads()
    loops: dict[tuple[int, str], _ClosedLoop] = {}
    times: dict[tuple[int, str], list[np.ndarray]] = {}
    try:
        for threads in thread_counts:
            numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
            for kernel in ("lanes", "scalar"):
                loops[threads, kernel] = _ClosedLoop(*problems, kernel, threads)
                times[threads, kernel] = []
        block = max(1, min(50, ticks // 100))  # 100 turns each: bursts of load average out
        done = 0
        while done < ticks:
            count = min(block, ticks - done)
            for (threads, kernel), loop in loops.items():
                numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
                times[threads, kernel].append(loop.ticks(count))
            done += count
    finally:
        numba.set_num_threads(previous)
    results: dict = {}
    for threads in thread_counts:
        result: dict = {"ticks": ticks, "threads": threads,
                        "lane_threads": loops[threads, "lanes"].batch.lane_threads()}
        for kernel, name in (("lanes", "vectorised"), ("scalar", "scalar")):
            measured = np.concatenate(times[threads, kernel])
            result[f"{name}_median_us"] = round(float(np.median(measured)), 2)
            result[f"{name}_p99_us"] = round(float(np.percentile(measured, 99)), 2)
        result["vectorised_over_scalar"] = round(result["vectorised_median_us"]
                                                 / result["scalar_median_us"], 3)
        if threads != thread_counts[0]:
            first = results[f"threads_{thread_counts[0]}"]["vectorised_median_us"]
            result[f"vectorised_over_{thread_counts[0]}_thread"] = round(
                result["vectorised_median_us"] / first, 3)
        results[f"threads_{threads}"] = result
    return results


def run(ticks: int = 20_000, numpy_ticks: int = 300, joint_ticks: int = 5_000,
        progress: Callable[[str], None] = lambda stage: None,
        robot: tuple[str, tuple[list[JointProblem], np.ndarray]] | None = None) -> dict:
    """Everything `bench --json` prints: the paper's N = 100 at 1 ms, the paper's robot setting
    (N = 5 at 3.3 ms) under `paper_robot`, and the batched MPC under `joints`: for each joint
    count, and for a robot's own problem when `robot` gives it (its name, its problems and
    start positions), one and two threads, the vectorised and the scalar kernel side by side.
    The host's load average, core count, numba's threading layer and the time the hypervisor
    took the CPUs during the run (/proc/stat's steal, summed over CPUs; None where the host
    has no such count) come with the figures (they move them).
    `progress` is told each stage as it starts (the whole run takes a quarter of a minute or
    more)."""
    stages = 2 + len(JOINT_COUNTS) + (robot is not None)
    steal_before = host_steal_s()
    progress(f"[1/{stages}] MPC N = 100 at 1 ms: {ticks} ticks, {numpy_ticks} of numpy iLQR")
    result = measure(OcpSettings(), ticks, numpy_ticks)
    result["paper_tick_us"] = PAPER_TICK_US
    result["speedup_over_paper"] = round(PAPER_TICK_US / result["tick_median_us"], 1)
    progress(f"[2/{stages}] MPC N = 5 at 3.3 ms (the paper's robot setting)")
    result["paper_robot"] = measure(OcpSettings(horizon=5, dt=3.3e-3), ticks, numpy_ticks)
    result["joints"] = {}
    for stage, joints in enumerate(JOINT_COUNTS, start=3):
        progress(f"[{stage}/{stages}] batched MPC of {joints} joints: {joint_ticks} ticks on "
                 f"{', '.join(map(str, THREAD_COUNTS))} threads")
        result["joints"][str(joints)] = measure_threads(joints, joint_ticks)
    if robot is not None:
        name, problems = robot
        progress(f"[{stages}/{stages}] batched MPC of {name}'s problem: {joint_ticks} ticks on "
                 f"{', '.join(map(str, THREAD_COUNTS))} threads")
        result["joints"][name] = measure_threads(len(problems[0]), joint_ticks,
                                                 problems=problems)
    result["default_threads"] = default_threads()
    # which of numba's layers ran the threads (OpenMP, TBB or its own workqueue): their wake-up
    # and join costs differ by tens of us a tick (controller.lanes' docstring)
    result["threading_layer"] = numba.threading_layer()
    result["cores"] = os.cpu_count()
    result["load_average"] = [round(load, 2) for load in os.getloadavg()]
    steal_after = host_steal_s()
    result["host_steal_s"] = (round(sum(steal_after.values()) - sum(steal_before.values()), 2)
                              if steal_before else None)
    return result
