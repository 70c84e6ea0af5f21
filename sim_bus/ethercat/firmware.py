"""The slave's firmware behind the ESC: the EtherCAT state machine with its checks and
refusals, the mailbox (CoE) and the process data, around one transport-neutral CiA 402 device.

States (ETG.1000.6): INIT; PRE-OP once the mailbox sync managers match the SII (CoE works,
PDO assignment and mapping can change); SAFE-OP once SM2/SM3 match the assigned PDOs (inputs
valid, outputs ignored); OP at the first output buffer after the request (outputs applied).
A refused request leaves the state, raises the error indicator and names the AL status
code; the master acknowledges it with bit 4 of AL control.

SM-synchronous cycle (free run): every completed output buffer (a frame writing SM2) runs one
device cycle, exactly as a SYNC does on CAN: outputs latched (in OP), physics advanced one
period, inputs sampled into SM3, all before the frame leaves this slave.

DC-synchronous cycle: when the master has activated SYNC0 (`sim_bus.ethercat.dc`) by the time
it requests OP, the device cycle runs on SYNC0 instead: the outputs that completed in the
window since the last SYNC0 are latched, the physics advances, the inputs are sampled for the
next frame to read. Missed windows are counted as the ETG slave stack code (SSC, on which most
drives' firmware is built) counts them (SM event missed counter 0x1C32:0B against the sync
error counter limit 0x10F1:02, `CoeObjects.sync_error_limit`, taken at the OP request): every
output buffer takes 1 off the counter and restarts a count of SYNC0 events; the first SYNC0
after outputs without new ones is free (SSC's u16SmSync0Value of 1 for SYNC0 mode: a frame
that falls just after one SYNC0 is taken by the next), each further one adds
SYNC_ERROR_WEIGHT (while the counter is not above the limit, as SSC's Sync0_Isr), and once
the counter reaches the limit the slave drops to SAFE-OP with AL status code 0x001A
(synchronization error; SSC's DC_CheckWatchdog: the sync sequence is valid while the counter
is below the limit, always with a limit of 0): a master whose frames go out irregularly (two
in one window, none in the next, as a SOEM master's do under load) is tolerated; with SSC's
default limit of 4 one that stops for three windows is not, with 9 (the default of Yaskawa's
Sigma-7 and Kollmorgen's AKD2G) four. A SYNC0 that stops coming in OP gives
0x002C (fatal sync error); either way the drive reacts as to a lost master (abort connection
option 0x6007: quick stop by default).
"""

import logging
import math
import operator
from collections import deque
from collections.abc import Sequence

import numpy as np

from protocol import ethercat as ec
from protocol.dictionary import mappable_object
from protocol.esi import SYNC_ERROR_COUNTER_LIMIT_DEFAULT, EsiDevice
from protocol.pdo import PdoLayout
from sim_bus.device import Cia402Device, DeviceAccessError
from sim_bus.ethercat.esc import Esc
from sim_bus.ethercat.mailbox import CoeMailbox
from sim_bus.ethercat.objects import CoeObjects
from sim_bus.faults import TPDO_DELAY, Fault

log = logging.getLogger(__name__)

# DC-synchronous operation (assumed figures of the virtual drive, stated here)
# SSC's figures: the counter's step per counted miss, its limit (MAX_SM_EVENT_MISSED, the
# default of 0x10F1:02) and the SYNC0 events after outputs that need none (u16SmSync0Value)
SYNC_ERROR_WEIGHT = 3
FREE_SYNC0 = 1
OUTPUT_MARGIN = 20e-6  # s: outputs must be complete this long before SYNC0 (copy time)
SYNC0_LOSS_CYCLES = 3  # cycle times without SYNC0 in OP: the sync is lost

_VALID_REQUESTS = frozenset(s.value for s in ec.AlState if s is not ec.AlState.NONE)


