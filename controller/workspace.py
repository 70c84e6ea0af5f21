"""Memory layout of the batched MPC: one float64 row per joint, holding everything its tick
reads and writes, and the named views the compiled code and Python see it through.

One 2-D array crosses the Python/numba border per call whatever the number of joints (each
array argument costs dispatch time), and each joint's row is its own, so the threads of a
parallel tick never write to the same memory. A row is

    header | dynamics parameters | cost vector | trajectory 1 | trajectory 2 | K | kff | reference

The header carries the tick's inputs, the solver's outcome and the MPC's bookkeeping; the two
trajectories are the current solution and the line search's trial, swapped (never copied) when
a trial is accepted.
"""

from typing import NamedTuple

import numba
import numpy as np
from numba.extending import register_jitable

from controller.problem import N_COST
from model.dynamics import N_PARAMS

JIT = {"cache": True, "error_model": "numpy", "nogil": True}

COLD, WARM, RESAMPLE, SKIP = 0, 1, 2, 3  # tick modes, per joint (both kernels read them here)

# header: inputs of the tick (written by Python before the call)
POSITION = 0  # rad, measured
VELOCITY = 1  # rad/s, measured
MODE = 2  # COLD, WARM, RESAMPLE or SKIP (see controller.mpc); the tick leaves the next one
INITIAL_CURRENT = 3  # A, the constant guess of a cold solve
COLD_ITERATIONS = 4  # iterations of a cold solve
WARM_ITERATIONS = 5  # iterations of a warm-started tick
TOLERANCE = 6  # relative cost decrease that counts as converged
REFERENCE = 7  # 4 values: the packed reference (controller.reference)
# header: outcome of the tick (written by the compiled code)
STATUS = 11  # controller.ilqr status code
ITERATIONS = 12
COST = 13
MU = 14  # final regularisation
ROLLOUTS = 15  # trajectory simulations, line-search trials included
PLANNED_CURRENT = 16  # A, the first control of the solution
REFERENCE_POSITION = 17  # rad, q* at t0
REFERENCE_VELOCITY = 18  # rad/s, qd* at t0
# header: the MPC's memory between ticks
LAST_T0 = 19  # s, time of the previous tick (a warm tick needs exactly one step between)
SECOND_IS_CURRENT = 20  # 1.0 when the second trajectory holds the current solution
HEADER = 21
PARAMETERS = HEADER  # model.dynamics layout
COST_VECTOR = PARAMETERS + N_PARAMS  # controller.problem layout
TRAJECTORIES = COST_VECTOR + N_COST


class Trajectory(NamedTuple):
    """A trajectory over the horizon with its linearisation and cost derivatives."""

    X: np.ndarray  # (N + 1, 2) states q, qd
    U: np.ndarray  # (N,) motor current
    A: np.ndarray  # (N, 4) dx+/dx, row-major
    B: np.ndarray  # (N, 2) dx+/du
    LX: np.ndarray  # (N + 1, 2) cost gradient in q, qd (terminal last)
    LXX: np.ndarray  # (N + 1, 2) cost Hessian diagonal in q, qd
    LU: np.ndarray  # (N,)
    LUU: np.ndarray  # (N,)
    LC: np.ndarray  # (N + 1,) stage costs, terminal last


class Workspace(NamedTuple):
    current: Trajectory  # the solution the next tick starts from
    trial: Trajectory  # where the line search writes
    K: np.ndarray  # (N, 2) feedback gains
    kff: np.ndarray  # (N,) feed-forward steps
    reference_position: np.ndarray  # (N + 1,) q* over the horizon
    reference_velocity: np.ndarray  # (N + 1,) qd* over the horizon


@register_jitable
def trajectory_size(n: int) -> int:
    return 2 * (n + 1) + n + 4 * n + 2 * n + 2 * (n + 1) + 2 * (n + 1) + n + n + n + 1


def row_size(n: int) -> int:
    """Floats in one joint's row for a horizon of n steps."""
    return TRAJECTORIES + 2 * trajectory_size(n) + 2 * n + n + 2 * (n + 1)


@numba.njit(**JIT)
def _trajectory(row, start, n):
    """The trajectory laid out from row[start]; returns it and where it ends."""
    x_end = start + 2 * (n + 1)
    u_end = x_end + n
    a_end = u_end + 4 * n
    b_end = a_end + 2 * n
    lx_end = b_end + 2 * (n + 1)
    lxx_end = lx_end + 2 * (n + 1)
    lu_end = lxx_end + n
    luu_end = lu_end + n
    lc_end = luu_end + n + 1
    return Trajectory(row[start:x_end].reshape((n + 1, 2)), row[x_end:u_end],
                      row[u_end:a_end].reshape((n, 4)), row[a_end:b_end].reshape((n, 2)),
                      row[b_end:lx_end].reshape((n + 1, 2)),
                      row[lx_end:lxx_end].reshape((n + 1, 2)), row[lxx_end:lu_end],
                      row[lu_end:luu_end], row[luu_end:lc_end]), lc_end


@numba.njit(**JIT)
def trajectories(row, n):
    """The two trajectories in their fixed order (which one is current is in the header)."""
    first, end = _trajectory(row, TRAJECTORIES, n)
    second, _ = _trajectory(row, end, n)
    return first, second


@numba.njit(**JIT)
def views(row, n):
    """The named views into one joint's row, current solution first."""
    first, second = trajectories(row, n)
    end = TRAJECTORIES + 2 * trajectory_size(n)
    K = row[end:end + 2 * n].reshape((n, 2))
    end += 2 * n
    kff = row[end:end + n]
    end += n
    ref_q = row[end:end + n + 1]
    ref_qd = row[end + n + 1:end + 2 * n + 2]
    if row[SECOND_IS_CURRENT] == 1.0:
        return Workspace(second, first, K, kff, ref_q, ref_qd)
    return Workspace(first, second, K, kff, ref_q, ref_qd)
