"""A `Cia402Device` exposed as a CANopen node: NMT slave with boot-up and heartbeat, SDO server
(canopen's, answering from the device), PDOs configured from the dictionary, SYNC, EMCY.

A SYNC is handled once per network for every virtual drive on it (`_BusSync`), as a bus
carries one SYNC to all its nodes: the bus's drives, one or more, are a batch whose steady
cycles advance in one compiled call (`sim_bus.line_physics.DriveLine`, as a virtual EtherCAT
line's do), the others through `Cia402Device.cycle()` itself; the TPDOs of the batch's
drives are packed from its values in the same compiled call, for the whole bus
(`sim_bus.line_physics.pack_values`), each frame a slice of those bytes. A received RPDO
that repeats what the drive acts on (its controlword, with new targets) goes into the
batch's output arrays, not through the device; anything that reads or changes the device
before the SYNC gets it applied first (`_CanLine.flush`). One
more drive on a batched bus costs about 7 us a SYNC (seven drives: 61 us a SYNC against 118
through the devices' own cycles); a lone drive's SYNC, RPDO and three TPDOs about 1 us less
as the batch than through its device. The device's own path stays the one behaviour; the
batch is checked against it (tests/test_canopen_bus_batch.py, one drive and four).

Every handler runs in the thread that delivers the frame (the network's receive thread, or the
sender's with the embedded link), so a SYNC is handled completely before the next frame is
looked at: lock-step comes for free when the master waits for the TPDOs.

The heartbeats and the watch over the master are in `sim_bus.canopen_watchdogs`; they run on
the drive's own time, made from the clock the node is given (why that is the SYNCs it took in
lock-step is explained there). A SYNC whose length disagrees with the
synchronous counter overflow value 0x1019 (a counter byte while it is 0, none while it is set)
is answered with EMCY 0x8240, once until the SYNCs are right again, and still runs the cycle.
"""

import logging
import operator
import threading
import time

import canopen
import numpy as np
from canopen.emcy import EmcyProducer
from canopen.objectdictionary import ObjectDictionary
from canopen.sdo import SdoAbortedError, SdoServer

from protocol import cia301, objects
from protocol.dictionary import has, mappable_object
from protocol.pdo import PdoLayout
from sim_bus.canopen_watchdogs import (
    DEFAULT_SILENCE_TIMEOUT,
    Clock,
    HeartbeatProducer,
    MasterWatch,
)
from sim_bus.device import LINE_KEYS, Cia402Device, DeviceAccessError
from sim_bus.faults import FLOOD_COB_ID, FLOOD_SECONDS, TPDO_DELAY, Fault
from sim_bus.line_physics import STEADY, DriveLine

log = logging.getLogger(__name__)

RESET_TIME = 0.01  # s from an NMT reset (or power-on) to the boot-up message, real time

NMT_STATE_NAMES = {cia301.NMT_BOOT_UP: "INITIALISING", cia301.NMT_STOPPED: "STOPPED",
                   cia301.NMT_OPERATIONAL: "OPERATIONAL",
                   cia301.NMT_PRE_OPERATIONAL: "PRE-OPERATIONAL"}


def _tuple_getter(keys: tuple) -> "operator.itemgetter":
    """itemgetter(*keys), always giving a tuple (itemgetter of one key gives the value)."""
    getter = operator.itemgetter(*keys)
    return getter if len(keys) > 1 else lambda table: (getter(table),)


_CONTROLWORD = (objects.CONTROLWORD, 0)
_TARGETS = ((objects.TARGET_TORQUE, 0), (objects.TARGET_CURRENT, 0))  # a batch's outputs
_COLUMN = {key: n for n, key in enumerate(LINE_KEYS)}


