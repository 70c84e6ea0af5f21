"""The virtual drives of one line advanced as a batch: one compiled call a cycle over the
line's joints (command, physics, sensors), where a Python cycle per drive cost about 10 us
each, a third of a millisecond for the whole TALOS.

One behaviour: `sim_bus.device.Cia402Device` stays the drive. Its plant's state, parameters
and noise draws live in rows of this line's arrays (`Plant.adopt`), the physics is the
model's own compiled step (`model.dynamics.step_sensed`, in a loop over the rows), and the
batch runs only a drive's steady cycles: whenever the device would do more than latch,
advance and sample (the controlword acts, the command trips, the joint leaves its window, a
quick stop is to finish, a fault is due, its terms changed), the batch leaves that drive's
cycle to `Cia402Device.cycle()` itself. What the batch repeats of the device (the command
in each mode, the saturation, the sensors' conversion) is checked against it, cycle for
cycle, in tests/test_line_physics.py.
"""

from collections.abc import Sequence

import numba
import numpy as np

from model import dynamics
from protocol import objects
from sim_bus.device import (
    COMMAND_CURRENT,
    COMMAND_TORQUE,
    LINE_KEYS,
    Cia402Device,
)
from sim_bus.plant import NOISE_BATCH
from sim_bus.sensing import (  # the float terms' columns: a row per drive, from line_terms
    CURRENT,
    DRY,
    DRY_LEVEL,
    JOINT_TORQUE,
    N_TERMS,
    POSITION,
    STATE_SIZE,
    T_DRIVE_GAIN,
    T_MAX_CURRENT,
    T_PERIOD,
    T_RATED_TORQUE,
    T_TRIP,
    T_WINDOW_HIGH,
    T_WINDOW_LOW,
    TIME,
    VELOCITY,
    sense,
)

# columns of the integer terms
I_KIND, I_BRAKED, I_FAULTED = range(3)
N_FLAGS = 3
N_OUTPUTS = 3  # the outputs a drive took: controlword, torque target, current target
# columns of the values a cycle leaves (`LINE_KEYS` order): echo, statusword, the readings
V_ECHO, V_STATUSWORD = 0, 1
V_READINGS = 2  # then LIVE_READINGS (`sim_bus.sensing` writes them)
N_VALUES = len(LINE_KEYS)
_MILLI = objects.MILLI
# drives whose noise draws a line renews a cycle at most: 2 of ~30 us each, so talos_32's 32
# drives, half their draws used (1 024 cycles before they run out), are renewed in 16 cycles
DRAWS_RENEWED = 2
# cycles between two looks at the draws used while no drive's were due: a look (numpy's max
# over the line's cursors) cost 5 us of a one-joint lock-step cycle's 80 here; 32 cycles use
# 64 of the 2 048 draws a drive has left when half are used
DRAWS_LOOK_EVERY = 32


# `advance_line`'s steady levels of a drive: its cycle is the physics alone while it applies
# no controlword (held outputs), or also with its controlword repeated (the state it is in is
# the one that controlword led to)
STEADY_HELD, STEADY = 1, 2
_NO_ROWS = np.zeros(0, dtype=np.bool_)


