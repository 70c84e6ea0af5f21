"""The CANopen master's cycle, once per CAN bus: RPDOs out, one SYNC, the TPDOs that answer it.

A `BusCycle` is the bus's, whatever the number of drives on it: each drive's transport joins
it at construction (taking a row) and hands it its PDO plan when mapped. Everything per frame
is prepared then, looked up by COB-ID: a received TPDO is copied, as the bytes it carries, into
its drive's row of the bus's input image (one slice assignment, no decoding in the receive
path); the cycle then decodes every row at once (one compiled call, `driver.process_image`),
or one row alone for a drive's own `sync` (one `struct.unpack_from`). Each cycle sends one
SYNC for every drive and advances the bus's clock by a period (`driver.clock`: drive time
passes as the drives cycle; the wall clock passes on its own).

Freshness: a TPDO counts for cycle k only if it answers SYNC k. Where the drive echoes the SYNC
counter (0x2004 in the first TPDO, the elbow drive), the echo decides, and the TPDOs behind it
follow it in order on the bus. Otherwise the frame's bus timestamp (python-can's: the kernel's
receive time on SocketCAN and udp_multicast; the send time on an in-process link) must lie
inside the synchronous window (0x1007) after SYNC k: a frame that reached us before SYNC k went
out (a late or doubled answer to SYNC k-1 crossing it) is refused, and so is one after the
window. The window is the master's response timeout: the master sends SYNC k+1 only after the
answer to k, so anything inside the window answers k, and a tighter window only turns a slow
host's late answer into a lost cycle (here, between Python processes on udp_multicast, 5 % of
answers take over 1 ms under load). Second copies are counted and never mixed in.
"""

import struct
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass

import canopen
import numpy as np

from driver.canopen_health import BusWatch
from driver.clock import Clock
from driver.interface import DriveError, DriveTimeout
from driver.process_image import INPUTS, OUTPUTS, code
from protocol import cia301
from protocol.pdo import PdoLayout

_ATTRIBUTE = "_actuator_link_bus_cycle"  # where a network keeps its BusCycle


@dataclass(frozen=True)
class PlannedPdo:
    """One PDO of the plan: channel n (0x1400/0x1800 + n), COB-ID, objects in wire order,
    and which slice of the inputs (or outputs) it carries. With `echo`, the layout's last
    object is the SYNC counter echo, not one of the inputs."""

    channel: int
    cob_id: int
    layout: PdoLayout
    start: int
    stop: int
    echo: bool = False


# the SYNC's data for each counter value (a bytes object made once, not one per cycle)
_SYNC_DATA = tuple(bytes([counter]) for counter in range(cia301.SYNC_COUNTER_MAX + 1))


@dataclass
class _Row:
    """One drive's place on the bus: its name and warnings (the transport's), its failure,
    its PDOs, where its TPDOs' bytes go in the input image and how to read them back."""

    name: str
    warnings: list[str]
    failure: DriveError | None = None
    rpdos: tuple[tuple[int, struct.Struct, int, int], ...] = ()
    # per TPDO: COB-ID, offset in the row, size, the echo's struct and offset (or None, 0)
    tpdos: tuple[tuple[int, int, int, struct.Struct | None, int], ...] = ()
    size: int = 0  # bytes of its TPDOs (the echo included)
    inputs: struct.Struct = struct.Struct("")  # the row's bytes as its inputs (echo skipped)
    # per input in plan order: (offset in the row, `driver.process_image.code`)
    input_fields: tuple[tuple[int, int], ...] = ()
    # per RPDO: its COB-ID and per output it carries (output index, size, signed)
    rpdo_fields: tuple[tuple[int, tuple[tuple[int, int, bool], ...]], ...] = ()
    window: float | None = None  # s, judged where the drive has a window and no echo
    counting: bool = False


