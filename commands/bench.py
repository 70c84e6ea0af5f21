"""`bench`: the speed of the MPC tick and the cold solve, against a plain numpy iLQR.

Every figure comes from the same problem in the same run: the paper's sinusoid (crossing the
-2.35 rad limit) tracked in closed loop on the exact model, N = 100 steps of 1 ms, and the
paper's robot setting N = 5 steps of 3.3 ms under `paper_robot`.
"""

import json
import sys
import time

import numpy as np

from commands.options import CommandParser, add_logging_argument, configure_logging, int_range
from controller import ilqr_reference
from controller.mpc import Mpc
from controller.problem import OcpSettings
from controller.reference import Sinusoid, reference_at
from model import dynamics
from model.dynamics import SUBSTEPS
from model.parameters import load_model

PAPER_TICK_US = 200.0  # paper: 100 steps of 1 ms on an i7-8850H laptop


def _closed_loop_ticks(mpc: Mpc, ticks: int, dt: float) -> np.ndarray:
    """Tick times (us) of the warm-started MPC driving the exact model; the cold first solve
    is excluded."""
    p = mpc.parameters.packed()
    q, qd = mpc.reference.packed()[1] + mpc.reference.packed()[2], 0.0
    result = mpc.tick(q, qd, 0.0)
    times = np.empty(ticks)
    for k in range(ticks):
        q, qd, *_ = dynamics.step(q, qd, result.current, p, dt, SUBSTEPS)
        start = time.perf_counter()
        result = mpc.tick(q, qd, (k + 1) * dt)
        times[k] = time.perf_counter() - start
    return times * 1e6


def _numpy_ticks(settings: OcpSettings, ticks: int) -> np.ndarray:
    """The straightforward version: numpy iLQR, warm start shifted by one, one iteration
    (simulate, backward pass, line search) per tick, on the same closed loop."""
    model = load_model()
    p = model.parameters.packed()
    from controller.problem import pack_cost

    c = pack_cost(settings, model.limits, model.parameters.drive_gain)
    packed = Sinusoid().packed()
    n, dt = settings.horizon, settings.dt
    q, qd = packed[1] + packed[2], 0.0
    offsets = np.arange(n + 1) * dt
    U = np.full(n, 0.0)
    _, U, _, _, _ = ilqr_reference.solve((q, qd), U, np.stack(reference_at(packed, offsets), 1),
                                         p, c, settings.max_iterations)
    times = np.empty(ticks)
    for k in range(ticks):
        q, qd, *_ = dynamics.step(q, qd, float(np.clip(U[0], -6, 6)), p, dt, SUBSTEPS)
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
        result = mpc.tick(packed[1] + packed[2], 0.0, 0.0)
        times.append(time.perf_counter() - start)
        if result.solve.status_name != "converged":
            raise RuntimeError(f"cold solve did not converge: {result.solve}")
    return float(np.median(times) * 1e3)


def measure(settings: OcpSettings, ticks: int, numpy_ticks: int) -> dict:
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


def main(argv: list[str] | None = None) -> int:
    parser = CommandParser(prog="bench", description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--ticks", type=int_range(1, 10_000_000), default=20000)
    parser.add_argument("--numpy-ticks", type=int_range(1, 10_000_000), default=300)
    add_logging_argument(parser)
    args = parser.parse_args(argv)
    configure_logging(parser.prog, args.log_level)
    result = measure(OcpSettings(), args.ticks, args.numpy_ticks)
    result["paper_tick_us"] = PAPER_TICK_US
    result["speedup_over_paper"] = round(PAPER_TICK_US / result["tick_median_us"], 1)
    result["paper_robot"] = measure(OcpSettings(horizon=5, dt=3.3e-3), args.ticks,
                                    args.numpy_ticks)
    if args.json:
        print(json.dumps(result))
    else:
        for key, value in result.items():
            print(f"{key}: {value}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