@numba.njit(cache=True, error_model="numpy")
def advance_line(rows: np.ndarray, controlwords: np.ndarray, torque_out: np.ndarray,
                 current_out: np.ndarray, counter: int, steady: np.ndarray,
                 controlword: np.ndarray, next_due: np.ndarray, cycles: np.ndarray,
                 terms: np.ndarray, flags: np.ndarray, ranges: np.ndarray,
                 torque_targets: np.ndarray, current_targets: np.ndarray,
                 state: np.ndarray, packed: np.ndarray, packed_braked: np.ndarray,
                 draws: np.ndarray, cursor: np.ndarray, values: np.ndarray,
                 applied: np.ndarray, outputs: np.ndarray, substeps: int, done: np.ndarray,
                 unwritten: np.ndarray, holding: np.ndarray) -> int:
    """One cycle of each drive in `rows`, as `Cia402Device.cycle()` runs it when nothing but
    the physics happens: the outputs taken (`controlwords`, and the targets where
    `torque_out` / `current_out` have a row per drive), the command latched in its mode and
    clamped at the drive's maximum, the plant advanced one period, the sensors sampled. A
    drive whose cycle has more to it (not `steady`, a new controlword, a fault due, its noise
    draws to renew, a command that trips, a joint leaving its window) is left untouched
    (False in `done`, a flag per row of `rows`): its device runs that cycle itself. `values`
    gets the readings, `applied` the current, `outputs` (controlword, torque target, current
    target) what the drive took, `unwritten` True for each drive that ran. Returns how many
    ran. `steady` per drive: STEADY_HELD (its cycle is the physics alone as long as no
    controlword is applied), STEADY (also with its controlword repeated), else 0; a drive
    `holding` (per drive; empty: none) is given the outputs it holds and applies none (an
    EtherCAT slave in SAFE-OP), so STEADY_HELD is enough for it. (Results in the caller's
    arrays, not a new one: boxing an array per call cost more than the cycle of a drive.)"""
    ran = 0
    for n in range(rows.shape[0]):
        done[n] = False
        j = rows[n]
        wanted = STEADY_HELD if holding.shape[0] and holding[j] else STEADY
        if (steady[j] < wanted or controlwords[j] != controlword[j]
                or next_due[j] <= cycles[j] + 1 or cursor[j] > NOISE_BATCH - 2):
            continue
        torque = torque_out[j] if torque_out.shape[0] else torque_targets[j]
        current_target = (current_out[j] / _MILLI if current_out.shape[0]
                          else current_targets[j])
        t = terms[j]
        kind = flags[j, I_KIND]
        if kind == COMMAND_CURRENT:
            command = current_target
        elif kind == COMMAND_TORQUE:
            command = torque / _MILLI * t[T_RATED_TORQUE] / t[T_DRIVE_GAIN]
        else:
            command = 0.0
        if abs(command) > t[T_TRIP]:
            continue
        limit = t[T_MAX_CURRENT]
        current = command if command < limit else limit  # max(-m, min(m, command))
        current = current if current > -limit else -limit
        q, qd, dry, level, joint = dynamics.step_sensed(
            state[j, POSITION], state[j, VELOCITY], current,
            packed_braked[j] if flags[j, I_BRAKED] else packed[j], packed[j], t[T_PERIOD],
            substeps)
        if not flags[j, I_FAULTED] and not t[T_WINDOW_LOW] <= q <= t[T_WINDOW_HIGH]:
            continue
        done[n] = True
        unwritten[j] = True
        ran += 1
        torque_targets[j], current_targets[j] = torque, current_target
        outputs[j, 0] = controlwords[j]
        if torque_out.shape[0]:
            outputs[j, 1] = torque_out[j]
        if current_out.shape[0]:
            outputs[j, 2] = current_out[j]
        cycles[j] += 1
        x = state[j]
        x[POSITION], x[VELOCITY], x[DRY], x[DRY_LEVEL], x[JOINT_TORQUE] = q, qd, dry, level, joint
        x[CURRENT] = current
        x[TIME] += t[T_PERIOD]
        applied[j] = current
        k = cursor[j]
        cursor[j] = k + 2
        values[j, V_ECHO] = counter
        sense(q, qd, current, joint, draws[j, k], draws[j, k + 1], t, ranges[j],
              values[j, V_READINGS:])
    return ran


@numba.njit(cache=True, nogil=True)
def pack_values(values: np.ndarray, fields: np.ndarray, out: np.ndarray) -> None:
    """Values of the line (`values`, a row per drive) into `out` (uint8), each
    little-endian at its place (`fields`, a row per value: drive row, value column, offset,
    size in bytes): a bus's TPDOs of its batch-cycled drives, as the drives' TPDOs carry
    them (`sim_bus.canopen_node`)."""
    for f in range(fields.shape[0]):
        value = values[fields[f, 0], fields[f, 1]]
        at = fields[f, 2]
        for b in range(fields[f, 3]):
            out[at + b] = (value >> (8 * b)) & 0xFF