class _Pdo:
    """One enabled PDO as configured in the dictionary: COB-ID, codec, the objects' keys;
    a TPDO whose objects a batch cycle leaves (`LINE_KEYS`) also packs from the batch's row
    (`of_row`), an RPDO knows where its objects go in a batch's outputs (`outputs_of`)."""

    __slots__ = ("cob_id", "codec", "pack", "keys", "sizes", "values_of", "of_row", "every",
                 "synchronous", "_outputs", "_columns", "controlword_at")

    def __init__(self, cob_id: int, layout: PdoLayout, transmission: int):
        self.cob_id = cob_id
        self.codec = layout.struct
        self.pack = self.codec.pack
        self.keys = tuple((o.index, o.subindex) for o in layout.objects)
        self.sizes = tuple(o.size for o in layout.objects)  # bytes on the wire
        # the values of the mapped objects from the device's value table, always as a tuple
        self.values_of = _tuple_getter(self.keys)
        self.of_row = (_tuple_getter(tuple(_COLUMN[key] for key in self.keys))
                       if all(key in _COLUMN for key in self.keys) else None)
        self.every = transmission if 1 <= transmission <= cia301.SYNC_COUNTER_MAX else 1
        self.synchronous = transmission <= cia301.SYNC_COUNTER_MAX
        self._outputs: tuple | None = None  # the batch outputs `_columns` are for
        self._columns: tuple[int, ...] | None = None
        self.controlword_at = self.keys.index(_CONTROLWORD) if _CONTROLWORD in self.keys else -1

    def outputs_of(self, outputs: tuple) -> tuple[int, ...] | None:
        """Where each of this RPDO's objects is in a batch's `outputs` (None: one is not)."""
        if outputs is not self._outputs:
            self._outputs = outputs
            self._columns = (tuple(outputs.index(key) for key in self.keys)
                             if all(key in outputs for key in self.keys) else None)
        return self._columns


class _CanLine(DriveLine):
    """The batch of one bus's drives, with the outputs its RPDOs brought: the controlword
    and the targets every drive of the bus has (`output_objects`, a row each in
    `output_rows`). Rows in `unapplied` hold an RPDO's values the device has not taken yet;
    they are applied (as the RPDO would have been) before anything reads or changes the
    device (`flush`), or taken by the next batch cycle."""

    def __init__(self, devices: list[Cia402Device]):
        super().__init__(devices)
        count = len(devices)
        self.output_objects = (_CONTROLWORD,) + tuple(
            key for key in _TARGETS if all(has(d.dictionary, *key) for d in devices))
        self.output_rows = np.zeros((len(self.output_objects), count), dtype=np.int64)
        self.controlwords = self.output_rows[0]  # a view, made once
        self.target_rows = list(self.output_rows[1:])
        self._output_views = list(self.output_rows)  # a row's item set costs less
        # per drive, the controlword it acts on when commanded and steady (STEADY; None
        # otherwise): what `take` checks an RPDO against, a Python int (reading it and
        # `_steady` from their arrays cost more than the rest of the check)
        self._held: list[int | None] = [None] * count
        self.unapplied: set[int] = set()
        self.rows = np.arange(count)
        self.load_kernel()

    def _read_terms(self, j: int) -> None:
        super()._read_terms(j)  # settles the device first: an unapplied RPDO is in it now
        self._held[j] = (int(self._controlword[j]) if self._steady[j] == STEADY else None)
        rows = self.output_rows
        rows[0, j] = self._controlword[j]
        for n, key in enumerate(self.output_objects[1:], start=1):
            rows[n, j] = (self.torque_targets[j] if key == _TARGETS[0]
                          else round(self.current_targets[j] * objects.MILLI))

    def take(self, j: int, device: Cia402Device, pdo: _Pdo, values: tuple) -> None:
        """A received RPDO's `values` for row `j`: into the outputs when they repeat what the
        device acts on and nothing changed it since its terms were read, else to the device
        at once."""
        columns = pdo.outputs_of(self.output_objects)
        at = pdo.controlword_at
        held = self._held[j]
        if (columns is None or held is None  # a drive commanded, and its terms steady
                or self._revisions[j] != device.revision + device.plant.revision
                or (at >= 0 and values[at] != held)):
            device.write_outputs(pdo.keys, values)
            return
        views = self._output_views
        for n, value in zip(columns, values, strict=True):
            views[n][j] = value
        self.unapplied.add(j)
        self.pending = True

    def flush(self) -> None:
        super().flush()
        if self.unapplied:
            waiting = sorted(self.unapplied)
            self.unapplied.clear()
            columns = self.output_rows[:, waiting].T.tolist()
            for j, values in zip(waiting, columns, strict=True):
                self.devices[j].write_outputs(self.output_objects, tuple(values))


