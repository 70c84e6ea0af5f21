"""The batched MPC tick with the joints side by side in SIMD lanes: the same iLQR as
`controller.ilqr` and `controller.mpc.tick_joint` (read those first), with every innermost loop
running over joints so that LLVM vectorises the backward pass, the forward simulation and the
barrier terms across them (AVX2 with FMA, AVX-512 where the CPU has it).

Layout: a joint-major structure of arrays. Joints go in chunks of `width` lanes (WIDTH, or one
for a joint alone); `trajectories[which, chunk, k, field, lane]` holds step k of joint
chunk x width + lane, so the values of one step for consecutive joints are contiguous, and
`gains`, `scratch` (per-joint parameters, cost vector and solver state) and `state` follow the
same pattern. The steps are a ring of n + 1 slots: a tick advances it by one instead of moving
the stored solution (see `_at`). The tick's inputs and outputs stay in the joints' workspace
rows (the `controller.workspace` header), so Python's side of the batch does not change; the
trajectory part of those rows is unused by this kernel.

Control flow: every joint keeps its own iLQR. A joint is in a phase (needs a backward pass, a
first simulation, a line-search trial, or is done) and the tick runs rounds of one masked
backward pass and one forward simulation over all joints until every joint is done. Each joint
thus goes through exactly the sequence of passes and decisions it goes through alone in
`tick_joint`: its own mode (cold, warm, resample, skip), regularisation, and line search that
accepts or rejects its own step. A simulation writes every lane of the trial trajectory; the
joints that accept it take it as their current solution (the two trajectories swap roles when
every joint of the chunk takes it, as in the scalar solver; otherwise the takers' lanes are
copied), and the trial lanes of the others are scratch. A round costs the same whatever the
number of joints still working in a chunk (a chunk is as slow as its slowest joint), and
nothing for a chunk none of whose joints works in it: that chunk's sweep, simulation and copy
are left out.

The transcendental functions are `controller.lane_math` (the scalar kernel's are libm's), so a
lane joint's decisions equal the scalar kernel's to rounding, not bit for bit (tested to 1e-9
relative in tests/test_batch_lanes.py); a joint decides the same bit for bit whatever its chunk
and width. The cost algebra and the discrete step are shared with the scalar kernel
(`controller.cost`, `controller.action_model`); the acceleration is the paper's joint model of
`model.dynamics.smooth_acceleration` written out for lanes, with the extra effects' terms
(`model.effects`) added by their own code in a batch whose models switch one on (`has_effects`:
that batch's loops over lanes are not vectorised, their terms branching and calling libm).

Threads: a chunk's tick is whole in itself (its own rounds, ring and current trajectory), so
any thread may run it. With threads, one parallel region a tick (a numba prange over the
threads) and each thread ticks its share of the chunks, then any other that no thread has
taken yet (`_tick_claimed`). Not fixed halves: waking the second thread costs the first
10-17 us on this virtual machine and the second starts 15-30 us into the tick (paced at
1 kHz; far later, or on the first thread's core, under load), and with halves the tick waited
for it: 32 joints took 142 us on two threads against 105 us on one (SCHED_RR, load 5.8). One
thread is the default where the machine has two cores or fewer (see `default_threads`).
numba's TBB layer (the `tbb` wheel, not a dependency: its libtbb.so.12 was not on the loader's
path here) started the two 40 us iterations of a region at 9 and 13 us and returned 2 us
after them, paced at 1 kHz, where OpenMP's passive wait took 17, 33 and 23 us; numba's own
workqueue layer 74, 70 and 23 us (SCHED_RR, load 4-5).
"""

import os
import platform

import llvmlite.binding as llvm
import numba
import numpy as np
from llvmlite import ir
from numba import literally, types
from numba.core import cgutils
from numba.extending import intrinsic, register_jitable

from controller import workspace as ws
from controller.action_model import stage_cost_given, step_given, terminal_cost_given
from controller.cost import control_box
from controller.ilqr import (
    ARMIJO,
    CONVERGED,
    LINE_SEARCH_FAILED,
    LINE_SEARCH_STEPS,
    MAX_ITERATIONS,
    MU_MAX,
    MU_MIN,
    NOT_FINITE,
    WARM_COST_RATIO,
    WARM_TRIALS,
)
from controller.lane_math import exp, sin_cos, tanh
from controller.problem import (
    C_ALPHA_POSITION,
    C_ALPHA_TORQUE,
    C_ALPHA_VELOCITY,
    C_DRIVE_GAIN,
    C_DT,
    C_FRICTION_SHARPNESS,
    N_COST,
)
from controller.reference import reference_at
from controller.workspace import COLD, JIT, SKIP, WARM
from model.dynamics import (
    EFFECT_OFFSET,
    N_PARAMS,
    P_DRIVE_GAIN,
    P_DRY,
    P_GRAVITY_MX,
    P_GRAVITY_MY,
    P_INERTIA,
    P_LINK_INERTIA,
    P_OFFSET,
    P_VISCOUS,
    current_losses,
    effect_terms,
)

# Joints go in chunks of WIDTH lanes: a compile-time width, so the compiler knows the loop over
# a chunk's lanes and the distance between two fields (and proves they do not overlap). Four
# doubles are one AVX2 register; with AVX-512 LLVM pairs two chunks' worth per instruction.
WIDTH = 8

# LLVM vectorises a loop with a constant trip count below 16 only if it needs no run-time check
# that its arrays do not overlap; a loop over a chunk's lanes reads and writes separate arrays
# (trajectories, gains, scratch), one cheap check per pair. The option is process-wide and read
# when a function is compiled: numba compiles ours at their first call, after this import.
# Elsewhere it only lets short loops with such checks be vectorised too.
llvm.set_option("", f"-vectorizer-min-trip-count={WIDTH}")

# fields of trajectories[which, chunk, k, field, lane]: the current solution and the trial. The
# step's Jacobians are kept as the acceleration's partial derivatives (AQ, AQD, AU), from which
# the backward pass forms A and B by `step_given`'s own expressions (the same bits): 13 fields
# instead of 16. In the control loop the line's simulation and the telemetry evict this working
# set between ticks, and the tick then runs at the speed of memory: with a 32 MB array written
# between ticks, talos_32's tick took 333-380 us against 127-142 us without (one thread).
Q, QD, U, AQ, AQD, AU, LQ, LQD, LQQ, LQDQD, LU, LUU, LC = range(13)
TRAJECTORY_FIELDS = 13
# fields of gains[chunk, k, field, lane]
K1, K2, KFF, REFERENCE_Q, REFERENCE_QD = range(5)  # feedback on q, qd; feed-forward; q*, qd*
GAIN_FIELDS = 5

