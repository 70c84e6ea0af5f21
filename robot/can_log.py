"""CAN logging as a python-can bus wrapper: every frame a master (or a virtual drive) sends or
receives, written in order by python-can's writer for the file's suffix (.log, .asc, .blf,
...). A library piece, so a program that opens drives without the command line can log its
bus the same way `--can-log` does."""

from __future__ import annotations

import collections
import copy
import threading
import time
from collections.abc import Callable

import can
import canopen

from protocol.cia301 import SYNC_COB_ID

# a frame after SYNC k is stamped at most this fraction of a period after it, so it stays
# before SYNC k+1 however long the host took in lock-step
LATEST_IN_CYCLE = 0.9


class CanLog:
    """`--can-log`: every frame this process sends or receives, written in order by
    python-can's writer for the file's suffix."""

    def __init__(self, path: str, channel: str) -> None:
        self._writer = can.Logger(path)
        self._channel = channel  # named in the file for frames that carry none (those sent)
        # the receive thread and the control thread both log; reentrant: a sender holds it
        # across the send and the write of its frame (see `sending`)
        self._lock = threading.RLock()
        self._open = True
        self._period: Callable[[], float] | None = None  # drive time: see use_drive_time
        self._sync_stamp: float | None = None
        self._sync_wall = 0.0

    def sending(self) -> threading.RLock:
        """Hold while sending a frame and logging it: an answer the receive thread gets before
        `send` returns then waits, and is logged after its question, as on the wire."""
        return self._lock

    def use_drive_time(self, period: Callable[[], float]) -> None:
        """Stamp frames on the run's time base instead of the wall clock, for a lock-step
        link where the drive advances `period()` seconds per SYNC whatever the wall clock
        does: the first SYNC at its wall-clock time, each next one a period later, and a frame
        after SYNC k at SYNC k plus the wall time since it (at most 0.9 of a period). The log
        then replays at the drive's pace (2 s of drive time in 2 s) and keeps its order.
        Frames before the first SYNC (bring-up) keep the wall clock."""
        self._period = period

    def _stamp(self, msg: can.Message, now: float) -> float:
        """The frame's time on the run's time base (see use_drive_time); under the lock."""
        if msg.arbitration_id == SYNC_COB_ID:
            self._sync_stamp = (now if self._sync_stamp is None
                                else self._sync_stamp + self._period())
            self._sync_wall = now
            return self._sync_stamp
        if self._sync_stamp is None:
            return now
        return self._sync_stamp + min(now - self._sync_wall, LATEST_IN_CYCLE * self._period())

    def write(self, msg: can.Message, is_rx: bool) -> None:
        logged = copy.copy(msg)
        logged.is_rx = is_rx
        if logged.channel is None:
            logged.channel = self._channel
        if not is_rx or not logged.timestamp:
            logged.timestamp = time.time()  # frames being sent carry no time yet
        with self._lock:
            if self._open:
                if self._period is not None:
                    logged.timestamp = self._stamp(logged, logged.timestamp)
                self._writer.on_message_received(logged)

    def stop(self) -> None:
        """Finish the file; idempotent."""
        with self._lock:
            if self._open:
                self._open = False
                self._writer.stop()


class LoggedBus(can.BusABC):
    """A python-can bus that hands every frame it sends or receives to a CanLog, periodic
    frames included (python-can's thread-based periodic sender goes through `send`).

    Some interfaces hand a sender its own frames back (udp_multicast does, on one host): such
    an echo is logged once, as sent, so the file reads like a capture of the bus. A CANopen
    COB-ID has one sender, so a frame equal to one of ours just sent is our echo."""

    ECHO_WINDOW = 64  # frames sent whose echo may still come

    def __init__(self, bus: can.BusABC, can_log: CanLog) -> None:
        self._bus, self._log = bus, can_log
        self._sent: collections.deque = collections.deque(maxlen=self.ECHO_WINDOW)
        self._sent_lock = threading.Lock()
        super().__init__(channel=None)
        self.channel_info = bus.channel_info

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        with self._sent_lock:
            self._sent.append((msg.arbitration_id, bytes(msg.data)))
        with self._log.sending():
            self._bus.send(msg, timeout)
            self._log.write(msg, is_rx=False)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        msg = self._bus.recv(timeout)  # filtered by the bus itself
        if msg is not None:
            frame = (msg.arbitration_id, bytes(msg.data))
            with self._sent_lock:
                echo = frame in self._sent
                if echo:
                    self._sent.remove(frame)
            if not echo:
                self._log.write(msg, is_rx=True)
        return msg, True

    def shutdown(self) -> None:
        super().shutdown()
        self._bus.shutdown()


def tap_link(master_network: canopen.Network, drive_network: canopen.Network,
             can_log: CanLog, period: Callable[[], float] | None = None) -> None:
    """Log the `--sim` link (sim_bus.embedded.LinkedNetwork: each side hands a frame to its
    peers in turn, in the sender's thread). The taps go first among the peers: the other
    side answers a frame inside its `notify` (a SYNC's TPDOs are sent before the SYNC's
    `send` returns), so a tap after it would log the answer before the question. `period`
    (lock-step): stamp on drive time (CanLog.use_drive_time)."""
    master_network.peers.insert(0, LinkTap(can_log, is_rx=False))
    drive_network.peers.insert(0, LinkTap(can_log, is_rx=True))
    if period is not None:
        can_log.use_drive_time(period)


class LinkTap:
    """A peer on one side of the --sim link (sim_bus.embedded.LinkedNetwork hands every frame
    its network sends to its peers' `notify`): what that side sends goes to the log, the
    master's frames as sent (Tx), the drive's as received (Rx). Placed by `tap_link`."""

    def __init__(self, can_log: CanLog, is_rx: bool) -> None:
        self._log, self._is_rx = can_log, is_rx

    def notify(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self._log.write(can.Message(timestamp=timestamp, arbitration_id=can_id,
                                    is_extended_id=can_id > 0x7FF, data=bytes(data)),
                        self._is_rx)