class CanOpenNode:
    """CANopen node `node_id` on `network`, serving `device`.

    `clock` (`driver.clock.clock_for`) makes the drive's own time (`time`), on which its
    watchdogs and resets run and which each SYNC it takes advances; `silence_timeout` (s,
    None: off): SYNC/RPDO silence after which the master counts as lost.
    """

    def __init__(self, network: canopen.Network, node_id: int, device: Cia402Device, *,
                 clock: Clock, silence_timeout: float | None = DEFAULT_SILENCE_TIMEOUT):
        if not 1 <= node_id <= 127:
            raise ValueError(f"node id {node_id} outside 1..127")
        self.network = network
        self.node_id = node_id
        self.device = device
        self.time = clock.timers()
        self.object_dictionary: ObjectDictionary = device.dictionary  # for canopen's SdoServer
        self.sdo = SdoServer(cia301.SDO_RX_BASE + node_id, cia301.SDO_TX_BASE + node_id, self)
        self.sdo.network = network
        self.emcy = EmcyProducer(cia301.EMCY_BASE + node_id)
        self.emcy.network = network
        self.nmt_state = cia301.NMT_BOOT_UP
        self.sync_count = 0
        self._silent = False
        self._tpdos: list[_Pdo] = []
        self._row_tpdos: list[tuple] | None = None  # see `_start_pdos`
        self._rpdos: dict[int, _Pdo] = {}
        self._latched: list[tuple[_Pdo, tuple[int, ...]]] = []  # synchronous RPDOs
        self._row = 0  # in its bus's batch (`_BusSync`)
        # its TPDOs' (COB-ID, start, stop) in the bus's packed TPDO bytes (`_BusSync`; None:
        # they are packed one by one)
        self._tpdo_frames: tuple[tuple[int, int, int], ...] | None = None
        # a network that sends those frames in one call (`sim_bus.embedded.LinkedNetwork`)
        self._send_slices = getattr(network, "send_slices", None)
        self._heartbeat = HeartbeatProducer(network.send_message, node_id,
                                            lambda: self.nmt_state, self.time)
        self.master_watch = MasterWatch(
            network.subscribe, device.read,
            has(device.dictionary, objects.CONSUMER_HEARTBEAT, 1), device.master_lost,
            self.time, silence_timeout, f"node {node_id}", on_idle=device.run_alone)
        # a SYNC's or an RPDO's call to the watch, only where it has a silence to judge
        self._watches_silence = self.master_watch.watches_silence
        self._counting = has(device.dictionary, objects.SYNC_COUNTER_OVERFLOW)
        self._sync_length_reported = False
        self._late_once = self._twice_once = self._reboot_in_cycle = False
        device.add_emergency_handler(self._send_emcy)
        device.add_fault_handler(self._act_fault)
        network.subscribe(cia301.NMT_COB_ID, self._on_nmt)
        network.subscribe(self.sdo.rx_cobid, self.sdo.on_request)
        self._bus = _BusSync.of(network)
        self._bus.join(self)

    @property
    def nmt_state_name(self) -> str:
        return NMT_STATE_NAMES.get(self.nmt_state, f"0x{self.nmt_state:02X}")

    # --- NMT --------------------------------------------------------------------------------

    def boot(self) -> None:
        """Power-on: boot-up message, then pre-operational with the heartbeat running."""
        self._silent = False
        self._restart()

    def _restart(self) -> None:
        """Initialisation, then the boot-up message, RESET_TIME later in the drive's own time
        (`later`), as a device's reset takes: a master that sends the reset and then starts
        waiting for the boot-up (canopen's documented `wait_for_bootup`) is not outrun by
        it."""
        self._heartbeat.stop()
        self._stop_pdos()
        self.master_watch.rearm()
        self.master_watch.configure()
        self.nmt_state = cia301.NMT_BOOT_UP
        self.time.later(RESET_TIME, self._boot_up)

    def _boot_up(self) -> None:
        if self._silent:
            return
        self.network.send_message(cia301.HEARTBEAT_BASE + self.node_id,
                                  bytes([cia301.NMT_BOOT_UP]))
        self.nmt_state = cia301.NMT_PRE_OPERATIONAL
        self._start_heartbeat()

    def _start_heartbeat(self) -> None:
        self._heartbeat.start(self.device.read(objects.PRODUCER_HEARTBEAT_MS))

    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self._silent or len(data) != 2 or data[1] not in (0, self.node_id):
            return
        command = data[0]
        if command == cia301.NMT_RESET_NODE:
            self.device.reset_application()
            self._restart()
        elif command == cia301.NMT_RESET_COMMUNICATION:
            self.device.reset_communication()
            self._restart()
        elif command == cia301.NMT_START:
            self.nmt_state = cia301.NMT_OPERATIONAL
            self._start_pdos()
        elif command == cia301.NMT_STOP:
            self.nmt_state = cia301.NMT_STOPPED
            self._stop_pdos()
        elif command == cia301.NMT_ENTER_PRE_OPERATIONAL:
            self.nmt_state = cia301.NMT_PRE_OPERATIONAL
            self._stop_pdos()

    # --- PDOs from the dictionary -----------------------------------------------------------

    def _start_pdos(self) -> None:
        self._stop_pdos()
        self._tpdos = self._configured(objects.TPDO_COMM, objects.TPDO_MAP)
        # each SYNC's TPDOs packed from a batch's row, where all can be
        self._row_tpdos = ([(pdo.cob_id, pdo.pack, pdo.of_row) for pdo in self._tpdos]
                           if all(pdo.of_row is not None and pdo.every == 1
                                  for pdo in self._tpdos) else None)
        self._rpdos = {pdo.cob_id: pdo for pdo in
                       self._configured(objects.RPDO_COMM, objects.RPDO_MAP)}
        for cob_id in self._rpdos:
            self.network.subscribe(cob_id, self._on_rpdo)
        self._bus.tpdos_changed()

    def _stop_pdos(self) -> None:
        for cob_id in self._rpdos:
            self.network.unsubscribe(cob_id, self._on_rpdo)
        self._tpdos, self._rpdos, self._latched = [], {}, []
        self.master_watch.stop_silence_watch()
        self._bus.tpdos_changed()

    def _configured(self, comm: int, mapping: int) -> list[_Pdo]:
        """The enabled PDOs as the dictionary holds them now."""
        read, dictionary = self.device.read, self.device.dictionary
        out = []
        for n in range(objects.PDO_CHANNELS):
            if comm + n not in dictionary:
                continue
            cob_id = read(comm + n, 1)
            count = read(mapping + n, 0)
            if cob_id & cia301.PDO_INVALID or count == 0:
                continue
            mapped = tuple(mappable_object(dictionary, read(mapping + n, k))
                           for k in range(1, count + 1))
            out.append(_Pdo(cob_id & cia301.COB_ID_MASK, PdoLayout(0, mapped),
                            read(comm + n, 2)))
        return out

    def _on_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        pdo = self._rpdos.get(can_id)
        if pdo is None or self._silent:
            return
        if len(data) != pdo.codec.size:
            log.warning("node %d: RPDO 0x%03X with %d bytes, %d expected", self.node_id,
                        can_id, len(data), pdo.codec.size)
            return
        if self._watches_silence:
            self.master_watch.activity()
        values = pdo.codec.unpack(data)
        if pdo.synchronous:
            self._latched.append((pdo, values))  # CiA 301: applied at the next SYNC
        else:  # to the bus's batch, which may keep them until the SYNC or hand them over
            self._bus.line.take(self._row, self.device, pdo, values)

    # --- SYNC -------------------------------------------------------------------------------

    def _sync_arrived(self, data: bytearray) -> None:
        """A SYNC this operational node takes (`_BusSync`), before the cycle: the master is
        alive, the SYNC's length is checked, the synchronous RPDOs latched since the last
        one are applied."""
        if self._watches_silence:
            self.master_watch.activity()
        counting = self._counting and self.device.setting(_SYNC_OVERFLOW) > 0
        if len(data) != (1 if counting else 0):
            if not self._sync_length_reported:
                self._sync_length_reported = True
                self._send_emcy(cia301.EMCY_SYNC_LENGTH, cia301.ERROR_REGISTER_COMMUNICATION)
        elif self._sync_length_reported:
            self._sync_length_reported = False
        latched = self._latched
        if latched:
            take, row, device = self._bus.line.take, self._row, self.device
            for pdo, values in latched:
                take(row, device, pdo, values)
            latched.clear()
        self.sync_count += 1
        self._reboot_in_cycle = False

    def _answer(self, row: list[int] | None) -> None:
        """After the cycle: the drive's time advances a period, and its TPDOs go out, packed
        from the batch's `row` of values where the batch ran the cycle (None: from the
        device's objects)."""
        self.time.tick(self.device.period)
        if self._silent or self._reboot_in_cycle:
            return
        count = self.sync_count
        if not (self._twice_once or self._late_once):  # every cycle: no list, no copies
            send = self.network.send_message
            if row is not None and self._row_tpdos is not None:
                for cob_id, pack, of_row in self._row_tpdos:
                    send(cob_id, pack(*of_row(row)))
                return
            table = self.device.values if row is None else None
            for pdo in self._tpdos:
                if pdo.every == 1 or count % pdo.every == 0:
                    send(pdo.cob_id, pdo.pack(*(pdo.values_of(table) if row is None
                                                or pdo.of_row is None
                                                else pdo.of_row(row))))
            return
        table = self.device.values
        frames = [(pdo.cob_id, pdo.pack(*pdo.values_of(table)))
                  for pdo in self._tpdos if count % pdo.every == 0]
        if self._twice_once:
            self._twice_once = False
            frames = frames * 2
        if self._late_once:
            # from another thread, as a drive's late answer: the bus (and, embedded, the
            # master's thread that sent the SYNC) is not held up meanwhile
            self._late_once = False
            late = threading.Timer(TPDO_DELAY, self._send, (frames,))
            late.daemon = True
            late.start()
            return
        self._send(frames)

    def _answer_packed(self, data: bytes, values: np.ndarray) -> None:
        """`_answer` after a batch cycle, the TPDOs cut from the bus's packed TPDO bytes
        `data` where they are laid out there (else from the batch's `values`)."""
        frames = self._tpdo_frames
        if frames is None or self._twice_once or self._late_once:
            self._answer(values[self._row].tolist())
            return
        self.time.tick(self.device.period)
        if self._silent or self._reboot_in_cycle:
            return
        if self._send_slices is not None:
            self._send_slices(data, frames)
            return
        send = self.network.send_message
        for cob_id, start, stop in frames:
            send(cob_id, data[start:stop])

    def _send(self, frames: list[tuple[int, bytes]]) -> None:
        send = self.network.send_message
        for cob_id, payload in frames:
            send(cob_id, payload)

    # --- SDO server (canopen's SdoServer calls these) ---------------------------------------

    def get_data(self, index: int, subindex: int, check_readable: bool = False) -> bytes:
        try:
            return self.device.read_bytes(index, subindex)
        except DeviceAccessError as exc:
            raise SdoAbortedError(exc.abort_code) from None

    def set_data(self, index: int, subindex: int, data: bytes,
                 check_writable: bool = False) -> None:
        if objects.is_pdo_mapping(index):
            self._check_mapping_write(index, subindex, data)
        try:
            self.device.write_bytes(index, subindex, data)
        except DeviceAccessError as exc:
            raise SdoAbortedError(exc.abort_code) from None
        if index == objects.PRODUCER_HEARTBEAT_MS:
            self._start_heartbeat()
        elif index == objects.CONSUMER_HEARTBEAT or index == objects.CYCLE_PERIOD_US:
            self.master_watch.configure()

    def _check_mapping_write(self, index: int, subindex: int, data: bytes) -> None:
        """What CAN adds to the device's own checks: no remapping while the PDOs run, and at
        most 8 bytes in a frame."""
        if self.nmt_state == cia301.NMT_OPERATIONAL:
            raise SdoAbortedError(cia301.SDO_ABORT_WRONG_STATE)
        if subindex == 0 and data:
            count = data[0]
            read = self.device.read
            bits = sum(read(index, k) & 0xFF for k in range(1, count + 1)
                       if (index, k) in self.device.dictionary[index])
            if bits > 8 * cia301.PDO_MAX_BYTES:
                raise SdoAbortedError(cia301.SDO_ABORT_PDO_LENGTH)

    # --- emergencies and faults -------------------------------------------------------------

    def _send_emcy(self, code: int, register: int) -> None:
        if self._silent:
            return
        if code == cia301.EMCY_NO_ERROR:
            self.emcy.reset(register)
        else:
            self.emcy.send(code, register)

    def _act_fault(self, fault: Fault) -> None:
        if fault is Fault.HEARTBEAT_STOPS:
            self.stop_heartbeat()
        elif fault is Fault.SILENT:
            self.go_silent()
        elif fault is Fault.TPDO_LATE:
            self._late_once = True
        elif fault is Fault.TPDO_TWICE:
            self._twice_once = True
        elif fault is Fault.BUS_FLOOD:
            threading.Thread(target=self._flood, daemon=True, name="bus-flood").start()
        elif fault is Fault.REBOOT:
            # a power glitch: application and communication restart, boot-up, disabled
            self._reboot_in_cycle = True
            self.device.reset_application()
            self._restart()
        elif fault is Fault.LEAVES_OP:
            log.warning("fault %s is EtherCAT's: a CANopen drive has no OP to leave",
                        fault.name.lower())
        elif fault is Fault.FRAME_LOST:
            log.warning("fault %s is EtherCAT's: a CANopen bus has no line-wide frame to lose",
                        fault.name.lower())

    def _flood(self) -> None:
        end = time.monotonic() + FLOOD_SECONDS
        while time.monotonic() < end:
            self.network.send_message(FLOOD_COB_ID, bytes(8))

    def stop_heartbeat(self) -> None:
        """Fault injection: the heartbeat producer dies while the rest keeps working."""
        self._heartbeat.stop()

    def go_silent(self) -> None:
        """Fault injection: the node disappears from the bus (power loss, cable cut)."""
        self._silent = True
        self._heartbeat.stop()
        self.master_watch.close()

    def close(self) -> None:
        self._heartbeat.stop()
        self.master_watch.close()
        self._stop_pdos()
        self._bus.leave(self)
        self.network.unsubscribe(cia301.NMT_COB_ID, self._on_nmt)
        self.network.unsubscribe(self.sdo.rx_cobid, self.sdo.on_request)


