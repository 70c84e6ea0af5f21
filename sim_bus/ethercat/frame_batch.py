"""A line's cyclic process data frame passed as a batch: the part of a frame that is every
steady slave's outputs in and inputs out, done for all of them at once.

Passing a frame slave by slave costs about 25 us a slave in Python (the ESC's FMMU copies,
the firmware's decode, the drive's cycle, the encode), most of a millisecond for the whole
TALOS; the slave process then cannot keep up with a 1 kHz master. Here, for the logical
datagrams (LRW/LRD/LWR) of a frame, every slave whose cycle is steady (`SlaveFirmware.
steady_keys`: in OP, no transition pending, not on SYNC0; or `safe_op_keys`: in SAFE-OP,
where the drive cycles on what it holds and the outputs are ignored) and whose FMMUs map exactly its
output and input sync manager buffers has its outputs gathered out of the frame at once
(numpy fancy indexing over the frame buffer), its drive cycled in one compiled call
(`sim_bus.line_physics.DriveLine`), its inputs scattered into the frame at once and its
share of the working counter added; its buffers, watchdog, and cycle count are left as the
ESC and firmware leave them. Everything else (other datagrams, slaves not steady, a drive
whose cycle has more to it than the physics) takes the ESC's own path, in line order.

In the steady state a frame costs no Python per slave: the free-run cycle of the batched
slaves is one compiled call over the frame's bytes (`frame_pass`), and once a plain frame (every
slave batched, nothing else in it) went through the per-slave bookkeeping, the next ones leave
it (watchdog deadline, the ESC's time, the firmware's cycle count) in the batch's arrays until
anything looks at the slaves (`FrameBatch.settle`). A frame of broadcast register reads (the
master's AL status check) is passed at once too (`FrameBatch.registers`), and a master's CoE
traffic beside the cycle leaves the plans as they are.

Same result as slave by slave (tests/test_segment_batch.py compares frames and devices),
given what the batch checks: the batched slaves' logical areas overlap no other slave's and
lie whole in one datagram each; the frame's other datagrams only read registers or write the
distributed clock's times, which a steady cycle neither reads nor changes, so their order
against the cycle does not matter. Any other frame goes slave by slave, and the plan is
made again before the next.
"""

import math
from collections.abc import Sequence
from operator import attrgetter

import numba
import numpy as np
from numba.typed import List

from model import dynamics
from protocol import ethercat as ec
from protocol import objects
from protocol.dictionary import mappable_object
from protocol.pdo import PdoLayout
from sim_bus.device import LINE_KEYS
from sim_bus.ethercat import dc
from sim_bus.ethercat.esc import Esc
from sim_bus.ethercat.firmware import (
    FREE_SYNC0,
    SYNC_ERROR_WEIGHT,
    LineSync,
    SlaveFirmware,
    missed_windows,
)
from sim_bus.line_physics import DriveLine, advance_line

_LOGICAL = frozenset((ec.Command.LRD, ec.Command.LWR, ec.Command.LRW))
_READS = frozenset((ec.Command.APRD, ec.Command.FPRD, ec.Command.BRD))
_MAILBOX_WRITES = frozenset((ec.Command.APWR, ec.Command.FPWR, ec.Command.BWR))
_WRITES_OUTPUTS = frozenset((ec.Command.LWR, ec.Command.LRW))
_READS_INPUTS = frozenset((ec.Command.LRD, ec.Command.LRW))
# registers a steady cycle changes (the process data watchdog's status): a frame reading them
# goes slave by slave, so the read sees them before or after the cycle as it would
_WATCHDOG_REGISTERS = (ec.REG_WATCHDOG_DIVIDER, ec.REG_WATCHDOG_COUNTER_PROCESS_DATA + 2)
# what other datagrams may write beside a batch: the distributed clock's times (an FRMW of
# the reference clock's system time rides in every cyclic frame of a DC master)
_CLOCK_TIMES = (dc.REG_RECEIVE_TIME_PORT0, dc.REG_SPEED_COUNTER_START)
_TORQUE, _CURRENT = (objects.TARGET_TORQUE, 0), (objects.TARGET_CURRENT, 0)
_TARGETS = frozenset((_TORQUE, _CURRENT))
_CONTROLWORD = (objects.CONTROLWORD, 0)
# AL status of a slave steady on SYNC0 that a window without outputs leaves as it was: in OP,
# or in SAFE-OP waiting to enter OP (no error indicator: a slave that just lost its sync has it)
_WAITING = frozenset((ec.AlState.OP, ec.AlState.SAFE_OP))


@numba.njit(cache=True)
def into_buffers(rows: np.ndarray, memories, starts: np.ndarray, outputs: np.ndarray,
                 inputs: np.ndarray) -> None:
    """Each batched slave's outputs into its SM2 buffer and inputs into its SM3 buffer (what
    the master's write and the firmware's sample leave there), a row of each image per
    slave."""
    out_size, in_size = outputs.shape[1], inputs.shape[1]
    for k in rows:
        memory = memories[k]
        memory[starts[k, 0]:starts[k, 0] + out_size] = outputs[k]
        memory[starts[k, 1]:starts[k, 1] + in_size] = inputs[k]


@numba.njit(cache=True)
def from_buffers(rows: np.ndarray, memories, starts: np.ndarray, which: int,
                 size: int) -> np.ndarray:
    """Row n: `size` bytes of slave rows[n]'s memory from starts[rows[n], which] (0: its SM2
    buffer, the outputs the last frame left; 1: its SM3 buffer, the inputs last sampled)."""
    out = np.empty((rows.shape[0], size), dtype=np.uint8)
    for n in range(rows.shape[0]):
        k = rows[n]
        start = starts[k, which]
        out[n] = memories[k][start:start + size]
    return out


