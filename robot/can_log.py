"""CAN logging as a python-can bus wrapper: every frame a master (or a virtual drive) sends or
receives, written in order by python-can's writer for the file's suffix (.log, .asc, .blf,
...). A library piece, so a program that opens drives without the command line can log its
bus the same way `--can-log` does."""

from __future__ import annotations

import collections
import copy
import threading
import time

import can


class CanLog:
    """`--can-log`: every frame this process sends or receives, written in order by
    python-can's writer for the file's suffix."""

    def __init__(self, path: str, channel: str) -> None:
        self._writer = can.Logger(path)
        self._channel = channel  # named in the file for frames that carry none (those sent)
        self._lock = threading.Lock()  # the receive thread and the control thread both log
        self._open = True

    def write(self, msg: can.Message, is_rx: bool) -> None:
        logged = copy.copy(msg)
        logged.is_rx = is_rx
        if logged.channel is None:
            logged.channel = self._channel
        if not is_rx or not logged.timestamp:
            logged.timestamp = time.time()  # frames being sent carry no time yet
        with self._lock:
            if self._open:
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


class LinkTap:
    """A peer on one side of the --sim link (sim_bus.embedded.LinkedNetwork hands every frame
    its network sends to its peers' `notify`): what that side sends goes to the log, the
    master's frames as sent (Tx), the drive's as received (Rx)."""

    def __init__(self, can_log: CanLog, is_rx: bool) -> None:
        self._log, self._is_rx = can_log, is_rx

    def notify(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self._log.write(can.Message(timestamp=timestamp, arbitration_id=can_id,
                                    is_extended_id=can_id > 0x7FF, data=bytes(data)),
                        self._is_rx)