class BusCycle:
    """The cycle of every drive on one canopen `network`, with the bus's `watch`."""

    @classmethod
    def of(cls, network: canopen.Network, clock: Clock,
           response_timeout: float) -> "BusCycle":
        """The network's cycle, made with its first drive (whose clock and response timeout
        it keeps), kept on the network as its `BusWatch` is."""
        cycle = getattr(network, _ATTRIBUTE, None)
        if cycle is None:
            cycle = cls(network, BusWatch.of(network, clock), response_timeout)
            setattr(network, _ATTRIBUTE, cycle)
        return cycle

    def __init__(self, network: canopen.Network, watch: BusWatch, response_timeout: float):
        self.network = network
        # a network that lets the waiting thread read its frames itself
        # (`driver.canopen_multicast`), looked up once
        self._receive_until = getattr(network, "receive_until", None)
        # a network that sends several frames cut from one buffer in one call
        # (`sim_bus.embedded.LinkedNetwork`), looked up once
        self._send_slices = getattr(network, "send_slices", None)
        self.watch = watch
        self.clock = watch.clock
        self.response_timeout = response_timeout
        self.period = 0.0
        self.cycle = 0
        self.rows: list[_Row] = []
        self.failed = False  # some row has a failure: the bus's cycle stops
        # a row failed or a drive reported an emergency since a segment last looked: one
        # look a cycle instead of one per drive (`driver.drive_group.CanOpenBus`)
        self.alarm = False
        self.blamed = 0  # the row whose failure was raised last (a segment names its joint)
        self._stride = 0  # bytes per row of the input image
        self._image = bytearray()
        self.image = np.frombuffer(self._image, np.uint8)  # the same bytes, for numpy
        # COB-ID -> (row, offset in the image, size, echo struct and offset or None)
        self._tpdos: dict[int, tuple[int, int, int, struct.Struct | None, int]] = {}
        self._open: list[bool] = []  # per row: its echo named this cycle's SYNC
        self._open_at_sync: list[bool] = []  # per row: it has no echo (open at each SYNC)
        self._pending: set[int] = set()
        self._all_tpdos: frozenset[int] = frozenset()
        self._counter = 0  # 1..240 in each SYNC when a drive counts SYNCs (0x1019)
        self._counting = False
        self._sync_stamp = 0.0
        # the frame handler takes the bare lock (a Condition's own `with` costs two Python
        # calls per frame); only the wait for the last TPDO needs the condition
        self._lock = threading.Lock()
        self._arrived = threading.Condition(self._lock)
        # collect() is waiting: only then does the last TPDO notify (embedded in lock-step the
        # TPDOs arrive inside the SYNC's send, and a Condition's notify costs 5 Python calls)
        self._waiting = False

    # --- drives join, map, leave ------------------------------------------------------------

    def join(self, name: str, warnings: list[str]) -> int:
        """A drive on this bus; returns its row."""
        self.rows.append(_Row(name, warnings))
        self._prepare()
        return len(self.rows) - 1

    def configure(self, row: int, rpdos: Sequence[PlannedPdo], tpdos: Sequence[PlannedPdo],
                  counting: bool, window: float | None, period: float) -> None:
        """Take drive `row`'s mapped PDOs; `counting`: it counts SYNCs (0x1019 set), so SYNCs
        carry the counter byte; `window`: s, its synchronous window (None: none); `period`:
        s, the cycle's."""
        entry = self.rows[row]
        self._unsubscribe(entry)
        formats, fields, placed, offset = [], {}, [], 0
        for pdo in tpdos:
            echo, echo_at = None, 0
            at = offset
            for k, obj in enumerate(pdo.layout.objects):
                char = pdo.layout.struct.format[1 + k]
                if pdo.echo and k == len(pdo.layout.objects) - 1:
                    formats.append(f"{obj.size}x")
                    echo, echo_at = struct.Struct("<" + char), offset - at
                else:
                    formats.append(char)
                    fields[pdo.start + k] = (offset, code(obj.size, obj.signed))
                offset += obj.size
            placed.append((pdo.cob_id, at, offset - at, echo, echo_at))
        entry.rpdos = tuple((p.cob_id, p.layout.struct, p.start, p.stop) for p in rpdos)
        entry.tpdos = tuple(placed)
        entry.size = offset
        entry.inputs = struct.Struct("<" + "".join(formats))
        entry.input_fields = tuple(fields[k] for k in sorted(fields))
        entry.rpdo_fields = tuple(
            (p.cob_id, tuple((p.start + k, obj.size, obj.signed)
                             for k, obj in enumerate(p.layout.objects))) for p in rpdos)
        entry.window = None if any(p.echo for p in tpdos) else window
        entry.counting = counting
        self.period = period
        self._prepare()
        self.clear(row)
        for cob_id, *_ in entry.tpdos:
            self.network.subscribe(cob_id, self._on_tpdo)
        self.watch.expect_cyclic_frames(self.frames_per_cycle)

    def leave(self, row: int) -> None:
        """Drive `row` takes no more part in the cycle."""
        entry = self.rows[row]
        self._unsubscribe(entry)
        entry.rpdos, entry.tpdos, entry.size = (), (), 0
        self._prepare()

    def _unsubscribe(self, entry: _Row) -> None:
        for cob_id, *_ in entry.tpdos:
            self.network.unsubscribe(cob_id, self._on_tpdo)

    def _prepare(self) -> None:
        """The input image and the look-up by COB-ID, laid out again for the rows as they
        are now (at bring-up only)."""
        stride = max((r.size for r in self.rows), default=0)
        tpdos = {cob_id: (n, n * stride + at, size, echo, echo_at)
                 for n, entry in enumerate(self.rows)
                 for cob_id, at, size, echo, echo_at in entry.tpdos}
        with self._lock:
            self._stride = stride
            self._image = bytearray(stride * len(self.rows))
            self.image = np.frombuffer(self._image, np.uint8)
            self._tpdos = tpdos
            self._all_tpdos = frozenset(tpdos)
            self._open_at_sync = [not any(p[3] for p in r.tpdos) for r in self.rows]
            self._open = self._open_at_sync[:]
            self._counting = any(r.counting for r in self.rows)

    @property
    def frames_per_cycle(self) -> int:
        """The bus's cyclic frames: the SYNC and every drive's PDOs."""
        return 1 + sum(len(r.rpdos) + len(r.tpdos) for r in self.rows)

    # --- failures ---------------------------------------------------------------------------

    def fail(self, row: int, error: DriveError) -> None:
        """Record what ended drive `row`'s link and wake a collect waiting for TPDOs that
        will not come (first failure wins)."""
        with self._arrived:
            if self.rows[row].failure is None:
                self.rows[row].failure = error
            self.failed = self.alarm = True
            self._arrived.notify_all()

    def clear(self, row: int) -> None:
        """Drive `row` starts afresh (booted again): its failure is forgotten."""
        with self._lock:
            self.rows[row].failure = None
            self.failed = any(r.failure is not None for r in self.rows)

    def _raise_failure(self) -> None:
        for n, entry in enumerate(self.rows):
            if entry.failure is not None:
                self.blamed = n
                raise entry.failure

    # --- the cycle --------------------------------------------------------------------------

    def trigger(self) -> None:
        """Expect the TPDOs that answer the next SYNC, send it (the counter byte where a
        drive counts SYNCs), and let a period of the clock pass. A failed drive stops the
        bus's cycle: raised here, `blamed` its row."""
        if self.failed:
            self._raise_failure()
        with self._lock:
            self._pending = set(self._all_tpdos)
            if self._counting:
                self._counter = self._counter % cia301.SYNC_COUNTER_MAX + 1
            # without an echo every TPDO after this SYNC answers it (within the window)
            self._open[:] = self._open_at_sync
            self._sync_stamp = time.time()  # the clock python-can stamps frames with
        self.network.send_message(cia301.SYNC_COB_ID,
                                  _SYNC_DATA[self._counter] if self._counting else b"")
        self.clock.advance(self.period)

    def collect(self) -> None:
        """Wait (up to the response timeout) for every TPDO answering the SYNC, then the
        bus's once-a-cycle jobs (`BusWatch.count_cycle`). A missing TPDO fails its drive."""
        receive = self._receive_until
        if receive is not None and self._pending and not self.failed:
            # the waiting thread reads the frames itself: no hand-over from a receive thread
            receive(lambda: not self._pending or self.failed, self.response_timeout)
        with self._lock:  # the condition's lock (its own `with` costs two Python calls)
            if self._pending and not self.failed and receive is None:
                self._waiting = True
                try:
                    self._arrived.wait_for(lambda: not self._pending or self.failed,
                                           self.response_timeout)
                finally:
                    self._waiting = False
            if self._pending:
                if self.failed:
                    self._raise_failure()  # a reboot or a lost heartbeat ended the wait
                row, _ = min(self._tpdos[c][:2] for c in self._pending)
                entry = self.rows[row]
                missing = ", ".join(f"0x{c:03X}" for c in sorted(self._pending)
                                    if self._tpdos[c][0] == row)
                entry.failure = DriveTimeout(
                    f"{entry.name}: no TPDO {missing} within {self.response_timeout * 1e3:.0f} "
                    f"ms of SYNC {self.cycle + 1}")
                self.failed = self.alarm = True
                self.blamed = row
                raise entry.failure
            self.cycle += 1
        self.watch.count_cycle(self.rows[0].warnings)

    def exchange(self) -> None:
        """One cycle of the bus: trigger, collect."""
        self.trigger()
        self.collect()

    def inputs(self, row: int) -> tuple[int, ...]:
        """Drive `row`'s inputs of the last cycle, in its plan's order."""
        return self.rows[row].inputs.unpack_from(self._image, row * self._stride)

    def input_layout(self, rows: Sequence[int]) -> np.ndarray:
        """Where the inputs of drives `rows` sit in `image`: a `driver.process_image` layout
        (per row: offset and code of each input; code 0 where the drive lacks it)."""
        layout = np.zeros((len(rows), 2 * INPUTS), dtype=np.int64)
        for n, row in enumerate(rows):
            for k, (offset, kind) in enumerate(self.rows[row].input_fields):
                layout[n, 2 * k:2 * k + 2] = row * self._stride + offset, kind
        return layout

    def output_layout(self, rows: Sequence[int]
                      ) -> tuple[np.ndarray, list[tuple[int, int, int]], int]:
        """Where the outputs of drives `rows` go in an output image of their RPDOs laid end
        to end: the `driver.process_image` layout, each RPDO's (COB-ID, start, stop) in the
        image, and its size in bytes."""
        layout = np.zeros((len(rows), 2 * OUTPUTS), dtype=np.int64)
        frames, at = [], 0
        for n, row in enumerate(rows):
            for cob_id, fields in self.rows[row].rpdo_fields:
                start = at
                for k, size, signed in fields:
                    layout[n, 2 * k:2 * k + 2] = at, code(size, signed)
                    at += size
                frames.append((cob_id, start, at))
        return layout, frames, at

    def send(self, row: int, outputs: Sequence[int]) -> None:
        """Drive `row`'s RPDOs with `outputs` (in its plan's order)."""
        send = self.network.send_message
        for cob_id, codec, start, stop in self.rows[row].rpdos:
            send(cob_id, codec.pack(*outputs[start:stop]))

    def send_frames(self, data: bytes, frames: Sequence[tuple[int, int, int]]) -> None:
        """RPDOs out of an output image (`output_layout`): each frame's slice of `data`."""
        if self._send_slices is not None:
            self._send_slices(data, frames)
            return
        send = self.network.send_message
        for cob_id, start, stop in frames:
            send(cob_id, data[start:stop])

    def _on_tpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        row, at, size, echo, echo_at = self._tpdos[can_id]
        if len(data) != size:
            self.rows[row].warnings.append(f"TPDO 0x{can_id:03X} with {len(data)} bytes, "
                                           f"{size} expected")
            return
        with self._lock:
            if echo is not None:
                # the first TPDO names its SYNC; the others follow it in order on the bus
                self._open[row] = echo.unpack_from(data, echo_at)[0] == self._counter
            elif (window := self.rows[row].window) is not None:
                delay = timestamp - self._sync_stamp
                if delay < 0 or delay > window:
                    self.rows[row].warnings.append(
                        f"TPDO 0x{can_id:03X} {delay * 1e3:+.2f} ms from SYNC, outside the "
                        f"{window * 1e3:.0f} ms synchronous window: not this cycle's")
                    return
            if can_id not in self._pending or not self._open[row]:
                # a second copy, or a frame from an earlier cycle: never mix it in
                self.rows[row].warnings.append(
                    f"unexpected TPDO 0x{can_id:03X} (duplicate or late)")
                return
            self._image[at:at + size] = data
            self._pending.discard(can_id)
            if not self._pending and self._waiting:
                self._arrived.notify_all()

    def close(self) -> None:
        for entry in self.rows:
            self._unsubscribe(entry)
            entry.tpdos = ()