class _BusSync:
    """The SYNC of one network for every virtual drive on it, in one pass: each node's
    checks, the steady drives' cycles in one batch call, the others'
    `Cia402Device.cycle()`, then each node's time and TPDOs in node order."""

    def __init__(self, network: canopen.Network):
        self.network = network
        self.nodes: list[CanOpenNode] = []
        self.line: _CanLine | None = None  # from the first drive's `join` on
        # where each batch-packable TPDO's objects go in the bus's TPDO bytes (`pack_values`),
        # and those bytes; None: to be laid out again (the nodes or their PDOs changed)
        self._packing: tuple[np.ndarray, np.ndarray] | None = None
        network.subscribe(cia301.SYNC_COB_ID, self._on_sync)

    @staticmethod
    def of(network: canopen.Network) -> "_BusSync":
        """The network's (made with its first virtual drive)."""
        bus = getattr(network, "_virtual_drives_sync", None)
        if bus is None:
            bus = network._virtual_drives_sync = _BusSync(network)
        return bus

    def join(self, node: CanOpenNode) -> None:
        self.nodes.append(node)
        self._rebuild()

    def leave(self, node: CanOpenNode) -> None:
        if node in self.nodes:
            self.nodes.remove(node)
        if self.nodes:
            self._rebuild()
            return
        if self.line is not None and self.line.pending:
            self.line.flush()
        self.network.unsubscribe(cia301.SYNC_COB_ID, self._on_sync)
        del self.network._virtual_drives_sync

    def _rebuild(self) -> None:
        """A batch of the nodes' drives now (each drive's state moves into its rows)."""
        if self.line is not None and self.line.pending:
            self.line.flush()
        self.line = _CanLine([node.device for node in self.nodes])
        for j, node in enumerate(self.nodes):
            node._row = j
        self._packing = None

    def tpdos_changed(self) -> None:
        """A node's TPDOs started or stopped: they are laid out again before the next SYNC."""
        self._packing = None

    def _lay_out(self) -> tuple[np.ndarray, np.ndarray]:
        """The bus's TPDO bytes: each node's TPDOs that are packed from its batch row, one
        after the other (a node's others: `_tpdo_frames` None)."""
        fields, at = [], 0
        for node in self.nodes:
            if node._row_tpdos is None or not node._tpdos:
                node._tpdo_frames = None
                continue
            frames = []
            for pdo in node._tpdos:
                start = at
                for key, size in zip(pdo.keys, pdo.sizes, strict=True):
                    fields.append((node._row, _COLUMN[key], at, size))
                    at += size
                frames.append((pdo.cob_id, start, at))
            node._tpdo_frames = tuple(frames)
        self._packing = (np.array(fields, dtype=np.int64).reshape(-1, 4),
                         np.zeros(at, dtype=np.uint8))
        return self._packing

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        operational = cia301.NMT_OPERATIONAL
        nodes = [node for node in self.nodes
                 if not node._silent and node.nmt_state == operational]
        if not nodes:
            return
        counter = data[0] if data else 0
        for node in nodes:
            node._sync_arrived(data)
        line = self.line
        rows = (line.rows if len(nodes) == len(self.nodes)
                else np.array([node._row for node in nodes]))
        # the cycle packs its values into the bus's TPDO bytes too, in the same call
        fields, packed = self._packing or self._lay_out()
        done = line.cycle(rows, line.controlwords, line.output_objects, line.target_rows,
                          counter, fields=fields, packed=packed)
        values = line.values
        if line.ran == len(nodes):  # nearly always: every node's cycle was the batch's
            line.unapplied.clear()
            data = packed.tobytes()
            for node in nodes:
                node._answer_packed(data, values)
            line.renew_draws()  # after the answers: a few drives' a cycle, not all in one
            return
        done = done.tolist()
        unapplied = line.unapplied
        if unapplied:  # what the batch took is applied; the others' devices take theirs
            if all(done):
                unapplied.clear()
            else:
                unapplied.difference_update(
                    j for j, ran in zip(rows.tolist(), done, strict=True) if ran)
        # every ran drive's TPDOs packed by the cycle (a drive's own cycle: it packs its
        # own), cut into frames by each node
        data = packed.tobytes()
        for node, ran in zip(nodes, done, strict=True):
            if ran:
                node._answer_packed(data, values)
            else:
                node.device.cycle(counter)
                node._answer(None)


_SYNC_OVERFLOW = (objects.SYNC_COUNTER_OVERFLOW, 0)