# rows of scratch[chunk, row, lane]: the dynamics parameters, the cost vector, the solver's state
PARAMETERS = 0
COSTS = N_PARAMS
(Q0, QD0, BOX, TOLERANCE, MU, COST, MERIT, DV1, DV2, ALPHA, VX1, VX2, V11, V12, V22, SWEEP_OK,
 TOTAL, NEEDS_SWEEP, TAKES, SHIFTS, SUM, SIMULATED_Q, SIMULATED_QD, INVERSE_INERTIA,
 SIMULATES) = range(COSTS + N_COST, COSTS + N_COST + 25)
SCRATCH = COSTS + N_COST + 25

# phases of a joint within a tick
DONE, WARM_SWEEP, FIRST_ROLLOUT, SWEEP, SEARCH = range(5)
# rows of state[chunk, row, lane], the solver's integer state
(PHASE, ATTEMPT, ITERATION, MAX_ITER, AFTER_WARM, STATUS, ITERATION_OFFSET, ROLLOUTS_OFFSET,
 ROLLOUTS) = range(9)
STATE = 9
PADDING = -1  # STATUS of a lane that is skipped this tick or holds no joint
# columns of current[chunk, column]: which trajectory is the current one, the ring slot of
# step 0 (both trajectories and the gains are rings of n + 1 steps), and whether a thread has
# taken the chunk in this tick (threads); a row is 64 bytes
WHICH, RING, TAKEN = 0, 1, 2
CURRENT = 8
TICKED = 0  # claims[TICKED]: the chunks the threads of a tick have ticked


def has_effects(packed_parameters: np.ndarray) -> bool:
    """Whether a joint's model switches on an extra effect (`model.effects`): a batch with one
    runs the lane kernel that computes their terms (`tick_kernel`'s `effects`)."""
    first = min(EFFECT_OFFSET.values(), default=P_LINK_INERTIA)
    return bool(np.any(packed_parameters[first:P_LINK_INERTIA]))