# what the SYNC0 pass (`sync0_pass`) did with each slave whose SYNC0 it took
RAN = 1  # its window's bookkeeping and its drive's cycle, inputs in SM3
FRESH_LEFT = 2  # the bookkeeping; its firmware runs the cycle, on the window's outputs
HELD_LEFT = 3  # the bookkeeping; its firmware runs the cycle, on what its drive holds
LOST = 4  # the bookkeeping found its sync lost: its firmware drops it out of OP
ELSEWHERE = 5  # not steady in OP on SYNC0: its firmware does the bookkeeping too
_OP = int(ec.AlState.OP)
_NONE = np.zeros(0, dtype=np.int64)  # an output the layout does not carry
_NO_HOLDING = np.zeros(0, dtype=np.bool_)  # SYNC0: every slave in the pass applies its outputs
_MILLI = objects.MILLI
_OUTBOX = attrgetter("_outbox")  # a firmware's mailbox messages waiting for the master


@numba.njit(cache=True)
def _field(memory: np.ndarray, at: int, size: int, signed: bool) -> int:
    """A little-endian integer of `size` bytes at `at`."""
    value = 0
    for b in range(size):
        value |= np.int64(memory[at + b]) << (8 * b)
    if signed and value >= 1 << (8 * size - 1):
        value -= 1 << (8 * size)
    return value


@numba.njit(cache=True)
def sync0_pass(now, present, steady_dc, memories, starts, local_at_zero, drift, correction,
               slew, anchor, next_sync0, armed, next_host, sync0_count, fresh, errors, since,
               last_sync0, missed, limits, excused_until, out_fields, in_fields,
               torque_field, current_field, controlwords, torque_out, current_out, encoded,
               line_arrays, substeps, cycle_rows, done, unwritten, due_rows, due_times,
               kinds) -> int:
    """A SYNC0 pass of the whole line in one call: what `LineClocks.take_due`,
    `LineSync.sync0_in_op`, the decode of the SM2 buffers (or the outputs the drives hold),
    `DriveLine.cycle` and the encode of the inputs into SM3 do for every slave steady in OP
    on SYNC0, in the same arithmetic, so the same results. Each present slave's SYNC0 due by
    `now` is taken, its pulses since the last look as one event at the last of them
    (`sim_bus.ethercat.dc`; its host time first worked out where a register write cleared it, for
    every armed clock as `LineClocks.upcoming` does); the due rows and their times go into
    `due_rows`/`due_times`, what became of each into `kinds` (RAN ... ELSEWHERE). Returns
    how many were due. `out_fields` (offset, size, signed) and `in_fields` (offset, size,
    column of the line's values) describe the PDOs; `torque_field`/`current_field` are the
    output fields of the targets (-1: not carried)."""
    (steady, line_controlword, next_due, cycles, terms, flags, ranges, torque_targets,
     current_targets, state, packed, packed_braked, draws, cursor, values, applied,
     outputs) = line_arrays
    count = present.shape[0]
    due = 0
    cycling = 0
    for k in range(count):
        kinds[k] = 0
        if not armed[k]:
            continue
        memory = memories[k]
        if np.isnan(next_host[k]):  # `DistributedClock.host_time_of` at `now`
            offset = np.uint64(0)
            for b in range(8):
                offset |= np.uint64(memory[dc.REG_SYSTEM_TIME_OFFSET + b]) << np.uint64(8 * b)
            local = np.uint64(np.int64(local_at_zero[k] + now * 1e9 * (1.0 + drift[k])
                                       + correction[k] + (now - anchor[k]) * 1e9 * slew[k]))
            ahead = np.int64(next_sync0[k] - (local + offset))
            next_host[k] = now + ahead * 1e-9 / (1.0 + drift[k] + slew[k])
        at = next_host[k]
        if not present[k] or not at <= now:
            continue
        cycle = np.uint32(0)
        for b in range(4):
            cycle |= np.uint32(memory[dc.REG_SYNC0_CYCLE_TIME + b]) << np.uint32(8 * b)
        # the pulses since the last look latched into one event, at the last of them
        # (`LineClocks.take_due`)
        step = cycle * 1e-9 / (1.0 + drift[k] + slew[k])
        late = np.int64(np.floor((now - at) / step)) if step > 0 else np.int64(0)
        at = at + late * step
        next_sync0[k] += np.uint64(cycle) * np.uint64(late + 1)
        next_host[k] = at + step
        sync0_count[k] += late + 1
        memory[dc.REG_SYNC0_STATUS] = 1
        due_rows[due], due_times[due] = k, at
        due += 1
        kinds[k] = ELSEWHERE
        if not steady_dc[k] or memory[ec.REG_AL_STATUS] != _OP:
            continue
        # the window's bookkeeping (`SlaveFirmware.sync0_window` in OP)
        last_sync0[k] = at
        got = fresh[k]
        fresh[k] = False
        since_before = since[k]
        since[k] += 1
        if not got:
            missed[k] += 1
            if since_before > FREE_SYNC0 and at > excused_until:
                # `LineSync.sync0_in_op`: SSC's count against 0x10F1:02 (0: no check)
                if errors[k] <= limits[k]:
                    errors[k] += SYNC_ERROR_WEIGHT
                if limits[k] != 0 and errors[k] >= limits[k]:
                    kinds[k] = LOST
                    continue
        # the outputs the cycle takes: the window's (SM2) or those the drive holds
        if got:
            start = starts[k, 0]
            controlwords[k] = _field(memory, start + out_fields[0, 0], out_fields[0, 1],
                                     out_fields[0, 2] != 0)
            if torque_field >= 0:
                torque_out[k] = _field(memory, start + out_fields[torque_field, 0],
                                       out_fields[torque_field, 1],
                                       out_fields[torque_field, 2] != 0)
            if current_field >= 0:
                current_out[k] = _field(memory, start + out_fields[current_field, 0],
                                        out_fields[current_field, 1],
                                        out_fields[current_field, 2] != 0)
            kinds[k] = FRESH_LEFT
        else:
            controlwords[k] = line_controlword[k]
            if torque_field >= 0:
                torque_out[k] = np.int64(torque_targets[k])
            if current_field >= 0:
                current_out[k] = np.int64(np.rint(current_targets[k] * _MILLI))
            kinds[k] = HELD_LEFT
        cycle_rows[cycling] = k
        cycling += 1
    if cycling:
        advance_line(cycle_rows[:cycling], controlwords, torque_out, current_out, 0, steady,
                     line_controlword, next_due, cycles, terms, flags, ranges, torque_targets,
                     current_targets, state, packed, packed_braked, draws, cursor, values,
                     applied, outputs, substeps, done, unwritten, _NO_HOLDING)
        for n in range(cycling):
            if not done[n]:
                continue
            k = cycle_rows[n]
            kinds[k] = RAN
            memory = memories[k]
            start = starts[k, 1]
            for f in range(in_fields.shape[0]):
                at_, size, value = in_fields[f, 0], in_fields[f, 1], values[k, in_fields[f, 2]]
                for b in range(size):
                    byte = (value >> (8 * b)) & 0xFF
                    encoded[k, at_ + b] = byte
                    memory[start + at_ + b] = byte
    return due