_N_RANGES = len(LINE_KEYS) - 2  # the readings' ranges: per reading, low and high


def buffer_sizes(count: int, size: int) -> tuple[int, int]:
    """The lengths of a line's integer and float buffers (`line_blocks`) for `count` drives
    whose packed parameters have `size` values."""
    return (count * (4 + N_FLAGS + N_OUTPUTS + 2 * _N_RANGES + N_VALUES),
            count * (3 + N_TERMS + STATE_SIZE + 2 * size + NOISE_BATCH))


def line_blocks(ints: np.ndarray, reals: np.ndarray, count: int, size: int) -> tuple:
    """A line's arrays as C-contiguous views of its two buffers (`buffer_sizes`), cut in
    one place for Python (`DriveLine.__init__`) and the compiled cycle (`advance_blocks`),
    so that its call takes two arrays for seventeen (each array argument costs numba's
    dispatch about 55 ns): the integers' counts (controlword, next_due, cycles, cursor, a
    row each), flags, outputs (as taken), ranges, values; the floats' scalars (torque
    and current targets, applied current, a row each), terms, state, plant (packed
    parameters, free; braked), noise draws."""
    at = 4 * count
    counts = ints[:at].reshape((4, count))
    flags = ints[at:at + count * N_FLAGS].reshape((count, N_FLAGS))
    at += count * N_FLAGS
    outputs = ints[at:at + count * N_OUTPUTS].reshape((count, N_OUTPUTS))
    at += count * N_OUTPUTS
    ranges = ints[at:at + count * _N_RANGES * 2].reshape((count, _N_RANGES, 2))
    at += count * _N_RANGES * 2
    values = ints[at:at + count * N_VALUES].reshape((count, N_VALUES))
    at = 3 * count
    scalars = reals[:at].reshape((3, count))
    terms = reals[at:at + count * N_TERMS].reshape((count, N_TERMS))
    at += count * N_TERMS
    state = reals[at:at + count * STATE_SIZE].reshape((count, STATE_SIZE))
    at += count * STATE_SIZE
    plant = reals[at:at + 2 * count * size].reshape((2, count, size))
    at += 2 * count * size
    draws = reals[at:at + count * NOISE_BATCH].reshape((count, NOISE_BATCH))
    return counts, flags, outputs, ranges, values, scalars, terms, state, plant, draws


_compiled_blocks = numba.njit(cache=True)(line_blocks)


@numba.njit(cache=True, error_model="numpy")
def advance_blocks(rows: np.ndarray, controlwords: np.ndarray, torque_out: np.ndarray,
                   current_out: np.ndarray, counter: int, steady: np.ndarray,
                   ints: np.ndarray, reals: np.ndarray, size: int, substeps: int,
                   done: np.ndarray, unwritten: np.ndarray, fields: np.ndarray,
                   packed: np.ndarray) -> int:
    """`advance_line` on a `DriveLine`'s buffers (`line_blocks`, `size` the packed
    parameters'), then the values packed where `fields` says (`pack_values`; none: no
    rows): the one call a cycle makes from Python. Returns how many drives ran."""
    counts, flags, outputs, ranges, values, scalars, terms, state, plant, draws = (
        _compiled_blocks(ints, reals, steady.shape[0], size))
    ran = advance_line(rows, controlwords, torque_out, current_out, counter, steady,
                       counts[0], counts[1], counts[2], terms, flags, ranges, scalars[0],
                       scalars[1], state, plant[0], plant[1], draws, counts[3], values,
                       scalars[2], outputs, substeps, done, unwritten, _NO_ROWS)
    pack_values(values, fields, packed)
    return ran


_NONE = np.zeros(0, dtype=np.int64)  # an output the layout does not carry
_NO_FIELDS = np.zeros((0, 4), dtype=np.int64)  # no values to pack
_NO_BYTES = np.zeros(0, dtype=np.uint8)
_TORQUE_KEY = (objects.TARGET_TORQUE, 0)
_CURRENT_KEY = (objects.TARGET_CURRENT, 0)