def default_threads() -> int:
    """One thread on a machine with two cores or fewer, else two. On the two shared cores here
    (a KVM guest; 32 joints = 4 chunks, one and two threads alternating in one process, load
    4-6 from other work) two threads took 0.95-1.02 times one thread's tick under SCHED_RR and
    1.12-1.20 times at normal priority, against 1.22-1.47 and 1.20-2.0 with fixed halves
    before: under load the woken thread is often put on the caller's own core (the second
    core is busy) and the tick runs in turn anyway. The second thread costs its wake-up each
    tick (15-30 us here at 1 kHz, the futex wake 10-17 us of the caller's time) and competes
    with whatever holds the other core; on a robot PC with two cores that is the bus and the
    telemetry. Two on larger machines is not measured here; fewer than 9 joints are one
    chunk, one thread, whatever the count."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return 1 if (cores or 1) <= 2 else 2


def width(joints: int) -> int:
    """Lanes per chunk: WIDTH, or one for a joint alone (a vector of one real joint and seven
    idle lanes costs more than the joint alone)."""
    return 1 if joints == 1 else WIDTH


def chunks(joints: int) -> int:
    return -(-joints // width(joints))


def allocate(joints: int, n: int) -> tuple[np.ndarray, ...]:
    """The lane workspace of a batch: (trajectories, gains, scratch, state, current, claims),
    where current[c] says which of the two trajectories is chunk c's current one and where its
    step 0 sits in the ring, and `claims` counts the chunks a tick's threads have ticked.
    Separate arrays, so a loop's reads and writes fall in few groups the compiler can check
    for overlap once. A chunk's row of `current` is 64 bytes, as is `claims`: the threads
    write them, each for the chunks it ticks."""
    count = chunks(joints)
    lanes = width(joints)
    return (np.zeros((2, count, n + 1, TRAJECTORY_FIELDS, lanes)),
            np.zeros((count, n + 1, GAIN_FIELDS, lanes)), np.zeros((count, SCRATCH, lanes)),
            np.zeros((count, STATE, lanes), dtype=np.int64),
            np.zeros((count, CURRENT), dtype=np.int64), np.zeros(CURRENT, dtype=np.int64))


def _costs_reader():
    """A jitable function returning the cost vector of lane w of chunk c as a tuple (what
    controller.cost indexes), read from scratch with no array view inside the lane loop."""
    items = ", ".join(f"S[c, {COSTS + i}, w]" for i in range(N_COST))
    namespace: dict = {}
    exec(f"def lane_costs(S, c, w):\n    return ({items},)\n", namespace)
    return register_jitable(forceinline=True)(namespace["lane_costs"])


lane_costs = _costs_reader()


def _parameters_reader():
    """The dynamics parameters of lane w of chunk c as a tuple (what model.dynamics indexes),
    as `lane_costs` reads the cost vector."""
    items = ", ".join(f"S[c, {PARAMETERS + i}, w]" for i in range(N_PARAMS))
    namespace: dict = {}
    exec(f"def lane_parameters(S, c, w):\n    return ({items},)\n", namespace)
    return register_jitable(forceinline=True)(namespace["lane_parameters"])


lane_parameters = _parameters_reader()


@intrinsic
def _data(typingctx, a):
    """The data pointer of a C-contiguous float64 array."""
    if not (isinstance(a, types.Array) and a.dtype == types.float64 and a.layout == "C"):
        return None

    def codegen(context, builder, signature, args):
        return context.make_array(signature.args[0])(context, builder, args[0]).data

    return types.CPointer(types.float64)(a), codegen


@register_jitable(forceinline=True)
def _steps(a, fields, width):
    """A (chunk, k, field, lane) array seen with its inner extents as compile-time constants:
    the offsets of fields within a step are then constants the compiler sees, so it can prove
    that the fields a loop writes are not the ones it reads and vectorise the loop over lanes.
    A view without reference counting: valid while `a` is."""
    return numba.carray(_data(a), (a.shape[0], a.shape[1], fields, width))


@register_jitable(forceinline=True)
def _rows(a, width):
    """scratch[chunk, row, lane] seen with its inner extents as compile-time constants."""
    return numba.carray(_data(a), (a.shape[0], SCRATCH, width))


@register_jitable(forceinline=True)
def _any(S, c, row, width):
    """Whether any lane of chunk c has scratch[row] set: a chunk none of whose joints works in
    a round is left out of its sweep or simulation. A tick's rounds go on until its slowest
    joint is done (a cold solve's line search is up to 10 trials an iteration), and
    a chunk of joints that finished early must not pay for them: measured on talos_32's
    problem, the wrists' and grippers' line searches (their friction step at the edge of
    stability) made every chunk run up to 16 simulations a tick."""
    for w in range(width):
        if S[c, row, w] != 0.0:
            return True
    return False


@register_jitable(forceinline=True)
def _at(k, r, n):
    """The slot of step k in a ring of n + 1 slots whose step 0 is in slot r: a tick advances
    the ring by one instead of moving every stored step (controller.mpc._shift's copy)."""
    slot = k + r
    return slot - (n + 1) if slot > n else slot


@register_jitable(forceinline=True)
def _acceleration(q, qd, u, S, c, w, effects):
    """`model.dynamics.smooth_acceleration` with the lane maths: qdd and its partial
    derivatives in q, qd and u. `effects` (a compile-time constant) adds the extra effects'
    terms (`model.effects`, computed by their own code with libm's functions), in
    smooth_acceleration's order: a joint whose effects are all off gets the same bits either
    way (their terms are zeros). Without them the loop over lanes is vectorised; with them,
    whose terms branch and call libm, it runs lane after lane."""
    if effects:
        return _acceleration_with_effects(q, qd, u, S, c, w)
    sharpness = S[c, COSTS + C_FRICTION_SHARPNESS, w]
    th = tanh(sharpness * qd)
    inv_inertia = S[c, INVERSE_INERTIA, w]  # 1 / I, as smooth_acceleration computes it
    sin_q, cos_q = sin_cos(q)
    my, mx = S[c, PARAMETERS + P_GRAVITY_MY, w], S[c, PARAMETERS + P_GRAVITY_MX, w]
    gravity = my * sin_q + mx * cos_q
    d_gravity = my * cos_q - mx * sin_q
    level = S[c, PARAMETERS + P_DRY, w]
    viscous = S[c, PARAMETERS + P_VISCOUS, w]
    gain = S[c, PARAMETERS + P_DRIVE_GAIN, w]
    torque = gain * u - viscous * qd - level * th - S[c, PARAMETERS + P_OFFSET, w] - gravity
    d_friction = viscous + level * sharpness * (1.0 - th * th)
    return (torque * inv_inertia, -d_gravity * inv_inertia, -d_friction * inv_inertia,
            gain * inv_inertia)


@register_jitable(forceinline=True)
def _acceleration_with_effects(q, qd, u, S, c, w):
    """`model.dynamics.smooth_acceleration` term by term, the base model's functions being the
    lane maths'."""
    p = lane_parameters(S, c, w)
    sharpness = S[c, COSTS + C_FRICTION_SHARPNESS, w]
    th = tanh(sharpness * qd)
    inv_inertia = S[c, INVERSE_INERTIA, w]
    sin_q, cos_q = sin_cos(q)
    gravity = p[P_GRAVITY_MY] * sin_q + p[P_GRAVITY_MX] * cos_q
    d_gravity = p[P_GRAVITY_MY] * cos_q - p[P_GRAVITY_MX] * sin_q
    level, level_q, level_qd, extra, extra_q, extra_qd = effect_terms(q, qd, p, p[P_DRY],
                                                                      gravity, d_gravity)
    level = level + p[P_DRY]
    loss, d_loss = current_losses(u, p)
    torque = (p[P_DRIVE_GAIN] * (u - loss) - p[P_VISCOUS] * qd - level * th - p[P_OFFSET]
              - gravity - extra)
    d_friction = p[P_VISCOUS] + level * sharpness * (1.0 - th * th) + level_qd * th + extra_qd
    return (torque * inv_inertia, -(d_gravity + extra_q + level_q * th) * inv_inertia,
            -d_friction * inv_inertia, p[P_DRIVE_GAIN] * (1.0 - d_loss) * inv_inertia)


@register_jitable(forceinline=True)
def _store_stage(T, G, S, c, k, w, q, qd, u, effects):
    """Step k (a slot) of lane w into trajectory T: state, control, linearisation
    and cost derivatives (controller.ilqr.store_stage). Returns the stage cost and x+."""
    costs = lane_costs(S, c, w)
    a, a_q, a_qd, a_u = _acceleration(q, qd, u, S, c, w, effects)
    step = step_given(q, qd, costs[C_DT], a, a_q, a_qd, a_u)  # its Jacobians: in _backward
    cost = stage_cost_given(q, qd, u, G[c, k, REFERENCE_Q, w], G[c, k, REFERENCE_QD, w], costs,
                            exp(costs[C_ALPHA_POSITION] * q), exp(costs[C_ALPHA_VELOCITY] * qd),
                            exp(costs[C_ALPHA_TORQUE] * (costs[C_DRIVE_GAIN] * u)))
    T[c, k, Q, w] = q
    T[c, k, QD, w] = qd
    T[c, k, U, w] = u
    T[c, k, LQ, w] = cost.l_q
    T[c, k, LQD, w] = cost.l_qd
    T[c, k, LQQ, w] = cost.l_qq
    T[c, k, LQDQD, w] = cost.l_qdqd
    T[c, k, LU, w] = cost.l_u
    T[c, k, LUU, w] = cost.l_uu
    T[c, k, LC, w] = cost.l
    T[c, k, AQ, w] = a_q
    T[c, k, AQD, w] = a_qd
    T[c, k, AU, w] = a_u
    return cost.l, step.q, step.qd


@register_jitable(forceinline=True)
def _store_terminal(T, G, S, c, n, w, q, qd):
    """The terminal state and its cost derivatives; returns the terminal cost."""
    costs = lane_costs(S, c, w)
    cost = terminal_cost_given(q, qd, G[c, n, REFERENCE_Q, w], G[c, n, REFERENCE_QD, w], costs,
                               exp(costs[C_ALPHA_POSITION] * q),
                               exp(costs[C_ALPHA_VELOCITY] * qd))
    T[c, n, Q, w] = q
    T[c, n, QD, w] = qd
    T[c, n, LQ, w] = cost.l_q
    T[c, n, LQD, w] = cost.l_qd
    T[c, n, LQQ, w] = cost.l_qq
    T[c, n, LQDQD, w] = cost.l_qdqd
    T[c, n, LC, w] = cost.l
    return cost.l


@numba.njit(**JIT)
def _rollout(current, trial, gains, scratch, n, r, c0, c1, width, effects):
    """Simulate u = U_cur + alpha kff + K (x - X_cur) from x0 into the trial trajectory, for
    every lane of chunks [c0, c1) with its own alpha and gains (controller.ilqr.rollout); the
    total cost, inf when not finite, goes to scratch[TOTAL]."""
    literally(effects)  # with or without the effects' terms: one kernel each
    literally(width)  # a compile-time lane count: one compiled kernel per width
    Tc, Tt = _steps(current, TRAJECTORY_FIELDS, width), _steps(trial, TRAJECTORY_FIELDS, width)
    G, S = _steps(gains, GAIN_FIELDS, width), _rows(scratch, width)
    for c in range(c0, c1):
        if not _any(S, c, SIMULATES, width):
            continue
        for w in range(width):
            S[c, SIMULATED_Q, w] = S[c, Q0, w]
            S[c, SIMULATED_QD, w] = S[c, QD0, w]
            S[c, TOTAL, w] = 0.0
        for k in range(n):
            # the state carried in scratch, not read back from the next slot of the ring (its
            # distance from this one changes at the wrap, which LLVM would check each step)
            i = _at(k, r, n)
            for w in range(width):
                q, qd = S[c, SIMULATED_Q, w], S[c, SIMULATED_QD, w]
                u = Tc[c, i, U, w] + S[c, ALPHA, w] * G[c, i, KFF, w] + G[c, i, K1, w] * (
                    q - Tc[c, i, Q, w]) + G[c, i, K2, w] * (qd - Tc[c, i, QD, w])
                cost, q_next, qd_next = _store_stage(Tt, G, S, c, i, w, q, qd, u, effects)
                S[c, TOTAL, w] += cost
                S[c, SIMULATED_Q, w] = q_next
                S[c, SIMULATED_QD, w] = qd_next
        last = _at(n, r, n)
        for w in range(width):
            total = S[c, TOTAL, w] + _store_terminal(Tt, G, S, c, last, w, S[c, SIMULATED_Q, w],
                                                     S[c, SIMULATED_QD, w])
            S[c, TOTAL, w] = total if np.isfinite(total) else np.inf


@numba.njit(**JIT)
def _backward(current, gains, scratch, n, r, c0, c1, width):
    """Riccati sweep of every lane of chunks [c0, c1) with its own mu
    (controller.ilqr.backward); writes the gains only of lanes with scratch[NEEDS_SWEEP] set. A
    lane whose regularised Quu is not positive at some step ends with scratch[SWEEP_OK] = 0
    (its later steps are computed and ignored: the scalar sweep would have stopped there)."""
    literally(width)  # a compile-time lane count: one compiled kernel per width
    Tc = _steps(current, TRAJECTORY_FIELDS, width)
    G, S = _steps(gains, GAIN_FIELDS, width), _rows(scratch, width)
    for c in range(c0, c1):
        if not _any(S, c, NEEDS_SWEEP, width):
            continue
        last = _at(n, r, n)
        for w in range(width):
            S[c, VX1, w] = Tc[c, last, LQ, w]
            S[c, VX2, w] = Tc[c, last, LQD, w]
            S[c, V11, w] = Tc[c, last, LQQ, w]
            S[c, V12, w] = 0.0
            S[c, V22, w] = Tc[c, last, LQDQD, w]
            S[c, DV1, w] = 0.0
            S[c, DV2, w] = 0.0
            S[c, SWEEP_OK, w] = 1.0
        for step in range(n - 1, -1, -1):
            k = _at(step, r, n)
            for w in range(width):
                mu = S[c, MU, w]
                box = S[c, BOX, w]
                vx1, vx2 = S[c, VX1, w], S[c, VX2, w]
                v11, v12, v22 = S[c, V11, w], S[c, V12, w], S[c, V22, w]
                step = step_given(0.0, 0.0, S[c, COSTS + C_DT, w], 0.0, Tc[c, k, AQ, w],
                                  Tc[c, k, AQD, w], Tc[c, k, AU, w])
                a11, a12, a21, a22, b1, b2 = (step.a11, step.a12, step.a21, step.a22, step.b1,
                                              step.b2)
                luu = Tc[c, k, LUU, w]
                qx1 = Tc[c, k, LQ, w] + a11 * vx1 + a21 * vx2
                qx2 = Tc[c, k, LQD, w] + a12 * vx1 + a22 * vx2
                qu = Tc[c, k, LU, w] + b1 * vx1 + b2 * vx2
                vb1 = v11 * b1 + v12 * b2
                vb2 = v12 * b1 + v22 * b2
                quu = luu + b1 * vb1 + b2 * vb2
                qux1 = vb1 * a11 + vb2 * a21
                qux2 = vb1 * a12 + vb2 * a22
                rb1 = vb1 + mu * b1
                rb2 = vb2 + mu * b2
                quu_r = luu + b1 * rb1 + b2 * rb2
                S[c, SWEEP_OK, w] = S[c, SWEEP_OK, w] if quu_r > 0.0 else 0.0
                qux1_r = rb1 * a11 + rb2 * a21
                qux2_r = rb1 * a12 + rb2 * a22
                va11 = v11 * a11 + v12 * a21
                va12 = v11 * a12 + v12 * a22
                va21 = v12 * a11 + v22 * a21
                va22 = v12 * a12 + v22 * a22
                qxx11 = Tc[c, k, LQQ, w] + a11 * va11 + a21 * va21
                qxx12 = a11 * va12 + a21 * va22
                qxx22 = Tc[c, k, LQDQD, w] + a12 * va12 + a22 * va22
                kk = -qu / quu_r
                k1 = -qux1_r / quu_r
                k2 = -qux2_r / quu_r
                u = Tc[c, k, U, w]
                clamped = abs(u + kk) > box
                kk = ((box if u + kk > 0.0 else -box) - u) if clamped else kk
                k1 = 0.0 if clamped else k1
                k2 = 0.0 if clamped else k2
                writes = S[c, NEEDS_SWEEP, w] != 0.0
                G[c, k, KFF, w] = kk if writes else G[c, k, KFF, w]
                G[c, k, K1, w] = k1 if writes else G[c, k, K1, w]
                G[c, k, K2, w] = k2 if writes else G[c, k, K2, w]
                S[c, VX1, w] = qx1 + k1 * quu * kk + k1 * qu + qux1 * kk
                S[c, VX2, w] = qx2 + k2 * quu * kk + k2 * qu + qux2 * kk
                S[c, V11, w] = qxx11 + k1 * quu * k1 + 2.0 * k1 * qux1
                S[c, V12, w] = qxx12 + k1 * quu * k2 + k1 * qux2 + qux1 * k2
                S[c, V22, w] = qxx22 + k2 * quu * k2 + 2.0 * k2 * qux2
                S[c, DV1, w] += kk * qu
                S[c, DV2, w] += 0.5 * kk * kk * quu


@numba.njit(**JIT)
def _shift(current, gains, scratch, n, r, c0, c1, width, effects):
    """The rest of controller.mpc._shift for lanes with scratch[SHIFTS] set, once the ring has
    advanced: the last control repeated, the last stage and the terminal state evaluated anew.
    Then every lane's shifted cost summed into scratch[SUM], in the scalar tick's order."""
    literally(effects)
    literally(width)  # a compile-time lane count: one compiled kernel per width
    Tc = _steps(current, TRAJECTORY_FIELDS, width)
    G, S = _steps(gains, GAIN_FIELDS, width), _rows(scratch, width)
    before_last, last, terminal = _at(n - 2, r, n), _at(n - 1, r, n), _at(n, r, n)
    for c in range(c0, c1):
        for w in range(width):
            if S[c, SHIFTS, w] != 0.0:
                _, q_next, qd_next = _store_stage(Tc, G, S, c, last, w, Tc[c, last, Q, w],
                                                  Tc[c, last, QD, w], Tc[c, before_last, U, w],
                                                  effects)
                _store_terminal(Tc, G, S, c, terminal, w, q_next, qd_next)
            S[c, SUM, w] = 0.0
        for k in range(n + 1):
            i = _at(k, r, n)
            for w in range(width):
                S[c, SUM, w] += Tc[c, i, LC, w]


@numba.njit(**JIT)
def _take(trajectories, scratch, current, n, joints, c, width):
    """The trial becomes the current solution of chunk c's lanes with scratch[TAKES] set: the
    two trajectories swap roles when every joint of the chunk takes it, the takers' lanes are
    copied otherwise."""
    literally(width)  # a compile-time lane count: one compiled kernel per width
    S = _rows(scratch, width)
    takers = 0
    for w in range(width):
        takers += S[c, TAKES, w] != 0.0
    if takers == 0:
        return
    if takers == min((c + 1) * width, joints) - c * width:
        current[c, WHICH] = 1 - current[c, WHICH]
        return
    Tc = _steps(trajectories[current[c, WHICH]], TRAJECTORY_FIELDS, width)
    Tt = _steps(trajectories[1 - current[c, WHICH]], TRAJECTORY_FIELDS, width)
    for k in range(n + 1):
        for f in range(TRAJECTORY_FIELDS):
            for w in range(width):
                takes = S[c, TAKES, w] != 0.0
                Tc[c, k, f, w] = Tt[c, k, f, w] if takes else Tc[c, k, f, w]


@numba.njit(**JIT)
def _finish(state, c, w, status):
    """A lane's iLQR ended with `status` (its iterations, cost and mu are in its state)."""
    state[c, PHASE, w] = DONE
    state[c, STATUS, w] = status


@numba.njit(**JIT)
def _start_first_rollout(G, scratch, state, c, w, n):
    """Classic iLQR from the controls in the current trajectory (controller.ilqr
    solve_from_controls): no feedback, alpha 0."""
    for i in range(n + 1):  # every slot of the ring: the order does not matter
        G[c, i, K1, w] = 0.0
        G[c, i, K2, w] = 0.0
        G[c, i, KFF, w] = 0.0  # times alpha 0 (the scalar solver's are finite leftovers,
        # a lane's may be those of a failed sweep)
    scratch[c, ALPHA, w] = 0.0
    state[c, PHASE, w] = FIRST_ROLLOUT


@numba.njit(**JIT)
def _start_iterations(scratch, state, c, w, cost, max_iterations, iteration_offset,
                      rollouts_offset):
    """controller.ilqr.iterate from a current trajectory of cost `cost`."""
    scratch[c, COST, w] = cost
    scratch[c, MU, w] = MU_MIN
    state[c, ITERATION, w] = 0
    state[c, MAX_ITER, w] = max_iterations
    state[c, ITERATION_OFFSET, w] = iteration_offset
    state[c, ROLLOUTS_OFFSET, w] = rollouts_offset
    state[c, ROLLOUTS, w] = 0
    state[c, AFTER_WARM, w] = 0
    state[c, PHASE, w] = SWEEP


@numba.njit(**JIT)
def _start_search(scratch, state, c, w, merit):
    state[c, PHASE, w] = SEARCH
    state[c, ATTEMPT, w] = 0
    scratch[c, ALPHA, w] = 1.0
    scratch[c, MERIT, w] = merit


@numba.njit(**JIT)
def _bump_mu(scratch, state, c, w):
    """Regularise more after a failed sweep or line search, or give up past MU_MAX."""
    scratch[c, MU, w] = max(scratch[c, MU, w] * 10.0, 1e-6)
    if scratch[c, MU, w] > MU_MAX:
        _finish(state, c, w, LINE_SEARCH_FAILED)


@numba.njit(**JIT)
def _begin(rows, Tc, G, scratch, state, t0, n, r, c0, c1, width):
    """Read each joint's inputs and mode from its row and set it on its way (tick_joint's
    opening), the ring having advanced one step; returns whether any lane shifts its warm
    solution."""
    joints = rows.shape[0]
    shifts = False
    for c in range(c0, c1):
        for w in range(width):
            j = c * width + w
            row = rows[min(j, joints - 1)]
            scratch[c, SHIFTS, w] = 0.0
            scratch[c, NEEDS_SWEEP, w] = 0.0
            scratch[c, TAKES, w] = 0.0
            state[c, PHASE, w] = DONE
            state[c, STATUS, w] = PADDING
            mode = row[ws.MODE]
            if j >= joints or mode == SKIP:
                if j < joints:
                    row[ws.MODE] = COLD
                continue
            for i in range(N_PARAMS):
                scratch[c, PARAMETERS + i, w] = row[ws.PARAMETERS + i]
            for i in range(N_COST):
                scratch[c, COSTS + i, w] = row[ws.COST_VECTOR + i]
            scratch[c, INVERSE_INERTIA, w] = 1.0 / scratch[c, PARAMETERS + P_INERTIA, w]
            costs = lane_costs(scratch, c, w)
            scratch[c, BOX, w] = control_box(costs)
            scratch[c, Q0, w] = row[ws.POSITION]
            scratch[c, QD0, w] = row[ws.VELOCITY]
            state[c, MAX_ITER, w] = int(row[ws.COLD_ITERATIONS] if mode == COLD
                                        else row[ws.WARM_ITERATIONS])
            scratch[c, TOLERANCE, w] = row[ws.TOLERANCE]
            scratch[c, MU, w] = MU_MIN
            state[c, ITERATION, w] = 0
            state[c, ROLLOUTS, w] = 0
            state[c, ITERATION_OFFSET, w] = 0
            state[c, ROLLOUTS_OFFSET, w] = 0
            reference = row[ws.REFERENCE:ws.REFERENCE + 4]
            dt = costs[C_DT]
            contiguous = abs(t0 - row[ws.LAST_T0] - dt) < 1e-6 * dt
            row[ws.LAST_T0] = t0
            if mode == WARM and contiguous:
                last = _at(n, r, n)
                G[c, last, REFERENCE_Q, w], G[c, last, REFERENCE_QD, w] = reference_at(
                    reference, t0 + n * dt)
                scratch[c, SHIFTS, w] = 1.0
                shifts = True
                state[c, PHASE, w] = WARM_SWEEP
                continue
            for k in range(n + 1):
                i = _at(k, r, n)
                G[c, i, REFERENCE_Q, w], G[c, i, REFERENCE_QD, w] = reference_at(
                    reference, t0 + k * dt)
            if mode == COLD:
                for k in range(n):
                    Tc[c, _at(k, r, n), U, w] = row[ws.INITIAL_CURRENT]
            else:  # the ring moved the controls up by one; the last one stays
                Tc[c, _at(n - 1, r, n), U, w] = Tc[c, _at(n - 2, r, n), U, w]
            _start_first_rollout(G, scratch, state, c, w, n)
    # lanes past the last joint compute on its parameters (no overflow, no denormals), ignored
    last_chunk, last_lane = divmod(joints - 1, width)
    if c0 <= last_chunk < c1:
        for w in range(last_lane + 1, width):
            for i in range(COSTS + N_COST):
                scratch[last_chunk, i, w] = scratch[last_chunk, i, last_lane]
            for i in (Q0, QD0, INVERSE_INERTIA):
                scratch[last_chunk, i, w] = scratch[last_chunk, i, last_lane]
    return shifts


@numba.njit(**JIT)
def _before_sweep(scratch, state, c0, c1, width):
    """Mark the lanes that sweep this round; an iterating lane first checks its iteration
    budget (the head of controller.ilqr.iterate's loop). Returns whether any lane sweeps."""
    any_sweep = False
    for c in range(c0, c1):
        for w in range(width):
            phase = state[c, PHASE, w]
            if phase == SWEEP:
                if state[c, ITERATION, w] >= state[c, MAX_ITER, w]:
                    _finish(state, c, w, MAX_ITERATIONS)
                    continue
                state[c, ITERATION, w] += 1
            elif phase != WARM_SWEEP:
                continue
            scratch[c, NEEDS_SWEEP, w] = 1.0
            any_sweep = True
    return any_sweep


@numba.njit(**JIT)
def _after_sweep(Tc, G, scratch, state, n, r, c0, c1, width):
    """Each lane that swept decides, as the scalar solver does after `backward`."""
    for c in range(c0, c1):
        for w in range(width):
            if scratch[c, NEEDS_SWEEP, w] == 0.0:
                continue
            scratch[c, NEEDS_SWEEP, w] = 0.0
            ok = scratch[c, SWEEP_OK, w] != 0.0
            if state[c, PHASE, w] == WARM_SWEEP:
                if not ok:
                    _start_first_rollout(G, scratch, state, c, w, n)
                    continue
                first = _at(0, r, n)
                d1 = scratch[c, Q0, w] - Tc[c, first, Q, w]
                d2 = scratch[c, QD0, w] - Tc[c, first, QD, w]
                merit = scratch[c, SUM, w] + scratch[c, VX1, w] * d1 + scratch[c, VX2, w] * d2 + (
                    0.5 * (scratch[c, V11, w] * d1 * d1 + 2.0 * scratch[c, V12, w] * d1 * d2
                           + scratch[c, V22, w] * d2 * d2))
                _start_search(scratch, state, c, w, merit)
                state[c, AFTER_WARM, w] = 1
                continue
            if not ok:
                _bump_mu(scratch, state, c, w)
                continue
            cost = scratch[c, COST, w]
            if -scratch[c, DV1, w] < scratch[c, TOLERANCE, w] * max(cost, 1.0) * 1e-3:
                _finish(state, c, w, CONVERGED)  # the model predicts no meaningful improvement
                continue
            _start_search(scratch, state, c, w, cost)


@numba.njit(**JIT)
def _after_rollout(G, scratch, state, n, c0, c1, width):
    """Each lane that simulated decides (solve_from_controls after its first simulation, the
    line search after a trial); sets scratch[TAKES] on the lanes whose trial becomes their
    current solution. Returns whether any lane still has work."""
    for c in range(c0, c1):
        for w in range(width):
            scratch[c, TAKES, w] = 0.0
            phase = state[c, PHASE, w]
            total = scratch[c, TOTAL, w]
            if phase == FIRST_ROLLOUT:
                scratch[c, TAKES, w] = 1.0  # simulated in place by the scalar solver, finite or not
                rollouts_offset = state[c, ROLLOUTS_OFFSET, w] + 1
                if not np.isfinite(total):
                    scratch[c, COST, w] = total
                    scratch[c, MU, w] = MU_MIN
                    state[c, ITERATION, w] = 0
                    state[c, ROLLOUTS, w] = 0
                    state[c, ITERATION_OFFSET, w] = 0
                    state[c, ROLLOUTS_OFFSET, w] = rollouts_offset
                    _finish(state, c, w, NOT_FINITE)
                    continue
                _start_iterations(scratch, state, c, w, total, state[c, MAX_ITER, w], 0,
                                  rollouts_offset)
                continue
            if phase != SEARCH:
                continue
            state[c, ATTEMPT, w] += 1
            alpha = scratch[c, ALPHA, w]
            expected = -(alpha * scratch[c, DV1, w] + alpha * alpha * scratch[c, DV2, w])
            warm = state[c, AFTER_WARM, w] == 1
            allowed = WARM_TRIALS if warm else LINE_SEARCH_STEPS
            last = state[c, ATTEMPT, w] >= allowed  # a warm tick may take its smallest step
            merit = scratch[c, MERIT, w]
            if np.isfinite(total) and (merit - total > ARMIJO * expected
                                       or warm and last and total <= WARM_COST_RATIO * merit):
                scratch[c, TAKES, w] = 1.0
                trials = state[c, ATTEMPT, w]
                if warm:
                    if state[c, MAX_ITER, w] == 1:
                        scratch[c, COST, w] = total
                        scratch[c, MU, w] = MU_MIN
                        state[c, ITERATION, w] = 1
                        state[c, ROLLOUTS, w] = trials
                        _finish(state, c, w, MAX_ITERATIONS)
                    else:
                        _start_iterations(scratch, state, c, w, total,
                                          state[c, MAX_ITER, w] - 1, 1, trials)
                    continue
                state[c, ROLLOUTS, w] += trials
                improvement = scratch[c, COST, w] - total
                scratch[c, COST, w] = total
                mu = scratch[c, MU, w]
                scratch[c, MU, w] = mu / 10.0 if mu > MU_MIN * 10.0 else MU_MIN
                state[c, PHASE, w] = SWEEP
                if improvement < scratch[c, TOLERANCE, w] * max(total, 1.0):
                    _finish(state, c, w, CONVERGED)
                continue
            if not last:
                scratch[c, ALPHA, w] = alpha * 0.5
                continue
            if warm:  # the warm step diverged: solve anew from the controls
                state[c, AFTER_WARM, w] = 0
                state[c, ROLLOUTS_OFFSET, w] = WARM_TRIALS
                _start_first_rollout(G, scratch, state, c, w, n)
                continue
            state[c, ROLLOUTS, w] += LINE_SEARCH_STEPS
            state[c, PHASE, w] = SWEEP
            _bump_mu(scratch, state, c, w)


@numba.njit(**JIT)
def _end(rows, Tc, G, state, scratch, n, r, c0, c1, width):
    """Each ticked joint's outcome into its row's header, and its next mode."""
    first = _at(0, r, n)
    for c in range(c0, c1):
        for w in range(width):
            status = state[c, STATUS, w]
            if status == PADDING:
                continue
            row = rows[c * width + w]
            row[ws.STATUS] = status
            row[ws.ITERATIONS] = state[c, ITERATION, w] + state[c, ITERATION_OFFSET, w]
            row[ws.COST] = scratch[c, COST, w]
            row[ws.MU] = scratch[c, MU, w]
            row[ws.ROLLOUTS] = state[c, ROLLOUTS, w] + state[c, ROLLOUTS_OFFSET, w]
            planned = Tc[c, first, U, w]
            row[ws.PLANNED_CURRENT] = planned
            row[ws.REFERENCE_POSITION] = G[c, first, REFERENCE_Q, w]
            row[ws.REFERENCE_VELOCITY] = G[c, first, REFERENCE_QD, w]
            usable = status == CONVERGED or status == MAX_ITERATIONS
            row[ws.MODE] = WARM if usable and np.isfinite(planned) else COLD


@numba.njit(**JIT)
def _simulates(scratch, state, c0, c1, width):
    """Mark the lanes that simulate this round; returns whether any does."""
    simulates = False
    for c in range(c0, c1):
        for w in range(width):
            phase = state[c, PHASE, w]
            lane = phase == FIRST_ROLLOUT or phase == SEARCH
            scratch[c, SIMULATES, w] = 1.0 if lane else 0.0
            simulates = simulates or lane
    return simulates


@numba.njit(**JIT)
def tick_chunk(rows, trajectories, gains, scratch, state, current, t0, n, c, width, effects):
    """Every joint of chunk c at time t0: rounds of one masked backward pass and one simulation
    until each joint's iLQR has ended (see the module docstring). A chunk's tick reads and
    writes only its own lanes, its row of `current` and its joints' rows: any thread may run
    it."""
    literally(width)  # a compile-time lane count: one compiled kernel per width
    literally(effects)
    r = current[c, RING] + 1  # every mode wants the stored steps moved up by one
    r = 0 if r > n else r
    current[c, RING] = r
    c1 = c + 1
    if _begin(rows, trajectories[current[c, WHICH]], gains, scratch, state, t0, n, r, c, c1,
              width):
        _shift(trajectories[current[c, WHICH]], gains, scratch, n, r, c, c1, width, effects)
    while True:
        cur = trajectories[current[c, WHICH]]
        swept = _before_sweep(scratch, state, c, c1, width)
        if swept:
            _backward(cur, gains, scratch, n, r, c, c1, width)
            _after_sweep(cur, gains, scratch, state, n, r, c, c1, width)
        simulates = _simulates(scratch, state, c, c1, width)
        if simulates:
            _rollout(cur, trajectories[1 - current[c, WHICH]], gains, scratch, n, r, c, c1,
                     width, effects)
            _after_rollout(gains, scratch, state, n, c, c1, width)
            _take(trajectories, scratch, current, n, rows.shape[0], c, width)
        if not swept and not simulates:
            break
    _end(rows, trajectories[current[c, WHICH]], gains, state, scratch, n, r, c, c1, width)


@intrinsic
def _fetch_add(typingctx, counters, i):
    """Item i of C-contiguous `counters` (counted through all its dimensions) += 1 as one
    atomic step (sequentially consistent), returning the value before."""
    if not (isinstance(counters, types.Array) and counters.dtype == types.int64
            and isinstance(i, types.Integer)):
        return None

    def codegen(context, builder, signature, args):
        array = context.make_array(signature.args[0])(context, builder, args[0])
        item = builder.gep(array.data, [args[1]])
        return builder.atomic_rmw("add", item, ir.Constant(ir.IntType(64), 1), "seq_cst")

    return types.int64(counters, i), codegen


@intrinsic
def _load(typingctx, counters, i):
    """Item i of C-contiguous `counters` read as one atomic step (acquire: what the writer did
    before its `_fetch_add` is seen after)."""
    if not (isinstance(counters, types.Array) and counters.dtype == types.int64
            and isinstance(i, types.Integer)):
        return None

    def codegen(context, builder, signature, args):
        array = context.make_array(signature.args[0])(context, builder, args[0])
        item = builder.gep(array.data, [args[1]])
        return builder.load_atomic(item, "acquire", 8)

    return types.int64(counters, i), codegen


_X86 = platform.machine().lower() in ("x86_64", "amd64", "i386", "i686")


@intrinsic
def _pause(typingctx):
    """The spin-wait hint (x86 PAUSE): a waiting loop yields the core's resources (nothing
    elsewhere)."""
    def codegen(context, builder, signature, args):
        if _X86:
            pause = cgutils.get_or_insert_function(
                builder.module, ir.FunctionType(ir.VoidType(), []), "llvm.x86.sse2.pause")
            builder.call(pause, [])
        return context.get_dummy_value()

    return types.void(), codegen


@numba.njit(**JIT)
def _tick_claimed(rows, trajectories, gains, scratch, state, current, claims, t0, n, effects,
                  thread, threads):
    """Tick every chunk no thread has taken yet, looking from this thread's own share of them
    (thread x count / threads on) round to the others'. When the threads start together each
    ticks its own share, the same chunks every tick (their data stays in that core's cache);
    a thread that starts late (woken late, or its core busy) finds part of its share taken by
    the others: no thread waits for a share that another has not begun. The calling thread
    then waits, spinning, for the chunks others are still ticking: at the region's end it
    would sleep (OpenMP's passive wait) and be woken 20-30 us after the last chunk ended
    (measured here, SCHED_RR); the spin lasts at most one chunk's tick, and the other threads
    sleep at once."""
    count = gains.shape[0]
    first = thread * count // threads
    for k in range(count):
        c = first + k
        c = c - count if c >= count else c
        if _fetch_add(current, c * CURRENT + TAKEN) != 0:
            continue  # another thread's
        if effects:
            tick_chunk(rows, trajectories, gains, scratch, state, current, t0, n, c, WIDTH, True)
        else:
            tick_chunk(rows, trajectories, gains, scratch, state, current, t0, n, c, WIDTH, False)
        _fetch_add(claims, TICKED)
    if numba.get_thread_id() == 0:
        while _load(claims, TICKED) < count:
            _pause()


@numba.njit(**JIT)
def _untaken(current, claims):
    """No chunk taken or ticked yet. Not written in the parallel kernels themselves: numba
    makes a slice assignment in a parallel function a parallel region of its own, and a
    region costs a wake-up and a join (40 us here)."""
    for c in range(current.shape[0]):
        current[c, TAKEN] = 0
    claims[TICKED] = 0


# The serial kernels, one compiled entry point per lane width and effects: numba compiles a
# function with all its branches, and every tick_chunk variant is the bulk of the compile
# (with the branches in one function a fresh install compiled all six variants, about 60 s of
# CPU here, before its first cycle; now a run compiles the one its joints need)


@numba.njit(**JIT)
def _tick_alone(rows, trajectories, gains, scratch, state, current, claims, t0, n, threads):
    """A joint alone: a chunk of one lane."""
    tick_chunk(rows, trajectories, gains, scratch, state, current, t0, n, 0, 1, False)


@numba.njit(**JIT)
def _tick_alone_effects(rows, trajectories, gains, scratch, state, current, claims, t0, n,
                        threads):
    tick_chunk(rows, trajectories, gains, scratch, state, current, t0, n, 0, 1, True)


@numba.njit(**JIT)
def _tick_serial(rows, trajectories, gains, scratch, state, current, claims, t0, n, threads):
    """Chunk after chunk, on this thread."""
    for c in range(gains.shape[0]):
        tick_chunk(rows, trajectories, gains, scratch, state, current, t0, n, c, WIDTH, False)


@numba.njit(**JIT)
def _tick_serial_effects(rows, trajectories, gains, scratch, state, current, claims, t0, n,
                         threads):
    for c in range(gains.shape[0]):
        tick_chunk(rows, trajectories, gains, scratch, state, current, t0, n, c, WIDTH, True)


@numba.njit(parallel=True, **JIT)
def _tick_parallel_plain(rows, trajectories, gains, scratch, state, current, claims, t0, n,
                         threads):
    """The chunks shared by up to `threads` threads (`_tick_claimed`)."""
    _untaken(current, claims)
    team = min(threads, gains.shape[0])
    for thread in numba.prange(team):
        _tick_claimed(rows, trajectories, gains, scratch, state, current, claims, t0, n, False,
                      thread, team)


@numba.njit(parallel=True, **JIT)
def _tick_parallel_effects(rows, trajectories, gains, scratch, state, current, claims, t0, n,
                           threads):
    _untaken(current, claims)
    team = min(threads, gains.shape[0])
    for thread in numba.prange(team):
        _tick_claimed(rows, trajectories, gains, scratch, state, current, claims, t0, n, True,
                      thread, team)


def tick_kernel(joints: int, effects: bool, threads: int):
    """The compiled tick for `joints` joints: `kernel(rows, *allocate(...), t0, n, threads)`
    steps every joint's MPC at time t0, chunk after chunk, on up to `threads` threads (one: no
    thread team is woken). `effects`: some joint's model carries an extra effect
    (`has_effects`). With more threads than one, each ticks its share of the chunks and then
    any other untaken one (`_tick_claimed`): one parallel region a tick, each thread running
    whole ticks of its chunks."""
    if joints == 1:
        return _tick_alone_effects if effects else _tick_alone
    if threads == 1 or chunks(joints) == 1:
        return _tick_serial_effects if effects else _tick_serial
    return _tick_parallel_effects if effects else _tick_parallel_plain