@numba.njit(cache=True)
def frame_pass(buffer, rows, out_at, in_at, holding, memories, starts, out_fields, in_fields,
               torque_field, current_field, controlwords, torque_out, current_out, encoded,
               line_arrays, substeps, done, unwritten) -> int:
    """Free run: the cycle of the batched slaves `rows` on a frame in one call, what the
    decode of their outputs at `out_at` in the frame `buffer`, `DriveLine.cycle` (through
    `advance_line`), the encode of the inputs and the copies into the frame (at `in_at`)
    and into the SM2/SM3 buffers do, in the same arithmetic as `sync0_pass`. A slave
    `holding` (by line row: in SAFE-OP) cycles on the outputs its drive holds, as
    `sync0_pass` does for a window without outputs: an ESC in SAFE-OP takes the outputs into
    SM2 and the application ignores them. `done` gets,
    per row, whether its drive ran here (the others are left as they were: their ESC
    passes the frame). Returns how many ran. (As a dozen small numpy operations and two
    compiled calls this cost some 40 us for talos' 32 slaves, most of the frame.)"""
    (steady, line_controlword, next_due, cycles, terms, flags, ranges, torque_targets,
     current_targets, state, packed, packed_braked, draws, cursor, values, applied,
     outputs) = line_arrays
    for n in range(rows.shape[0]):
        k, at = rows[n], out_at[n]
        if holding[k]:
            controlwords[k] = line_controlword[k]
            if torque_field >= 0:
                torque_out[k] = np.int64(torque_targets[k])
            if current_field >= 0:
                current_out[k] = np.int64(np.rint(current_targets[k] * _MILLI))
            continue
        controlwords[k] = _field(buffer, at + out_fields[0, 0], out_fields[0, 1],
                                 out_fields[0, 2] != 0)
        if torque_field >= 0:
            torque_out[k] = _field(buffer, at + out_fields[torque_field, 0],
                                   out_fields[torque_field, 1], out_fields[torque_field, 2] != 0)
        if current_field >= 0:
            current_out[k] = _field(buffer, at + out_fields[current_field, 0],
                                    out_fields[current_field, 1],
                                    out_fields[current_field, 2] != 0)
    ran = advance_line(rows, controlwords, torque_out, current_out, 0, steady,
                       line_controlword, next_due, cycles, terms, flags, ranges,
                       torque_targets, current_targets, state, packed, packed_braked, draws,
                       cursor, values, applied, outputs, substeps, done, unwritten, holding)
    out_size = 0
    for f in range(out_fields.shape[0]):
        out_size = max(out_size, out_fields[f, 0] + out_fields[f, 1])
    for n in range(rows.shape[0]):
        if not done[n]:
            continue
        k = rows[n]
        memory = memories[k]
        # the outputs into SM2 before the inputs into the frame (a slave's two areas may
        # overlap in the logical image)
        memory[starts[k, 0]:starts[k, 0] + out_size] = buffer[out_at[n]:out_at[n] + out_size]
        start = starts[k, 1]
        for f in range(in_fields.shape[0]):
            at_, size, value = in_fields[f, 0], in_fields[f, 1], values[k, in_fields[f, 2]]
            for b in range(size):
                byte = (value >> (8 * b)) & 0xFF
                encoded[k, at_ + b] = byte
                memory[start + at_ + b] = byte
                buffer[in_at[n] + at_ + b] = byte
    return ran


def batchable_keys(out_keys: Sequence[tuple[int, int]],
                   in_keys: Sequence[tuple[int, int]]) -> bool:
    """Whether a layout is one the line's batch can cycle: the controlword first, then
    target torque and/or current, inputs among the drive's live objects (`LINE_KEYS`)."""
    return (bool(out_keys) and bool(in_keys) and out_keys[0] == _CONTROLWORD
            and set(out_keys[1:]) <= _TARGETS and len(set(out_keys)) == len(out_keys)
            and set(in_keys) <= set(LINE_KEYS))


