"""The CANopen master's cycle: RPDOs out, one SYNC, the TPDOs that answer it back.

Everything per frame is prepared when the PDOs are mapped: a `struct.Struct` and the slice of
the input (or output) tuple each PDO carries, looked up by COB-ID. A received TPDO is one
unpack and one slice assignment; a cycle builds no dicts.

Freshness: a TPDO counts for cycle k only if it answers SYNC k. Where the drive echoes the SYNC
counter (0x2004 in the first TPDO, the elbow drive), the echo decides, and the TPDOs behind it
follow it in order on the bus. Otherwise the frame's bus timestamp (python-can's: the kernel's
receive time on SocketCAN and udp_multicast) must lie inside the synchronous window (0x1007)
after SYNC k: a frame that reached us before SYNC k went out (a late or doubled answer to SYNC
k-1 crossing it) is refused, and so is one after the window. The window is the master's
response timeout: the master sends SYNC k+1 only after the answer to k, so anything inside the
window answers k, and a tighter window only turns a slow host's late answer into a lost cycle
(here, between Python processes on udp_multicast, 5 % of answers take over 1 ms under load). In
lock-step the window's end is not judged (wall time means nothing there). Second copies are
counted and never mixed in.
"""

import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass

import canopen

from driver.interface import DriveError, DriveTimeout
from protocol import cia301
from protocol.pdo import PdoLayout


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


class SyncCycle:
    def __init__(self, network: canopen.Network, name: str, *, lockstep: bool,
                 response_timeout: float, warnings: list[str]):
        self.network = network
        self.name = name
        self.lockstep = lockstep
        self.response_timeout = response_timeout
        self.cycle = 0
        self.warnings = warnings  # shared with the transport, drained by the CiA 402 layer
        self.failure: DriveError | None = None
        self._rpdos: list[tuple[int, object, int, int]] = []
        self._tpdos: dict[int, tuple[object, int, int, bool]] = {}
        self._all_tpdos: frozenset[int] = frozenset()
        self._inputs: list[int] = []
        self._pending: set[int] = set()
        self._counter = 0  # 1..240 in each SYNC when the drive counts SYNCs (0x1019)
        self._counting = False
        self._has_echo = False
        self._window: float | None = None
        self._open = False
        self._sync_stamp = 0.0
        # the frame handlers take the bare lock (a Condition's own `with` costs two Python
        # calls per frame); only the wait for the last TPDO needs the condition
        self._lock = threading.Lock()
        self._arrived = threading.Condition(self._lock)
        # collect() is waiting: only then does the last TPDO notify (embedded in lock-step the
        # TPDOs arrive inside the SYNC's send, and a Condition's notify costs 5 Python calls)
        self._waiting = False

    def configure(self, rpdos: Sequence[PlannedPdo], tpdos: Sequence[PlannedPdo],
                  inputs: int, counting: bool, window: float | None) -> None:
        """Take the mapped PDOs; `counting`: SYNCs carry the counter byte (0x1019 set);
        `window`: s, the synchronous window (None: none)."""
        for cob_id in self._tpdos:
            self.network.unsubscribe(cob_id, self._on_tpdo)
        self._rpdos = [(p.cob_id, p.layout.struct, p.start, p.stop) for p in rpdos]
        self._tpdos = {p.cob_id: (p.layout.struct, p.start, p.stop, p.echo) for p in tpdos}
        self._all_tpdos = frozenset(self._tpdos)
        self._inputs = [0] * inputs
        self._counting = counting
        self._window = window
        self._has_echo = any(p.echo for p in tpdos)
        for cob_id in self._tpdos:
            self.network.subscribe(cob_id, self._on_tpdo)

    @property
    def frames_per_cycle(self) -> int:
        """This drive's PDOs in one cycle (the SYNC apart)."""
        return len(self._rpdos) + len(self._tpdos)

    def send(self, outputs: Sequence[int]) -> None:
        send = self.network.send_message
        for cob_id, codec, start, stop in self._rpdos:
            send(cob_id, codec.pack(*outputs[start:stop]))

    def fail(self, error: DriveError) -> None:
        """Record what ended the link and wake an exchange waiting for TPDOs that will not
        come (first failure wins)."""
        with self._arrived:
            if self.failure is None:
                self.failure = error
            self._arrived.notify_all()

    def exchange(self) -> tuple[int, ...]:
        """One cycle of this drive alone: arm, send its SYNC, collect."""
        self.network.send_message(cia301.SYNC_COB_ID, self.arm())
        return self.collect()

    def arm(self) -> bytes:
        """Expect the TPDOs that answer the next SYNC; returns that SYNC's data (the counter
        byte where the drive counts SYNCs). Split from `collect` so that several drives on
        one bus can share one SYNC (`driver.drive_group`): arm each, send one SYNC, collect
        each."""
        if self.failure is not None:
            raise self.failure
        with self._lock:
            self._pending = set(self._all_tpdos)
            if self._counting:
                self._counter = self._counter % cia301.SYNC_COUNTER_MAX + 1
            # without an echo every TPDO after this SYNC answers it (within the window)
            self._open = not self._has_echo
            self._sync_stamp = time.time()  # the clock python-can stamps frames with
        return _SYNC_DATA[self._counter] if self._counting else b""

    def collect(self) -> tuple[int, ...]:
        """The inputs answering the armed SYNC, waiting up to the response timeout."""
        with self._lock:  # the condition's lock (its own `with` costs two Python calls)
            if self._pending and self.failure is None:
                self._waiting = True
                try:
                    self._arrived.wait_for(lambda: not self._pending or self.failure is not None,
                                           self.response_timeout)
                finally:
                    self._waiting = False
            if self._pending:
                if self.failure is not None:
                    raise self.failure  # a reboot or a lost heartbeat ended the wait
                missing = ", ".join(f"0x{c:03X}" for c in sorted(self._pending))
                self.failure = DriveTimeout(
                    f"{self.name}: no TPDO {missing} within {self.response_timeout * 1e3:.0f} "
                    f"ms of SYNC {self.cycle + 1}")
                raise self.failure
            self.cycle += 1
            return tuple(self._inputs)

    def _on_tpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        codec, start, stop, echo = self._tpdos[can_id]
        if len(data) != codec.size:
            self.warnings.append(f"TPDO 0x{can_id:03X} with {len(data)} bytes, "
                                 f"{codec.size} expected")
            return
        values = codec.unpack(data)
        with self._lock:
            if echo:
                # the first TPDO names its SYNC; the others follow it in order on the bus
                self._open = values[-1] == self._counter
            elif self._window is not None and not self._has_echo:
                delay = timestamp - self._sync_stamp
                if delay < 0 or delay > self._window and not self.lockstep:
                    self.warnings.append(f"TPDO 0x{can_id:03X} {delay * 1e3:+.2f} ms from SYNC, "
                                         f"outside the {self._window * 1e3:.0f} ms synchronous "
                                         "window: not this cycle's")
                    return
            if can_id not in self._pending or not self._open:
                # a second copy, or a frame from an earlier cycle: never mix it in
                self.warnings.append(f"unexpected TPDO 0x{can_id:03X} (duplicate or late)")
                return
            self._inputs[start:stop] = values[:stop - start]
            self._pending.discard(can_id)
            if not self._pending and self._waiting:
                self._arrived.notify_all()

    def close(self) -> None:
        for cob_id in self._tpdos:
            self.network.unsubscribe(cob_id, self._on_tpdo)
        self._tpdos = {}