class DriveLine:
    """The drives of one line; `cycle` runs a cycle of those given, in one compiled call for
    every steady one, and says which ran (the others' cycles are their devices' to run).

    What a batch cycle leaves in a device (its objects, cycle count, applied current,
    targets) is written back when anything next reads or changes that device (`flush`, from
    `Cia402Device._settle`), not every cycle: in a run nobody looks between two cycles."""

    def __init__(self, devices: Sequence[Cia402Device]):
        self.devices = list(devices)
        count = len(self.devices)
        size = self.devices[0].plant.parameters.packed().size if count else 0
        # the line's arrays: views of two buffers (`line_blocks`), the types
        # `advance_line` is compiled for
        self._buffers = tuple(np.zeros(n, dtype=dtype) for n, dtype in zip(
            buffer_sizes(count, size), (np.int64, np.float64), strict=True))
        # the outputs as taken: controlword, torque and current targets
        (counts, self.flags, self.outputs, self.ranges, self.values, scalars, self.terms,
         self.state, plant, self.draws) = line_blocks(*self._buffers, count, size)
        self._controlword, self._next_due, self._cycles, self.cursor = counts
        # per mille of rated torque, A, A
        self.torque_targets, self.current_targets, self.applied = scalars
        self.packed, self.packed_braked = plant
        for j, device in enumerate(self.devices):
            device.plant.adopt(self.state[j], self.packed[j], self.packed_braked[j],
                               self.draws[j], self.cursor[j:j + 1])
            device.join_line(self)
        # what decides, per drive, whether its next cycle is the batch's
        # terms steady (STEADY_HELD), and the controlword repeated (STEADY): `advance_line`
        self._steady = np.zeros(count, dtype=np.int8)
        self._drifting: list[int] = []
        # the devices' revisions the terms are from (-1: read them before the next cycle),
        # and whether any may have changed since (set by the devices and their plants)
        self._revisions = [-1] * count
        self.changed = True
        self._rows = np.arange(count)
        # drives whose last cycles ran here and are not written back yet; their output keys
        self.pending = False
        self._unwritten = np.zeros(count, dtype=np.bool_)
        self._output_keys: tuple = ()
        # the outputs a cycle was last given, and where its targets are in output_values
        self._outputs_given: tuple | None = None
        self._torque_at = self._current_at = -1
        self._done = np.zeros(count, dtype=np.bool_)
        self.ran = 0  # how many drives the last `cycle` ran
        self._renew_wait = 0  # calls of `renew_draws` before it looks at the draws again
        # the arrays each `advance_blocks` call takes, gathered once (attribute look-ups a
        # cycle otherwise): the line's own, never replaced
        self._kernel = (self._steady, *self._buffers, size)

    def __len__(self) -> int:
        return len(self.devices)

    def renew_draws(self, most: int = DRAWS_RENEWED) -> int:
        """Renew the noise draws of at most `most` drives that have used half of theirs, the
        most used first (`Plant.refill_draws`, the sequence unchanged). A line's drives use
        theirs up together, and the cycle that emptied them renewed every one: on talos_32
        one frame in 2 048 took 3 ms to answer (the drives' cycles out of the batch), which
        the master saw as a late sample. Called once a cycle, off the answer's path where the
        caller has one, this spreads that work over the cycles before. How many renewed."""
        if self._renew_wait:
            self._renew_wait -= 1
            return 0
        cursor = self.cursor
        if not cursor.size or cursor.max() < NOISE_BATCH // 2:
            self._renew_wait = DRAWS_LOOK_EVERY - 1
            return 0
        rows = np.flatnonzero(cursor >= NOISE_BATCH // 2)
        rows = rows[np.argsort(-cursor[rows], kind="stable")][:most]
        for j in rows.tolist():
            self.devices[j].plant.refill_draws()
        return len(rows)

    def flush(self) -> None:
        """Write what the batch's cycles left into the devices they ran for."""
        self.pending = False
        rows = np.flatnonzero(self._unwritten)
        self._unwritten[:] = False
        keys = LINE_KEYS + self._output_keys
        columns = [0] + [1 + (key == _CURRENT_KEY) for key in self._output_keys[1:]]
        written = np.concatenate((self.values[rows], self.outputs[rows][:, columns]),
                                 axis=1).tolist()
        cycles, applied = self._cycles[rows].tolist(), self.applied[rows].tolist()
        current = self.current_targets[rows].tolist()
        torque = self.torque_targets[rows].astype(np.int64).tolist()
        for n, j in enumerate(rows.tolist()):
            self.devices[j].cycled_by_line(keys, written[n], cycles[n], applied[n],
                                           current[n], torque[n])

    def _read_terms(self, j: int) -> None:
        device = self.devices[j]
        terms = device.line_terms()
        plant = device.plant
        self._steady[j] = (STEADY if terms.commanded else STEADY_HELD) if terms.steady else 0
        self._controlword[j] = terms.controlword
        self._next_due[j] = terms.next_due
        self._cycles[j] = terms.cycle_count
        low, high = terms.window
        self.terms[j] = (terms.period, terms.max_current, terms.trip_current, low, high,
                         terms.increments_per_rad, terms.rated_current, terms.rated_torque,
                         terms.drive_gain, plant.parameters.torque_sensor_gain,
                         plant.noise.current, plant.noise.joint_torque)
        self.flags[j] = (terms.kind, terms.braked, terms.faulted)
        self.ranges[j] = terms.ranges
        self.values[j, V_STATUSWORD] = terms.statusword
        self.values[j, V_READINGS:] = terms.readings
        self.torque_targets[j] = terms.target_torque_permille
        self.current_targets[j] = terms.target_current
        if plant.drifts and j not in self._drifting:
            self._drifting.append(j)
        elif not plant.drifts and j in self._drifting:
            self._drifting.remove(j)

    def refresh(self) -> bool:
        """Read again the terms of every drive that changed (or may have been cycled
        elsewhere) since they were read; whether any had."""
        if not self.changed:
            return False
        self.changed = False
        revisions = [d.revision + d.plant.revision for d in self.devices]
        if revisions == self._revisions:
            return False
        for j, (now, then) in enumerate(zip(revisions, self._revisions, strict=True)):
            if now != then:
                self._read_terms(j)
        # reading them settled the devices, whose revisions stay as they were
        self._revisions = revisions
        return True

    def cycle(self, rows: np.ndarray, controlwords: np.ndarray, outputs: tuple,
              output_values: list, counter: int = 0, refresh: bool = True,
              others_idle: bool = False, fields: np.ndarray = _NO_FIELDS,
              packed: np.ndarray = _NO_BYTES) -> np.ndarray:
        """One cycle of the drives `rows` (indices, in line order) under these outputs, a
        row per drive of the line: `controlwords` and, for the objects `outputs` other than
        the controlword (target torque and current), `output_values`. The rows whose cycle
        ran here (bool over `rows`, the line's own array: valid until its next cycle); every
        drive not among them may have been cycled
        another way, so its terms are read again before its next. `refresh` False: the
        caller has just called `refresh`. `others_idle`: the caller knows the drives not in
        `rows` did not cycle (a SYNC0 batch of part of the line), so only those of `rows`
        not run here are read again. How many ran: `ran`. `fields`, `packed`: the values
        packed after the cycle, in the same compiled call (`pack_values`)."""
        if refresh and self.changed:
            self.refresh()
        devices = self.devices
        self.prepare(outputs)
        count = len(rows)
        done = self._done if count == len(devices) else self._done[:count]
        ran = self.ran = advance_blocks(
            rows, controlwords,
            output_values[self._torque_at] if self._torque_at >= 0 else _NONE,
            output_values[self._current_at] if self._current_at >= 0 else _NONE,
            counter, *self._kernel, dynamics.SUBSTEPS, done, self._unwritten, fields, packed)
        if ran == len(devices):
            return done
        if others_idle:
            if ran < count:
                self.cycled_elsewhere(rows[~done].tolist())
        else:  # the others may run elsewhere: read them again
            self.cycled_elsewhere(np.setdiff1d(self._rows, rows[done],
                                               assume_unique=True).tolist())
        return done

    def prepare(self, outputs: tuple) -> tuple[int, int]:
        """Before a cycle of the drives under outputs of the objects `outputs` (run by
        `cycle`, or by a caller's compiled code through `advance_line`): the drifting
        plants' parameters renewed, the output keys taken (what the devices were last given
        written back first when they change), the line marked as holding results to write
        back. Where target torque and current are among the targets (-1: not carried)."""
        for j in self._drifting:
            self.devices[j].plant.renew_parameters()
        if outputs is not self._outputs_given:
            if outputs != self._output_keys:
                if self.pending:
                    self.flush()
                self._output_keys = outputs
            self._outputs_given = outputs
            targets = outputs[1:]
            self._torque_at = targets.index(_TORQUE_KEY) if _TORQUE_KEY in targets else -1
            self._current_at = targets.index(_CURRENT_KEY) if _CURRENT_KEY in targets else -1
        self.pending = True
        return self._torque_at, self._current_at

    def kernel_arrays(self) -> tuple:
        """The line's arrays `advance_line` takes after `counter`, up to `done` (exclusive),
        for compiled code of a caller that runs the cycle inside its own (a segment's SYNC0
        pass): steady, controlword, next_due, cycles, terms, flags, ranges, torque and
        current targets, state, packed, packed_braked, draws, cursor, values, applied,
        outputs; then `unwritten` is the last argument."""
        return (self._steady, self._controlword, self._next_due, self._cycles, self.terms,
                self.flags, self.ranges, self.torque_targets, self.current_targets, self.state,
                self.packed, self.packed_braked, self.draws, self.cursor, self.values,
                self.applied, self.outputs)

    def held_outputs(self, rows: np.ndarray, outputs: tuple) -> tuple[np.ndarray, list]:
        """The outputs the drives `rows` hold (their last controlword and targets), as
        `cycle` takes them for the objects `outputs`: a cycle under these is the cycle of a
        drive that got no new outputs (a SYNC0 whose window had none)."""
        targets = []
        for key in outputs[1:]:
            if key == _CURRENT_KEY:
                targets.append(np.rint(self.current_targets[rows] * _MILLI).astype(np.int64))
            else:
                targets.append(self.torque_targets[rows].astype(np.int64))
        return self._controlword[rows], targets

    def load_kernel(self) -> None:
        """Compile (a first run) or load (from the cache) the batch's kernel now, with a
        cycle of no drive: numba does it at the first call, which would otherwise be a first
        cycle in OP (0.1 s from the cache, longer than a master waits for its frame; seconds
        when it compiles)."""
        count = len(self.devices)
        self.cycle(np.zeros(0, dtype=np.int64), np.zeros(count, dtype=np.int64),
                   ((objects.CONTROLWORD, 0), _TORQUE_KEY), [np.zeros(count, dtype=np.int64)])

    def cycled_elsewhere(self, rows: Sequence[int]) -> None:
        """The drives `rows` may have run cycles of their own (`Cia402Device.cycle()`, which
        the line is not told of): their terms are read again before their next batch
        cycle."""
        revisions = self._revisions
        for j in rows:
            revisions[j] = -1
        self.changed = True

def compile_ahead() -> None:
    """Compile the batch's kernel now (`DriveLine.load_kernel` on a line of one virtual
    drive): `actuatord --sim` calls it inside the first run's notice, before any drive is
    enabled; a first run's compile was otherwise the loop's first cycle (12 s at load 7)."""
    from model.parameters import Payload, load_model
    from sim_bus.embedded import make_device
    from sim_bus.plant import SensorNoise

    DriveLine([make_device(load_model(), Payload(), SensorNoise())]).load_kernel()