def _pdo_fields(out_layout: PdoLayout, in_layout: PdoLayout,
                keys: tuple) -> tuple[np.ndarray, np.ndarray, int, int]:
    """What `sync0_pass` decodes and encodes with: the output fields' (offset, size,
    signed), the input fields' (offset, size, column in `LINE_KEYS`), and the output fields
    of target torque and current (-1: not carried)."""
    def offsets(layout: PdoLayout) -> list[int]:
        sizes = [o.bits // 8 for o in layout.objects]
        return [sum(sizes[:n]) for n in range(len(sizes))]

    out_fields = np.array([(at, o.bits // 8, o.signed) for at, o in
                           zip(offsets(out_layout), out_layout.objects, strict=True)],
                          dtype=np.int64)
    in_fields = np.array([(at, o.bits // 8, LINE_KEYS.index((o.index, o.subindex)))
                          for at, o in zip(offsets(in_layout), in_layout.objects, strict=True)],
                         dtype=np.int64)
    out_keys = list(keys[0])
    return (out_fields, in_fields,
            out_keys.index(_TORQUE) if _TORQUE in out_keys else -1,
            out_keys.index(_CURRENT) if _CURRENT in out_keys else -1)


class InputEncoder:
    """The drives' inputs as a packed process image, a row per slave, from the line's
    values (`DriveLine.values`, columns in `LINE_KEYS` order)."""

    def __init__(self, layout: PdoLayout, count: int):
        self.image = np.zeros(count, layout.dtype)
        self._fields = [(f"f{k}", LINE_KEYS.index((o.index, o.subindex)))
                        for k, o in enumerate(layout.objects)]
        self.bytes = self.image.view(np.uint8).reshape(count, layout.size)

    def encode(self, values: np.ndarray, rows: np.ndarray | None) -> None:
        """Rows `rows` (None: all) of the image from `values` (same rows)."""
        image = self.image
        for field, column in self._fields:
            if rows is None:
                image[field] = values[:, column]
            else:
                image[field][rows] = values[rows, column]


class _Plan:
    """Which slaves a frame of this layout batches, and where their data lie in it."""

    def __init__(self, rows: np.ndarray, out_index: np.ndarray, in_index: np.ndarray,
                 wkc: np.ndarray, wkc_offsets: list[int], others: list, watchdogs: list[bool]):
        self.rows = rows  # line positions of the batched slaves
        self.out_index = out_index  # (batched, out size) frame offsets of their outputs
        self.in_index = in_index  # (batched, in size) frame offsets of their inputs
        self.wkc = wkc  # (batched, logical datagrams) each one's working counter share
        self.wkc_offsets = wkc_offsets  # the logical datagrams' working counters
        self.others = others  # per slave: the spans the ESC still passes (None: all)
        self.watchdogs = watchdogs  # per slave: batched, and its outputs retrigger it
        # the slaves that take the reference clock's time at once, and where it lies
        self.clock_rows = np.zeros(0, dtype=np.int64)
        self.clock_span = (0, 0)
        # every slave batched with nothing else of the frame to pass: once a frame of this
        # plan went through the per-slave loop (`primed`: every watchdog status bit set),
        # the next ones leave the per-slave part to `FrameBatch.settle`
        self.plain = all(rest == [] for rest in others)
        self.primed = False
        self.wkc_sums = wkc.sum(axis=0).tolist()  # the working counters, every slave done
        self.on_sync0 = np.zeros(len(rows), dtype=bool)  # each on SYNC0 (`FrameBatch._plan`)
        self.free_run = True
        self.out_at = out_index[:, 0].copy() if len(rows) else rows  # where each one's lie
        self.in_at = in_index[:, 0].copy() if len(rows) else rows


class FrameBatch:
    """The batch of one segment's slaves (`escs`, `firmwares`, `line` in line order, their
    distributed clocks joined in `clocks`, their SYNC0 bookkeeping in `sync`)."""

    def __init__(self, escs: Sequence[Esc], firmwares: Sequence[SlaveFirmware],
                 line: DriveLine, clocks: dc.LineClocks, sync: LineSync):
        self.escs, self.firmwares, self.line = list(escs), list(firmwares), line
        self.clocks, self.sync = clocks, sync
        count = len(self.escs)
        self.stale = True  # the slaves may have changed: find which are steady again
        # their registers may have changed (FMMUs, sync managers): the frame plans too
        self._replan = True
        # their drives may have run cycles the line was not told of: read them again
        self._drives_unknown = True
        self._steady = np.zeros(count, dtype=bool)
        self._dc = np.zeros(count, dtype=bool)  # steady on SYNC0 (else on the frame)
        # steady in SAFE-OP (free run): cycles on the frame, its outputs ignored
        self._holding = np.zeros(count, dtype=bool)
        self._keys: tuple | None = None
        self._layouts: tuple[PdoLayout, PdoLayout] | None = None
        self._encoder: InputEncoder | None = None
        # the PDOs as `sync0_pass` takes them (none until a layout is found)
        self._fields = (np.zeros((0, 3), dtype=np.int64), np.zeros((0, 3), dtype=np.int64),
                        -1, -1)
        self._no_inputs = np.zeros((count, 0), dtype=np.uint8)
        self._line_arrays = line.kernel_arrays()
        self._scratch = {name: np.zeros(count, dtype=dtype) for name, dtype in (
            ("controlwords", np.int64), ("torque", np.int64), ("current", np.int64),
            ("cycle_rows", np.int64), ("done", np.bool_), ("due_rows", np.int64),
            ("due_times", np.float64), ("kinds", np.int64))}
        self._plans: dict = {}  # frame layout -> _Plan (or None: not batched)
        self._memories = List([np.frombuffer(esc.memory, np.uint8) for esc in self.escs])
        self._starts = np.zeros((count, 2), dtype=np.int64)
        self.batched = 0  # slave cycles the batch ran (the rest ran through their ESCs)
        # what plain frames (`_Plan.plain`) left unwritten in the ESCs and firmwares: the
        # last one's time and plan (their watchdog deadlines, their `now`) and each
        # firmware's cycles since; `settle` writes them
        self._fed_at: float | None = None
        self._fed_plan: _Plan | None = None
        self._uncounted = np.zeros(count, dtype=np.int64)
        self._warm()

    def _warm(self) -> None:
        """Load the compiled code now, not in the first frame in OP or the first SYNC0:
        loading it takes about 0.1 s, longer than a master waits for its frame (the SYNC0
        pass loaded at the first SYNC0 cost the slaves their first windows: a sync error
        before OP)."""
        count, none = len(self.escs), np.zeros(0, dtype=np.int64)
        if not count:
            return
        self.line.load_kernel()
        self._pass(-math.inf, np.zeros(count, dtype=bool))  # no SYNC0 is due before all time
        # a frame's free-run cycle of no slave (the first frame in OP waited seconds for its
        # compile: the master had given the line up after 100 ms)
        out_fields, in_fields, _, _ = self._fields
        scratch = self._scratch
        frame_pass(np.zeros(0, dtype=np.uint8), none, none, none, self._holding,
                   self._memories, self._starts,
                   out_fields, in_fields, -1, -1, scratch["controlwords"], _NONE, _NONE,
                   self._no_inputs, self._line_arrays, dynamics.SUBSTEPS, scratch["done"],
                   self.line._unwritten)
        empty = np.zeros((count, 1), dtype=np.uint8)
        into_buffers(none, self._memories, self._starts, empty, empty)
        from_buffers(none, self._memories, self._starts, 0, 1)

    # --- the plan --------------------------------------------------------------------------

    def _find_steady(self) -> None:
        """Which slaves are steady with one common batchable layout and plain FMMUs; the
        frame plans are kept while that stays as it was and nothing else changed."""
        before = self._steady.copy(), self._dc.copy()
        self._steady[:] = self._dc[:] = self._holding[:] = False
        self._find_steady_into()
        if self._replan or not (np.array_equal(before[0], self._steady)
                              and np.array_equal(before[1], self._dc)):
            self._plans.clear()
        self.stale = self._replan = False

    def _find_steady_into(self) -> None:
        keys = [(firmware.steady_keys() or firmware.safe_op_keys()
                 or firmware.sync0_steady_keys()) if esc.present
                else None for esc, firmware in zip(self.escs, self.firmwares, strict=True)]
        common = next((k for k in keys if k is not None and batchable_keys(*k)), None)
        if common is None:
            return
        if common != self._keys:
            firmware = self.firmwares[keys.index(common)]
            self._layouts = tuple(PdoLayout(0, tuple(
                mappable_object(firmware.device.dictionary, entry)
                for entry in firmware.objects.assigned_entries(assign)))
                for assign in (ec.RXPDO_ASSIGN, ec.TXPDO_ASSIGN))
            self._keys = common
            self._encoder = InputEncoder(self._layouts[1], len(self.escs))
            self._fields = _pdo_fields(*self._layouts, common)
        sizes = (self._layouts[0].size, self._layouts[1].size)
        for k, (esc, firmware) in enumerate(zip(self.escs, self.firmwares, strict=True)):
            if keys[k] != common or esc._plan is None:
                continue
            out_start, out_length = esc.sync_manager(firmware.outputs_sm)[:2]
            in_start, in_length = esc.sync_manager(firmware.inputs_sm)[:2]
            writes, reads = esc._plan
            # exactly one FMMU onto each whole buffer, nothing else mapped
            if (len(writes) == 1 and len(reads) == 1 and len(esc._fmmus) == 2
                    and (out_length, in_length) == sizes
                    and writes[0][2] == out_start and writes[0][1] - writes[0][0] == out_length
                    and writes[0][3]
                    and reads[0][2] == in_start and reads[0][1] - reads[0][0] == in_length):
                self._steady[k] = True
                self._dc[k] = firmware.sync0_steady_keys() is not None
                self._holding[k] = firmware.safe_op_keys() is not None
                self._starts[k] = out_start, in_start

    def _plan(self, frame: bytearray, spans: list) -> "_Plan | None":
        """The plan for a frame of these datagrams; None: slave by slave."""
        logical, others = [], []
        for span in spans:
            command, header, data, length = span
            if command in _LOGICAL:
                address = int.from_bytes(frame[header + 2:header + 6], "little")
                logical.append((command, address, address + length, data, length))
            elif command != ec.Command.NOP:
                ado = frame[header + 4] | frame[header + 5] << 8
                end = ado + length
                reads_only = command in _READS and end <= ec.PROCESS_RAM_START and not (
                    ado < _WATCHDOG_REGISTERS[1] and _WATCHDOG_REGISTERS[0] < end)
                clock = _CLOCK_TIMES[0] <= ado and end <= _CLOCK_TIMES[1]
                if not (reads_only or clock):
                    return None
                others.append(span)
        if not logical:
            return None
        rows, out_index, in_index, wkc = [], [], [], []
        ranges = [(start, stop) for esc in self.escs for start, stop, *_ in esc._fmmus]
        for k in np.flatnonzero(self._steady).tolist():
            esc = self.escs[k]
            (o_start, o_stop, *_), = esc._plan[0]
            (i_start, i_stop, *_), = esc._plan[1]
            shares = [0] * len(logical)
            places = []
            for start, stop, wanted, share in ((o_start, o_stop, _WRITES_OUTPUTS, 2),
                                               (i_start, i_stop, _READS_INPUTS, 1)):
                over = [n for n, d in enumerate(logical) if d[1] < stop and start < d[2]]
                if len(over) != 1:
                    break
                command, address, end, data, _ = logical[over[0]]
                if command not in wanted or not (address <= start and stop <= end):
                    break
                # nobody else's FMMU over this area (this slave's own two may overlap)
                if sum(1 for s, e in ranges if s < stop and start < e) > (
                        2 if o_start < i_stop and i_start < o_stop else 1):
                    break
                shares[over[0]] += share if command == ec.Command.LRW else 1
                places.append(data + start - address + np.arange(stop - start))
            else:
                rows.append(k)
                out_index.append(places[0])
                in_index.append(places[1])
                wkc.append(shares)
        if not rows:
            return None
        batched = set(rows)
        plan = _Plan(
            np.array(rows, dtype=np.int64), np.array(out_index), np.array(in_index),
            np.array(wkc, dtype=np.int64), [d[3] + d[4] for d in logical],
            [others if k in batched else None for k in range(len(self.escs))],
            [k in batched and bool(self.escs[k]._plan[0][0][4]) for k in range(len(self.escs))])
        self._plan_clock(plan, frame, spans)
        plan.plain = plan.plain and not plan.clock_rows.size
        # which of them are on SYNC0: as the plan, kept while the steady slaves are
        plan.on_sync0 = self._dc[plan.rows]
        plan.free_run = not plan.on_sync0.any()
        return plan

    def _plan_clock(self, plan: _Plan, frame: bytearray, spans: list) -> None:
        """A DC master's reference clock datagram (an FRMW of 0x0910, 8 bytes, after the
        process data, as SOEM appends it): the batched slaves on SYNC0 behind the reference
        take its write at once (`dc.LineClocks.compare`) instead of each through its ESC."""
        command, header, data, length = spans[-1]
        logical_last = max(n for n, span in enumerate(spans) if span[0] in _LOGICAL)
        if (command != ec.Command.FRMW or length != 8 or logical_last == len(spans) - 1
                or frame[header + 4] | frame[header + 5] << 8 != dc.REG_SYSTEM_TIME):
            return
        station = frame[header + 2] | frame[header + 3] << 8
        reference = next((k for k, esc in enumerate(self.escs)
                          if esc.station_address == station), None)
        if reference is None:
            return
        rows = [k for k in plan.rows.tolist() if k > reference and self._dc[k]]
        for k in rows:
            plan.others[k] = plan.others[k][:-1]
        plan.clock_rows = np.array(rows, dtype=np.int64)
        plan.clock_span = data, data + length  # its data and its working counter

    def registers(self, frame: bytearray, spans: list) -> bool:
        """A frame of broadcast register reads only (BRD below the distributed clock's
        registers: SOEM's state check reads the AL status of the whole line so every few
        cycles) passed at once: each present slave ORs its registers into the data, counts
        itself in the working counter and the address, and posts a waiting mailbox message,
        as its ESC does (`Esc.process`); False, the frame untouched, for any other frame.
        (Slave by slave such a frame cost some 200 us for talos' 32 slaves.)"""
        for command, header, _, length in spans:
            if command != ec.Command.BRD or (frame[header + 4] | frame[header + 5] << 8) \
                    + length > dc.REG_RECEIVE_TIME_PORT0:
                return False
        present = [(esc, firmware) for esc, firmware in zip(self.escs, self.firmwares,
                                                            strict=True) if esc.present]
        memories = [esc.memory for esc, _ in present]
        for _, header, data, length in spans:
            address = frame[header + 4] | frame[header + 5] << 8
            value = int.from_bytes(frame[data:data + length], "little")
            for memory in memories:
                value |= int.from_bytes(memory[address:address + length], "little")
            frame[data:data + length] = value.to_bytes(length, "little")
            adp = frame[header + 2] | frame[header + 3] << 8
            ec.WKC.pack_into(frame, header + 2, (adp + len(present)) & 0xFFFF)
            ec.WKC.pack_into(frame, data + length, (ec.WKC.unpack_from(frame, data + length)[0]
                                                    + len(present)) & 0xFFFF)
        for esc, firmware in present:
            if firmware.mail_waiting():
                firmware.frame_passed(esc)
        return True

    def settle(self) -> None:
        """Write into the ESCs and firmwares what plain frames left in the batch's arrays:
        each slave's time of the last frame and the process data watchdog deadline it set,
        and the cycles each firmware ran. Called before anything looks at them (a frame
        slave by slave, SYNC0, the watchdogs' check, the report): a steady frame then costs
        no Python per slave, and every slave ends as the per-slave path leaves it."""
        plan, at = self._fed_plan, self._fed_at
        if at is not None:
            self._fed_at = self._fed_plan = None
            escs = self.escs
            for k, when in zip(plan.rows.tolist(), (at + self.clocks.hop[plan.rows]).tolist(),
                               strict=True):
                esc = escs[k]
                esc.now = when
                if plan.watchdogs[k] and esc._watchdog_period:
                    esc._watchdog_deadline = when + esc._watchdog_period
        uncounted = self._uncounted
        if uncounted.any():
            for k in np.flatnonzero(uncounted).tolist():
                self.firmwares[k].cycles += int(uncounted[k])
            uncounted[:] = 0

    def passed_without(self, frame: bytearray, spans: list) -> None:
        """The frame went slave by slave: unless it only read registers, it may have
        changed the slaves (state, sync managers, FMMUs) and run their drives' cycles
        outside the line, so both are looked at again before the next batch."""
        self.settle()
        for command, header, _, length in spans:
            if command == ec.Command.NOP:
                continue
            ado = frame[header + 4] | frame[header + 5] << 8
            end = ado + length
            if command in _READS and end <= ec.PROCESS_RAM_START:
                continue
            if command in _READS and self._in_mailboxes(ado, end, writing=False):
                continue  # the master takes a message: no slave or drive changes
            if command in _MAILBOX_WRITES and self._in_mailboxes(ado, end, writing=True):
                # a message to the slave (an SDO): its drive says itself when an object it
                # changed matters to the batch (`Cia402Device._changed`); the firmware's
                # state is looked at again, its sync managers and FMMUs are as they were
                self.stale = True
                continue
            self.stale = self._replan = self._drives_unknown = True
            return

    def _in_mailboxes(self, address: int, end: int, writing: bool) -> bool:
        """Whether [address, end) lies in every slave's mailbox-out buffer (`writing`) or
        mailbox-in buffer: a master's CoE traffic beside the cyclic frames (a Python look
        per slave, in frames that pass slave by slave anyway)."""
        for esc, firmware in zip(self.escs, self.firmwares, strict=True):
            start, size, _, _ = esc.sync_manager(
                firmware.mailbox_out if writing else firmware.mailbox_in)
            if not (size and start <= address and end <= start + size):
                return False
        return True

    def slaves_changed(self, cycled: bool) -> None:
        """Something outside a frame changed the slaves (a watchdog expired, SYNC0 fired);
        `cycled`: their drives ran cycles too."""
        self.settle()
        self.stale = self._replan = True
        self._drives_unknown = self._drives_unknown or cycled

    def cycled_elsewhere(self, rows: Sequence[int]) -> None:
        """The drives `rows` ran cycles outside the batch (alone)."""
        self.settle()
        self.line.cycled_elsewhere(rows)

    # --- one frame ---------------------------------------------------------------------------

    def process(self, frame: bytearray, view: memoryview, spans: list, now: float) -> bool:
        """Pass the frame through the line with its steady slaves' process data as a batch;
        False (the frame untouched) when this frame has none: the caller passes it slave by
        slave."""
        line = self.line
        if self.stale:
            self._find_steady()
        key = tuple(spans) + tuple(bytes(frame[h + 2:h + 6]) for _, h, _, _ in spans)
        plan = self._plans.get(key, False)
        if plan is False:
            plan = self._plans[key] = self._plan(frame, spans)
        if plan is None:
            return False
        # the drives as they are now (read again only when the line may be behind them)
        if self._drives_unknown:
            line.cycled_elsewhere(range(len(self.escs)))
            self._drives_unknown = False
        if line.refresh():
            self._find_steady()
            plan = self._plans.get(key, False)
            if plan is False:
                plan = self._plans[key] = self._plan(frame, spans)
            if plan is None:
                return False
        buffer = np.frombuffer(frame, np.uint8)
        on_sync0 = plan.on_sync0
        if plan.free_run:
            done = self._cycle_now(buffer, plan, None)
        else:
            done = np.ones(len(plan.rows), dtype=bool)
            if not on_sync0.all():
                free = ~on_sync0
                done[free] = self._cycle_now(buffer, plan, free)
            self._exchange(buffer, plan, on_sync0)
        all_done = bool(done.all())
        shares = plan.wkc_sums if all_done else plan.wkc[done].sum(axis=0).tolist()
        for offset, share in zip(plan.wkc_offsets, shares, strict=True):
            if share:
                ec.WKC.pack_into(frame, offset, (ec.WKC.unpack_from(frame, offset)[0] + share)
                                 & 0xFFFF)
        if plan.primed and all_done:
            # plain and steady: the ESCs and firmwares written when next looked at
            if self._fed_plan is not plan:
                self.settle()
            self._fed_at, self._fed_plan = now, plan
            self._uncounted[plan.rows] += 1
            if any(map(_OUTBOX, self.firmwares)):  # a message to post: as the loop below
                for esc, firmware in zip(self.escs, self.firmwares, strict=True):
                    if firmware._outbox:
                        firmware.frame_passed(esc)
            return True
        self.settle()
        # the rest of the frame slave by slave, in line order (a batched slave's cycle
        # leaves its watchdog retriggered and its cycle counted, or on SYNC0 its outputs
        # noted for the window); a batched slave whose drive had more to its cycle passes
        # the whole frame through its ESC (its data untouched)
        others = plan.others
        if not all_done:
            others = list(others)
            for k in plan.rows[~done].tolist():
                others[k] = None
        firmwares, dc_steady = self.firmwares, self._dc
        # the outputs' bookkeeping of the slaves in OP on SYNC0 at once, each at its own time;
        # slaves entering OP, and any whose SYNC0 stopped, each through its firmware
        alone = (self._outputs_in_op(plan.rows[on_sync0 & done], now) if not plan.free_run
                 else ())
        for k, (esc, at) in enumerate(zip(self.escs, (now + self.clocks.hop).tolist(),
                                          strict=True)):
            esc.now = at
            rest = others[k]
            if rest is None:
                esc.process(frame, view, spans)
                continue
            if plan.watchdogs[k]:
                esc._trigger_watchdog()
            firmware = firmwares[k]
            if not dc_steady[k]:
                firmware.cycles += 1
            elif k in alone:
                memory = esc.memory
                status = memory[ec.REG_AL_STATUS]
                firmware.outputs_received(esc)
                if memory[ec.REG_AL_STATUS] != status:  # its sync lost: slave by slave again
                    self.stale = True
            if rest:
                esc.process(frame, view, rest)
            else:
                firmware.frame_passed(esc)
        rows = plan.clock_rows
        if rows.size:
            data, counter = plan.clock_span
            clocks = self.clocks
            clocks.compare(rows, frame[data:data + 8], now + clocks.hop[rows])
            ec.WKC.pack_into(frame, counter, (ec.WKC.unpack_from(frame, counter)[0]
                                              + rows.size) & 0xFFFF)
        plan.primed = plan.plain and all_done and plan.free_run
        return True

    def _outputs_in_op(self, rows: np.ndarray, now: float) -> set[int]:
        """The frame's outputs reached the slaves `rows` (steady on SYNC0) at `now` plus each
        one's hop: those in OP counted for their next SYNC0 at once (`LineSync.outputs_in`).
        The rows left to their firmware: not in OP yet, or their SYNC0 stopped."""
        clocks = self.clocks
        status = dc.read_registers(clocks.memories, rows, ec.REG_AL_STATUS, 1)[:, 0]
        in_op = rows[status == ec.AlState.OP]
        alone = set(rows[status != ec.AlState.OP].tolist())
        if in_op.size:
            lost = self.sync.outputs_in(in_op, now + clocks.hop[in_op],
                                        clocks.upcoming(now)[in_op], clocks.cycle_times(in_op))
            alone.update(lost.tolist())
        return alone

    def _outputs(self, outputs: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, list]:
        """The controlwords and target columns (a row per slave of the line) of `outputs`,
        the output images of the slaves `rows`."""
        decoded = outputs.view(self._layouts[0].dtype)[:, 0]
        count = len(self.escs)
        controlwords = np.zeros(count, dtype=np.int64)
        controlwords[rows] = decoded["f0"]
        targets = []
        for n in range(1, len(self._keys[0])):
            column = np.zeros(count, dtype=np.int64)
            column[rows] = decoded[f"f{n}"]
            targets.append(column)
        return controlwords, targets

    def _cycle_now(self, buffer: np.ndarray, plan: _Plan, mask: np.ndarray | None
                   ) -> np.ndarray:
        """Free run: the batched slaves (`mask` over the plan's rows, None: all) cycle on
        the frame's outputs and put their fresh inputs in it (`frame_pass`). Whose drive
        ran (over the masked rows)."""
        line = self.line
        rows, out_at, in_at = plan.rows, plan.out_at, plan.in_at
        if mask is not None:
            rows, out_at, in_at = rows[mask], out_at[mask], in_at[mask]
        line.prepare(self._keys[0])
        out_fields, in_fields, torque_field, current_field = self._fields
        scratch = self._scratch
        done = scratch["done"][:len(rows)]
        ran = frame_pass(buffer, rows, out_at, in_at, self._holding, self._memories,
                         self._starts,
                         out_fields, in_fields, torque_field, current_field,
                         scratch["controlwords"],
                         scratch["torque"] if torque_field >= 0 else _NONE,
                         scratch["current"] if current_field >= 0 else _NONE,
                         self._encoder.bytes, self._line_arrays, dynamics.SUBSTEPS, done,
                         line._unwritten)
        if ran < len(self.escs):  # as `DriveLine.cycle`: the others may run elsewhere
            line.cycled_elsewhere(np.setdiff1d(np.arange(len(self.escs)), rows[done],
                                               assume_unique=True).tolist())
        self.batched += ran
        return done.copy()

    def _exchange(self, buffer: np.ndarray, plan: _Plan, mask: np.ndarray) -> None:
        """DC: the batched slaves (`mask` over the plan's rows) take the frame's outputs
        into their SM2 buffers (for their next SYNC0) and give it the inputs their last
        SYNC0 sampled into SM3; no drive cycles."""
        rows = plan.rows[mask]
        outputs = buffer[plan.out_index[mask]]  # a copy: taken before inputs
        inputs = from_buffers(rows, self._memories, self._starts, 1,
                              plan.in_index.shape[1])
        buffer[plan.in_index[mask]] = inputs
        count = len(self.escs)
        full_outputs = np.zeros((count, outputs.shape[1]), dtype=np.uint8)
        full_outputs[rows] = outputs
        full_inputs = np.zeros((count, inputs.shape[1]), dtype=np.uint8)
        full_inputs[rows] = inputs
        into_buffers(rows, self._memories, self._starts, full_outputs, full_inputs)

    # --- SYNC0 -------------------------------------------------------------------------------

    def _pass(self, now: float, present: np.ndarray) -> int:
        """`sync0_pass` on this line's arrays (its result in `_scratch`): how many were due."""
        clocks, sync, scratch = self.clocks, self.sync, self._scratch
        out_fields, in_fields, torque_field, current_field = self._fields
        return sync0_pass(now, present, self._dc, self._memories, self._starts,
                          clocks.local_at_zero, clocks.drift, clocks.correction, clocks.slew,
                          clocks.anchor, clocks.next_sync0, clocks.armed, clocks.next_host,
                          clocks.sync0_count, sync.fresh, sync.errors, sync.since,
                          sync.last_sync0, sync.missed, sync.limit, sync.excused_until,
                          out_fields, in_fields, torque_field, current_field,
                          scratch["controlwords"],
                          scratch["torque"] if torque_field >= 0 else _NONE,
                          scratch["current"] if current_field >= 0 else _NONE,
                          self._encoder.bytes if self._encoder is not None
                          else self._no_inputs, self._line_arrays, dynamics.SUBSTEPS,
                          scratch["cycle_rows"], scratch["done"], self.line._unwritten,
                          scratch["due_rows"], scratch["due_times"], scratch["kinds"])

    def sync0(self, now: float, present: np.ndarray) -> np.ndarray:
        """The line's SYNC0 events due by `now` (the slaves `present`), one a slave, each at
        its own time (`LineClocks.take_due`): the rows whose SYNC0 fired. Every slave steady
        in OP on SYNC0 in one compiled call (`sync0_pass`: its window's bookkeeping, its
        drive's cycle on the SM2 buffer when outputs came in the window and on what it holds
        when none did, its inputs into SM3); the others each through its firmware
        (`sync0_window`, `run_cycle`), exactly as `SlaveFirmware.sync0` runs them one by one.
        (A window without outputs went slave by slave, a device cycle in Python each: on a
        late master the line fell further behind with every window missed, 7 ms an answer
        over a veth, and lost its sync. As many small numpy operations the pass cost 250 us
        for 32 slaves, more than the frame.)"""
        line = self.line
        self.settle()
        if self.stale:
            self._find_steady()
        if self._drives_unknown:
            line.cycled_elsewhere(range(len(self.escs)))
            self._drives_unknown = False
        if line.refresh():
            self._find_steady()
        if self._keys is not None:
            line.prepare(self._keys[0])
        due = self._pass(now, present)
        scratch = self._scratch
        rows = scratch["due_rows"][:due].copy()
        if not due:
            return rows
        escs, firmwares, steady = self.escs, self.firmwares, self._dc
        for k, t in zip(rows.tolist(), scratch["due_times"][:due].tolist(), strict=True):
            escs[k].now = t
        kinds = scratch["kinds"][rows]
        ran = rows[kinds == RAN].tolist()
        for k in ran:
            firmwares[k].cycles += 1
        self.batched += len(ran)
        if len(ran) == due:
            return rows
        single = []
        for k in rows[kinds == LOST].tolist():
            firmwares[k]._sync_lost(escs[k], ec.AL_SYNC_ERROR, missed_windows(
                firmwares[k].missed_sync0, int(self.sync.since[k])))
            single.append((k, False))
        single.extend((k, True) for k in rows[kinds == FRESH_LEFT].tolist())
        single.extend((k, False) for k in rows[kinds == HELD_LEFT].tolist())
        # the slaves not steady in OP (entering OP, or not on SYNC0): their firmware's
        # bookkeeping; those steady and waiting for OP cycle in the batch all the same
        fresh, held = [], []
        for k in rows[kinds == ELSEWHERE].tolist():
            apply = firmwares[k].sync0_window(escs[k])
            if apply is None:
                continue
            if steady[k] and (apply or escs[k].memory[ec.REG_AL_STATUS] in _WAITING):
                (fresh if apply else held).append(k)
            else:
                single.append((k, apply))
        if fresh or held:
            rows_ = np.array(fresh + held, dtype=np.int64)
            outputs = from_buffers(rows_, self._memories, self._starts, 0,
                                   self._layouts[0].size)
            controlwords, targets = self._outputs(outputs, rows_)
            if held:
                kept = rows_[len(fresh):]
                controlwords[kept], kept_targets = line.held_outputs(kept, self._keys[0])
                for column, values in zip(targets, kept_targets, strict=True):
                    column[kept] = values
            done = line.cycle(rows_, controlwords, self._keys[0], targets, refresh=False,
                              others_idle=True)
            ran_ = rows_[done]
            self._encoder.encode(line.values, ran_)
            full_outputs = np.zeros((len(self.escs), outputs.shape[1]), dtype=np.uint8)
            full_outputs[rows_] = outputs  # a held slave's buffer written back as it was
            into_buffers(ran_, self._memories, self._starts, full_outputs, self._encoder.bytes)
            for k in ran_.tolist():
                firmwares[k].cycles += 1
            single.extend((k, n < len(fresh)) for n, k in zip(
                np.flatnonzero(~done).tolist(), rows_[~done].tolist(), strict=True))
            self.batched += len(ran_)
        if single:
            line.cycled_elsewhere([k for k, _ in single])
            for k, apply in single:
                firmwares[k].run_cycle(apply)
                # a slave that left its steady state (entered OP, lost its sync) is looked
                # at again; one that only missed a window stays as it was
                if steady[k] != (firmwares[k].sync0_steady_keys() is not None):
                    self.stale = True
        return rows