class LineSync:
    """The SYNC0 bookkeeping of a line's slaves (SSC's counters, what came in each window), a
    row each (`SlaveFirmware.join`), in one set of arrays: a segment's batch does a frame's or
    a SYNC0's bookkeeping for every slave steady in OP at once (`outputs_in`, `sync0_in_op`);
    a slave's firmware does the same for itself, on its row, in every other case."""

    def __init__(self, count: int):
        self.fresh = np.zeros(count, dtype=bool)  # outputs completed for the next SYNC0
        self.errors = np.zeros(count, dtype=np.int64)  # SSC's SM event missed counter
        self.since = np.zeros(count, dtype=np.int64)  # SYNC0 events since the last outputs
        self.last_sync0 = np.full(count, math.nan)  # host time of the last SYNC0 (NaN: none)
        self.missed = np.zeros(count, dtype=np.int64)  # SYNC0 events in OP without outputs
        # the sync error counter limit (0x10F1:02) each took at its OP request; 0: no check
        self.limit = np.full(count, SYNC_ERROR_COUNTER_LIMIT_DEFAULT, dtype=np.int64)
        # host time up to which an empty window is the slave host's own doing, not counted
        # (`excuse`)
        self.excused_until = -math.inf

    def excuse(self, arrival: float, answered: float, cycle: float) -> None:
        """The answer to the frame that arrived at `arrival` left at `answered`, more than a
        SYNC0 cycle (`cycle`, s) later: the process running these slaves stalled, and the
        master, waiting for that answer, could send nothing meanwhile (hardware forwards a
        frame in microseconds). The windows whose SYNC0 comes before the master's next
        frame could (`answered` plus a cycle) are not counted against its sync: the virtual
        slave's host must not pass its own stall off as the master's. (Stalls of 2-6 ms of
        this process lost talos_32's sync over a veth: the master, blocked on the answer,
        left three windows empty.)"""
        if answered - arrival > cycle > 0:
            self.excused_until = max(self.excused_until, answered + cycle)

    def join(self, firmwares: Sequence["SlaveFirmware"]) -> None:
        for row, firmware in enumerate(firmwares):
            firmware.join(self, row)

    def outputs_in(self, rows: np.ndarray, now: np.ndarray, upcoming: np.ndarray,
                   cycle_times: np.ndarray) -> np.ndarray:
        """Outputs completed at `now` (per row) for slaves in OP on SYNC0, their next SYNC0
        at `upcoming` (inf: none) every `cycle_times` s: `SlaveFirmware._outputs_for_sync0`
        for each at once. The rows whose SYNC0 stopped coming (their firmware says so)."""
        lost = np.isinf(upcoming) | (now - self.last_sync0[rows]
                                     > SYNC0_LOSS_CYCLES * cycle_times)
        taken = rows[~lost & (upcoming - now >= OUTPUT_MARGIN)]
        self.fresh[taken] = True
        self.since[taken] = 0
        self.errors[taken] = np.maximum(self.errors[taken] - 1, 0)
        return rows[lost]

    def sync0_in_op(self, rows: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The SYNC0 at `times` of slaves in OP on SYNC0: `SlaveFirmware.sync0_window` for
        each at once. (whether each applies outputs, the rows whose sync is lost: their
        firmware drops them out of OP)."""
        self.last_sync0[rows] = times
        fresh = self.fresh[rows]
        self.fresh[rows] = False
        self.missed[rows[~fresh]] += 1
        limit = self.limit[rows]
        counted = ~fresh & (self.since[rows] > FREE_SYNC0) & (times > self.excused_until)
        self.errors[rows[counted & (self.errors[rows] <= limit)]] += SYNC_ERROR_WEIGHT
        lost = counted & sync_lost(self.errors[rows], limit)
        self.since[rows] += 1
        return fresh & ~lost, rows[lost]


def sync_lost(errors, limit):
    """SSC's DC_CheckWatchdog: the sync sequence is invalid once the SM event missed counter
    reaches the sync error counter limit, never with a limit of 0 (the check off)."""
    return (limit != 0) & (errors >= limit)


def _sync_field(name: str, kind: type) -> property:
    """An attribute of one firmware kept in its row of its line's `LineSync` array `name`."""
    def get(self):
        return kind(getattr(self._sync, name)[self._row])

    def put(self, value) -> None:
        getattr(self._sync, name)[self._row] = value

    return property(get, put)


class FrameFaults:
    """Whether a fault on a frame's answer (held, sent twice, lost: `SlaveFirmware`'s
    `delay_next_frame`, `repeat_next_frame`, `lose_next_frame`) waits on some slave of a
    line: set by the slave that takes one, cleared by the line once none waits."""

    __slots__ = ("pending",)

    def __init__(self) -> None:
        self.pending = False


class SlaveFirmware:
    """One slave's application; `attach` it to its ESC before the first frame."""

    _fresh = _sync_field("fresh", bool)
    _sync_errors = _sync_field("errors", int)
    _since_outputs = _sync_field("since", int)
    missed_sync0 = _sync_field("missed", int)
    _sync_limit = _sync_field("limit", int)

    @property
    def _last_sync0(self) -> float | None:
        value = float(self._sync.last_sync0[self._row])
        return None if math.isnan(value) else value

    @_last_sync0.setter
    def _last_sync0(self, value: float | None) -> None:
        self._sync.last_sync0[self._row] = math.nan if value is None else value

    def join(self, line: LineSync, row: int) -> None:
        """Keep this firmware's SYNC0 bookkeeping in row `row` of `line` from now on."""
        for name in ("fresh", "errors", "since", "last_sync0", "missed", "limit"):
            getattr(line, name)[row] = getattr(self._sync, name)[self._row]
        self._sync, self._row = line, row

    def __init__(self, device: Cia402Device, esi: EsiDevice):
        self.device = device
        self.esi = esi
        self.objects = CoeObjects(device, esi)
        self.mailbox_out = esi.sm_number("MBoxOut")
        self.mailbox_in = esi.sm_number("MBoxIn")
        self.outputs_sm = esi.sm_number("Outputs")
        self.inputs_sm = esi.sm_number("Inputs")
        size = min(esi.sync_manager("MBoxOut").default_size,
                   esi.sync_manager("MBoxIn").default_size)
        self.mailbox = CoeMailbox(self.objects, size)
        self.esc: Esc | None = None
        self._outbox: deque[bytes] = deque()
        self._deferred: list[bytes] | None = None
        self._last_sent: bytes | None = None
        self._op_requested = False
        self._outputs_seen = False
        self._out_keys: tuple[tuple[int, int], ...] = ()
        self._in_keys: tuple[tuple[int, int], ...] = ()
        self._unpack_outputs = self._pack_inputs = None
        self._out_start = self._in_start = 0
        self._input_values = None  # the device's value table -> the inputs, in PDO order
        self.cycles = 0
        self._dc = False  # the device cycle runs on SYNC0 (decided at the OP request)
        # SYNC0 bookkeeping, in a row of its line's arrays (`LineSync`; its own until joined)
        self._sync, self._row = LineSync(1), 0
        self.refused_outputs = 0  # output values the device refused (out of its range)
        self.delay_next_frame = 0.0  # s, fault injection: hold the frame this long
        self.repeat_next_frame = False  # fault injection: send the frame twice
        self.lose_next_frame = False  # fault injection: the frame lost on its way back
        # set with any of the three (its own until its line shares one among its slaves)
        self.frame_faults = FrameFaults()
        device.add_emergency_handler(self._emergency)
        device.add_fault_handler(self._communication_fault)

    def attach(self, esc: Esc) -> None:
        self.esc = esc
        self._enter_init()

    @property
    def state(self) -> int:
        return self.esc.al_status & ec.AL_STATE_MASK if self.esc is not None else 0

    # --- AL control ------------------------------------------------------------------------

    def al_control(self, esc: Esc, control: int) -> None:
        requested = control & ec.AL_STATE_MASK
        status = esc.al_status
        current = status & ec.AL_STATE_MASK
        error = status & ec.AL_ERROR
        code = _u16(esc, ec.REG_AL_STATUS_CODE)
        if error:
            if control & ec.AL_ERROR:
                error, code = 0, ec.AL_NO_ERROR
            elif requested > current and requested != ec.AlState.BOOT:
                return  # an unacknowledged error blocks every way up
        if requested not in _VALID_REQUESTS:
            esc.set_al_status(current | ec.AL_ERROR, ec.AL_UNKNOWN_STATE)
            return
        if requested == ec.AlState.BOOT:
            esc.set_al_status(current | ec.AL_ERROR, ec.AL_BOOTSTRAP_NOT_SUPPORTED)
            return
        if requested == current:
            if current == ec.AlState.SAFE_OP:
                self._op_requested = False
            esc.set_al_status(current | error, code)
            return
        refusal = self._transition(current, requested)
        if refusal:
            esc.set_al_status(current | ec.AL_ERROR, refusal)
            return
        if requested == ec.AlState.OP and (self._dc or not self._outputs_seen):
            # OP at the first output buffer (valid outputs); in DC mode at the first SYNC0
            # that has them
            self._op_requested = True
            esc.set_al_status(current | error, code)
            return
        esc.set_al_status(requested | error, code)

    def _transition(self, current: int, requested: int) -> int:
        """Leave `current` for `requested`; the AL status code of a refusal, or 0."""
        if current == ec.AlState.OP:
            self._leave_op(f"master requested {ec.al_state_name(requested)}")
        if requested == ec.AlState.INIT:
            self._enter_init()
            return 0
        if requested == ec.AlState.PRE_OP:
            if current == ec.AlState.INIT:
                return self._start_mailbox()
            self._stop_process_data()
            self.objects.pdo_config_allowed = True
            return 0
        if requested == ec.AlState.SAFE_OP:
            if current == ec.AlState.PRE_OP:
                return self._start_process_data()
            if current == ec.AlState.OP:
                self._op_requested = False
                return 0
            return ec.AL_INVALID_STATE_CHANGE
        # OP
        if current != ec.AlState.SAFE_OP:
            return ec.AL_INVALID_STATE_CHANGE
        self.esc.set_sync_manager_active(self.outputs_sm, True)  # off after a sync error
        return self._choose_synchronization()

    def _choose_synchronization(self) -> int:
        """SAFE-OP -> OP: SYNC0 active means DC-synchronous, with a cycle time that must be
        the drive's period (0x1006) and a first SYNC0 still to come; else free run."""
        clock = self.esc.dc
        self._dc = clock.sync0_active
        if not self._dc:
            return 0
        if abs(clock.cycle_time * 1e-9 - self.device.period) > 1e-7:
            log.warning("SYNC0 cycle time %d ns, the drive's period is %.0f us",
                        clock.cycle_time, self.device.period * 1e6)
            self._dc = False
            return ec.AL_DC_INVALID_SYNC_CYCLE_TIME
        if clock.next_sync0 is None:
            log.warning("SYNC0 activated with a start time already past")
            self._dc = False
            return ec.AL_INVALID_DC_SYNC_CONFIGURATION
        self._fresh = False
        self._sync_errors = self._since_outputs = 0
        self._last_sync0 = None
        self._sync_limit = self.objects.sync_error_limit
        return 0

    def _enter_init(self) -> None:
        self._stop_process_data()
        self.objects.pdo_config_allowed = False
        self._outbox.clear()
        self._last_sent = None
        esc = self.esc
        esc.clear_mailbox(self.mailbox_out)
        esc.clear_mailbox(self.mailbox_in)

    def _start_mailbox(self) -> int:
        """INIT -> PRE-OP: the mailbox sync managers must be the SII's."""
        for number, kind in ((self.mailbox_out, "MBoxOut"), (self.mailbox_in, "MBoxIn")):
            expected = self.esi.sync_manager(kind)
            start, length, control, activate = self.esc.sync_manager(number)
            if (start != expected.start or not expected.min_size <= length
                    <= expected.max_size or control != expected.control
                    or not activate & ec.SM_ACTIVATE_ENABLE):
                log.warning("SM%d %s: start 0x%04X length %d control 0x%02X activate 0x%02X "
                            "does not match the SII", number, kind, start, length, control,
                            activate)
                return ec.AL_INVALID_MAILBOX_CONFIGURATION
        self.mailbox.size = min(self.esc.sync_manager(self.mailbox_out)[1],
                                self.esc.sync_manager(self.mailbox_in)[1])
        self.mailbox.reset()
        self.esc.clear_mailbox(self.mailbox_in)
        self.objects.pdo_config_allowed = True
        return 0

    def _start_process_data(self) -> int:
        """PRE-OP -> SAFE-OP: SM2/SM3 must carry exactly the assigned PDOs."""
        try:
            outputs = [mappable_object(self.device.dictionary, e)
                       for e in self.objects.assigned_entries(ec.RXPDO_ASSIGN)]
            inputs = [mappable_object(self.device.dictionary, e)
                      for e in self.objects.assigned_entries(ec.TXPDO_ASSIGN)]
        except ValueError as exc:
            log.warning("process data mapping: %s", exc)
            return ec.AL_INVALID_OUTPUT_CONFIGURATION
        out_codec = PdoLayout(0, tuple(outputs))
        in_codec = PdoLayout(0, tuple(inputs))
        for number, codec, direction, code in (
                (self.outputs_sm, out_codec, ec.SM_DIRECTION_WRITE,
                 ec.AL_INVALID_OUTPUT_CONFIGURATION),
                (self.inputs_sm, in_codec, ec.SM_DIRECTION_READ,
                 ec.AL_INVALID_INPUT_CONFIGURATION)):
            start, length, control, activate = self.esc.sync_manager(number)
            enabled = bool(activate & ec.SM_ACTIVATE_ENABLE)
            if not codec.objects and not enabled:
                continue
            if (length != codec.size or not enabled
                    or control & ec.SM_CONTROL_MODE_MASK != ec.SM_MODE_BUFFERED
                    or control & ec.SM_CONTROL_DIRECTION_MASK != direction
                    or start < ec.PROCESS_RAM_START or self._overlaps_mailbox(start, length)):
                log.warning("SM%d: start 0x%04X length %d control 0x%02X activate 0x%02X, "
                            "expected %d bytes for the assigned PDOs", number, start, length,
                            control, activate, codec.size)
                return code
        # the cycle's codecs and buffer addresses (an enabled sync manager cannot move)
        self._unpack_outputs = out_codec.struct.unpack_from
        self._pack_inputs = in_codec.struct.pack_into
        self._out_start = self.esc.sync_manager(self.outputs_sm)[0]
        self._in_start = self.esc.sync_manager(self.inputs_sm)[0]
        self._out_keys = tuple((o.index, o.subindex) for o in outputs)
        self._in_keys = tuple((o.index, o.subindex) for o in inputs)
        if self._in_keys:
            getter = operator.itemgetter(*self._in_keys)
            self._input_values = getter if len(self._in_keys) > 1 else (
                lambda table: (getter(table),))
        self._outputs_seen = self._op_requested = False
        self.objects.pdo_config_allowed = False
        self.device.master_found()  # whoever starts the process data now is the master to watch
        self._write_inputs()
        self.esc.set_sync_manager_active(self.outputs_sm, True)
        self.esc.set_sync_manager_active(self.inputs_sm, True)
        return 0

    def _overlaps_mailbox(self, start: int, length: int) -> bool:
        for number in (self.mailbox_out, self.mailbox_in):
            other, other_length, _, _ = self.esc.sync_manager(number)
            if start < other + other_length and other < start + length:
                return True
        return False

    def _stop_process_data(self) -> None:
        esc = self.esc
        esc.set_sync_manager_active(self.outputs_sm, False)
        esc.set_sync_manager_active(self.inputs_sm, False)
        esc.stop_watchdog()
        self._op_requested = self._outputs_seen = self._dc = False

    def _leave_op(self, reason: str) -> None:
        """Outputs stop being applied; a drive left powered reacts as to a lost master
        (abort connection option 0x6007)."""
        if self.device.power_stage_on:
            self.device.master_lost(f"EtherCAT {reason}", ec.EMCY_ESM_TRANSITION)

    # --- process data ----------------------------------------------------------------------

    def outputs_received(self, esc: Esc) -> None:
        self._outputs_seen = True
        if self._dc:
            self._outputs_for_sync0(esc)
            return
        memory = esc.memory
        if self._op_requested:
            self._op_requested = False
            memory[ec.REG_AL_STATUS] = ec.AlState.OP | memory[ec.REG_AL_STATUS] & ec.AL_ERROR
        self.run_cycle(memory[ec.REG_AL_STATUS] & ec.AL_STATE_MASK == ec.AlState.OP)

    def run_cycle(self, apply_outputs: bool) -> None:
        """The drive's cycle: the outputs latched (when `apply_outputs`), one device cycle,
        the inputs sampled into SM3; on a completed output buffer (free run) or on SYNC0."""
        device = self.device
        if apply_outputs and self._out_keys:
            try:
                device.write_outputs(self._out_keys, self._unpack_outputs(self.esc.memory,
                                                                          self._out_start))
            except DeviceAccessError as exc:
                self.refused_outputs += 1
                log.debug("outputs refused: %s", exc)
        device.cycle()
        self.cycles += 1
        self._write_inputs()

    def steady_keys(self) -> tuple[tuple, tuple] | None:
        """(output objects, input objects) of the process data while a completed output
        buffer does nothing here but run the drive's cycle (OP, no OP transition pending):
        what a line linked in one process (`sim_bus.ethercat.linked`) may then run for this
        slave in its batch, counting the cycle in `cycles`. None otherwise, and in DC mode,
        where the cycle runs on SYNC0 (`sync0`), not on the buffer."""
        if self._dc or self._op_requested or self.esc.memory[
                ec.REG_AL_STATUS] & ec.AL_STATE_MASK != ec.AlState.OP:
            return None
        return self._out_keys, self._in_keys

    def safe_op_keys(self) -> tuple[tuple, tuple] | None:
        """`steady_keys` in SAFE-OP on completed output buffers (free run, no OP transition
        pending, outputs seen before): a buffer then only runs the drive's cycle on what it
        holds, its outputs ignored and its inputs sampled (`run_cycle(False)`), as an ESC in
        SAFE-OP does; the segment's batch runs these slaves' cycles at once as well (slave by
        slave, 32 slaves took 1.1-1.3 ms a frame over a veth, more than the period, on the
        way to OP). None otherwise."""
        if self._dc or self._op_requested or not self._outputs_seen or self.esc.memory[
                ec.REG_AL_STATUS] & ec.AL_STATE_MASK != ec.AlState.SAFE_OP:
            return None
        return self._out_keys, self._in_keys

    def sync0_steady_keys(self) -> tuple[tuple, tuple] | None:
        """`steady_keys` in DC mode: (output objects, input objects) while a completed
        output buffer only waits for SYNC0 (`outputs_received`) and a SYNC0 with fresh
        outputs does nothing but the drive's cycle besides its bookkeeping (in OP on SYNC0,
        or in SAFE-OP waiting for the first SYNC0 with outputs to enter OP); the segment's
        batch (`sim_bus.ethercat.frame_batch`) then moves the buffers and runs the cycles
        of all such slaves at once. None otherwise."""
        state = self.esc.memory[ec.REG_AL_STATUS] & ec.AL_STATE_MASK
        if not self._dc or (state != ec.AlState.OP or self._op_requested) and not (
                state == ec.AlState.SAFE_OP and self._op_requested):
            return None
        return self._out_keys, self._in_keys

    def _outputs_for_sync0(self, esc: Esc) -> None:
        """DC mode: the buffer waits for SYNC0; one completed inside OUTPUT_MARGIN of it is
        late and misses that SYNC0 (the one after takes the next frame's). In OP, SYNC0 must
        keep coming."""
        clock = esc.dc
        now = esc.now
        if esc.al_status & ec.AL_STATE_MASK == ec.AlState.OP:
            last = self._last_sync0
            if clock.next_sync0 is None or last is not None and (
                    now - last > SYNC0_LOSS_CYCLES * clock.cycle_time * 1e-9):
                self._sync_lost(esc, ec.AL_FATAL_SYNC_ERROR, "no SYNC0 for "
                                f"{(now - (last or now)) * 1e3:.1f} ms")
                return
        upcoming = clock.next_sync0_host_time(now)
        if upcoming is None or upcoming - now >= OUTPUT_MARGIN:
            self._fresh = True
            self._since_outputs = 0
            self._sync_errors = max(0, self._sync_errors - 1)

    def sync0(self, esc: Esc) -> None:
        """DC mode: latch the outputs of the window, advance the physics, sample the inputs."""
        apply = self.sync0_window(esc)
        if apply is not None:
            self.run_cycle(apply)

    def sync0_window(self, esc: Esc) -> bool | None:
        """SYNC0's bookkeeping before the drive's cycle: whether outputs came in the window
        (counted against the sync error limit, OP entered or left on it). None: no cycle (a
        free-running slave does not use SYNC0); else whether the cycle applies the outputs.
        The caller runs the cycle (`sync0`, or the segment's batch for many slaves at once)."""
        if not self._dc:
            return None  # SYNC0 pulses a free-running slave does not use
        self._last_sync0 = esc.now
        fresh, self._fresh = self._fresh, False
        memory = esc.memory
        state = memory[ec.REG_AL_STATUS] & ec.AL_STATE_MASK
        if self._op_requested and fresh:
            self._op_requested = False
            memory[ec.REG_AL_STATUS] = ec.AlState.OP | memory[ec.REG_AL_STATUS] & ec.AL_ERROR
            state = ec.AlState.OP
        elif state == ec.AlState.OP and not fresh:
            self.missed_sync0 += 1
            if self._since_outputs > FREE_SYNC0 and esc.now > self._sync.excused_until:
                if self._sync_errors <= self._sync_limit:
                    self._sync_errors += SYNC_ERROR_WEIGHT
                if sync_lost(self._sync_errors, self._sync_limit):
                    self._sync_lost(esc, ec.AL_SYNC_ERROR, missed_windows(
                        self.missed_sync0, self._since_outputs + 1))
                    state = ec.AlState.SAFE_OP
        self._since_outputs += 1
        return state == ec.AlState.OP and fresh

    def _sync_lost(self, esc: Esc, code: int, reason: str) -> None:
        """OP -> SAFE-OP with the error indicator and `code`, the output sync manager off (the
        master's writes are refused, so its working counter shows the slave gone); the drive
        stops as it does for a lost master."""
        self._op_requested = False
        esc.set_al_status(ec.AlState.SAFE_OP | ec.AL_ERROR, code)
        esc.set_sync_manager_active(self.outputs_sm, False)
        log.warning("slave 0x%04X: %s (%s)", esc.station_address, reason,
                    ec.al_status_name(code))
        self.device.master_lost(f"EtherCAT DC: {reason}", ec.EMCY_ESM_TRANSITION)

    def _write_inputs(self) -> None:
        if self._in_keys:
            self._pack_inputs(self.esc.memory, self._in_start,
                              *self._input_values(self.device.values))

    def watchdog_expired(self, esc: Esc) -> None:
        """No outputs within the watchdog time: the master is gone. OP drops to SAFE-OP with
        the error indicator (AL status code 0x001B) and the drive reacts to the lost master."""
        state = esc.al_status & ec.AL_STATE_MASK
        if state == ec.AlState.OP or self._op_requested:
            self._op_requested = False
            esc.set_al_status(ec.AlState.SAFE_OP | ec.AL_ERROR, ec.AL_SM_WATCHDOG)
            self.device.master_lost("EtherCAT sync manager watchdog expired",
                                    ec.EMCY_ESM_TRANSITION)

    # --- mailbox ---------------------------------------------------------------------------

    def mailbox_received(self, esc: Esc, message: bytes) -> None:
        if esc.al_status & ec.AL_STATE_MASK == ec.AlState.INIT:
            return  # the mailbox runs from PRE-OP on
        self._deferred = []  # an emergency the request itself causes follows its answer
        try:
            # the answer goes before emergencies still queued: a master waiting for it may
            # not survive another message first (SOEM 2.0's ecx_mbxreceive reads on into the
            # buffer it released for the emergency, and crashes)
            self._outbox.extendleft(reversed(self.mailbox.handle(message)))
        finally:
            deferred, self._deferred = self._deferred, None
            self._outbox.extend(deferred)
        self.frame_passed(esc)

    def mailbox_read(self, esc: Esc) -> None:
        self.frame_passed(esc)

    def mailbox_repeat(self, esc: Esc) -> None:
        if self._last_sent is not None:
            esc.clear_mailbox(self.mailbox_in)
            esc.post_mailbox(self.mailbox_in, self._last_sent)

    def mail_waiting(self) -> bool:
        return bool(self._outbox)

    def frame_passed(self, esc: Esc) -> None:
        """Post the next queued message once the mailbox-in buffer is free."""
        if self._outbox and esc.mailbox_in_empty(self.mailbox_in):
            message = self._outbox[0]
            if esc.post_mailbox(self.mailbox_in, message):
                self._outbox.popleft()
                self._last_sent = message

    def _emergency(self, code: int, register: int) -> None:
        """The device's emergency, as a CoE emergency (from PRE-OP on; lost in INIT, as on
        a real slave). Posted at the next frame: this may run in another thread."""
        if self.esc is not None and self.state != ec.AlState.INIT:
            message = self.mailbox.emergency(code, register)
            (self._deferred if self._deferred is not None else self._outbox).append(message)

    # --- faults of the communication (the device acts out its own) ---------------------------

    def _communication_fault(self, fault: Fault) -> None:
        esc = self.esc
        if fault is Fault.SILENT:
            esc.present = False
        elif fault is Fault.REBOOT:
            self.reboot()
        elif fault is Fault.TPDO_LATE:
            self.delay_next_frame = TPDO_DELAY
            self.frame_faults.pending = True
        elif fault is Fault.TPDO_TWICE:
            self.repeat_next_frame = True
            self.frame_faults.pending = True
        elif fault is Fault.LEAVES_OP:
            self.leave_op_on_error(ec.AL_SYNCHRONIZATION_ERROR)
        elif fault is Fault.FRAME_LOST:
            self.lose_next_frame = True
            self.frame_faults.pending = True
        else:
            log.warning("fault %s has no EtherCAT equivalent here", fault.name.lower())

    def leave_op_on_error(self, code: int) -> None:
        """The application leaves OP on its own, as a drive does on an error of its own (a
        sync error): SAFE-OP with the error indicator and `code`, its drive reacting as to a
        lost master. The ESC still moves the process data (a master sees a whole working
        counter); only the AL status tells."""
        if self.state == ec.AlState.OP or self._op_requested:
            self._op_requested = False
            self.esc.set_al_status(ec.AlState.SAFE_OP | ec.AL_ERROR, code)
            self._leave_op(f"left OP: AL status code {ec.al_status_name(code)}")

    def reboot(self) -> None:
        """Power glitch: ESC registers back to reset values (INIT, no station address), the
        device back to power-on values, its physics untouched."""
        self.esc.power_on()
        self.device.reset_application()
        self.objects.reset()
        self._enter_init()

    def hold(self) -> float:
        """Fault injection: how long the segment holds the current frame (0 normally)."""
        delay, self.delay_next_frame = self.delay_next_frame, 0.0
        return delay


def missed_windows(missed: int, since: int) -> str:
    """Why a slave lost its sync: its windows without outputs in OP, and how many of them
    in a row lately (`since`: SYNC0 events since outputs came, the first of which took
    them): a master silent for that many periods, or a few misses now and then."""
    return (f"outputs missed their SYNC0 window {missed} times, the last {since - 1} "
            "in a row")


def _u16(esc: Esc, address: int) -> int:
    return esc.memory[address] | esc.memory[address + 1] << 8
