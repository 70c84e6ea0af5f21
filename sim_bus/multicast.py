"""Virtual drives on python-can's `udp_multicast` buses, lean: the process that stands in for
hardware must answer every frame within the cycle, on a host that runs the master too.

Through python-can and canopen a frame cost the drives' process about 20 us to send (a
`can.Message`, its checks, a msgpack dict, a socket timeout set) and 20 us to receive (a
`select`, an ioctl for the timestamp, msgpack, a checked `can.Message`, the notifier's
listeners, canopen's node scanner), plus the echo of every frame it sent itself, which
udp_multicast delivers back: talos_arm's four buses (two drives each, nine frames a cycle)
took about 1.5 ms of CPU a millisecond, more than a core, and the master waited for its
samples ("late sample"). Here a frame is one decode in place (`protocol.can_datagram`) and
one socket call each way, and one thread receives for every bus of the process, awake when
the master's next SYNC is due (`MulticastReceiver`).

Own frames: the drives' TPDOs, heartbeats and SDO answers (two thirds of a bus's datagrams)
come back to their own socket through multicast loopback. They leave from a socket of the
network's own (an ephemeral port, connected to the group), and the kernel drops what comes
from that address before queueing it (`protocol.can_datagram.own_frames_filter`): each echo
was a wake-up, a receive and a decode of the one thread that answers every bus (talos_arm:
21 a millisecond). Where the filter is refused (IPv6 groups), an echo is dropped after
decoding, as any frame no node subscribes to.

The datagrams are python-can's own (`protocol.can_datagram`, as
`can.interfaces.udp_multicast.utils.pack_message` writes them), so a python-can master on the
same group reads them as it reads its own. The socket is the one python-can's bus made (group
joined, loopback on), used through its file descriptor.
"""

import logging
import os
import select
import socket
import threading
import time
from collections.abc import Sequence

import can
import canopen

from protocol import cia301
from protocol.can_datagram import (
    DATAGRAM_MAX,
    HOP_LIMIT,
    SO_ATTACH_FILTER,
    decode,
    encode,
    encode_slices,
    own_frames_fprog,
    receiver_options,
    sender_options,
)
from sim_bus.rhythm import AHEAD, Rhythm

log = logging.getLogger(__name__)

POLL_TIMEOUT = 0.05  # s: how long closing waits for the receive thread at most
SELECT_FDS = 1024  # FD_SETSIZE: select's descriptors end below it


class MulticastNetwork(canopen.Network):
    """A canopen Network of virtual drives on the udp_multicast bus python-can's `config`
    names (interface "udp_multicast", its group as channel, its port). Its frames are received
    by a `MulticastReceiver` (one for all of a process's buses)."""

    def __init__(self, config: dict):
        super().__init__(None)
        self.bus = can.Bus(ignore_config=True, **config)
        self.channel = config["channel"]
        # the bus's socket (its options, its group) through a descriptor of our own; it is
        # bound to the group's port, where the frames go
        try:
            self._socket = socket.socket(fileno=os.dup(self.bus.fileno()))
            self._socket.setblocking(False)
            self._sender = _sender_socket(self._socket.family,
                                          (self.channel, self._socket.getsockname()[1]),
                                          config.get("hop_limit", HOP_LIMIT))
            _drop_from(self._socket, *self._sender.getsockname()[:2])
            _own_group_only(self._socket)
        except Exception:
            self.bus.shutdown()
            raise
        self._send_lock = threading.Lock()

    def fileno(self) -> int:
        return self._socket.fileno()

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        """One classic CAN frame, as python-can's `pack_message` writes it."""
        datagram = encode(can_id, bytes(data), time.time(), remote)
        with self._send_lock:  # nodes send from their own threads (heartbeats)
            self._sender.send(datagram)

    def send_slices(self, data: bytes, frames: Sequence[tuple[int, int, int]]) -> None:
        """Several frames, each `(can_id, start, stop)` a slice of `data` (a drive's TPDOs cut
        from its bus's packed bytes, `sim_bus.canopen_node`), packed together and sent in
        order, with one stamp and one hold of the lock: the frames of one answer leave
        together."""
        send = self._sender.send
        with self._send_lock:
            for datagram in encode_slices(data, frames, time.time()):
                send(datagram)

    def receive_ready(self) -> bool:
        """Dispatch every datagram waiting on the socket to this network's subscribers, as
        canopen's listener does (error and remote frames ignored). Whether a SYNC came."""
        recv, subscribers = self._socket.recv, self.subscribers
        synced = False
        while True:
            try:
                datagram = recv(DATAGRAM_MAX)
            except BlockingIOError:
                return synced
            try:
                frame = decode(datagram)
            except ValueError as exc:
                log.warning("bus %s: datagram dropped: %s", self.channel, exc)
                continue
            if frame is None:
                continue
            can_id, data = frame
            if can_id == cia301.SYNC_COB_ID:
                synced = True
            callbacks = subscribers.get(can_id)
            if not callbacks:
                continue
            now = time.time()
            for callback in callbacks:
                try:
                    callback(can_id, data, now)
                except Exception:  # one handler's failure must not stop the bus
                    log.exception("bus %s: handler of 0x%03X failed", self.channel, can_id)

    def disconnect(self) -> None:
        self._sender.close()
        self._socket.close()
        self.bus.shutdown()


def _sender_socket(family: socket.AddressFamily, group: tuple[str, int],
                   hop_limit: int) -> socket.socket:
    """A socket that sends to `group` from an address of its own (an ephemeral port), its
    frames looped back to this host's receivers, `hop_limit` its TTL (0: they stay on this
    host)."""
    sender = socket.socket(family, socket.SOCK_DGRAM)
    try:
        for option in sender_options(family, hop_limit):
            sender.setsockopt(*option)
        sender.connect(group)  # fixes the source address the receivers see
    except OSError:
        sender.close()
        raise
    return sender


def _own_group_only(receiver: socket.socket) -> None:
    """Have `receiver` get its own group's datagrams only (`receiver_options`)."""
    try:
        for option in receiver_options(receiver.family):
            receiver.setsockopt(*option)
    except OSError as exc:
        log.warning("buses on one port with several groups hear each other (%s)", exc)


def _drop_from(receiver: socket.socket, address: str, port: int) -> None:
    """Have the kernel drop what `receiver` gets from `address`:`port` (IPv4; the kernel
    keeps its own copy of the program)."""
    if receiver.family != socket.AF_INET:
        return
    program, fprog = own_frames_fprog(address, port)  # the program lives through the call
    try:
        receiver.setsockopt(socket.SOL_SOCKET, SO_ATTACH_FILTER, fprog)
    except OSError as exc:  # echoes are then dropped after decoding (no subscriber)
        log.info("own frames dropped in user space (socket filter refused: %s)", exc)


class MulticastReceiver(threading.Thread):
    """One thread receiving for every `MulticastNetwork` of the process, until `stop`: a
    thread per bus would contend for the interpreter each frame.

    It keeps the master's rhythm (`Rhythm`): it sleeps until AHEAD before the next cycle's
    SYNC is due and then looks at the buses without sleeping until it comes (or until AHEAD
    after it was due: then it sleeps until a frame comes). Hardware answers a SYNC within
    microseconds; a thread asleep on this host took 56 us median (90 p90) from the kernel's
    receipt of the SYNC to its first line of Python (talos_arm across processes, the drives
    on a CPU of their own), each cycle, on the master's critical path. The look costs the
    drives' CPU up to twice AHEAD a period."""

    def __init__(self, networks: list[MulticastNetwork]):
        super().__init__(daemon=True, name="multicast-receiver")
        self._networks = {network.fileno(): network for network in networks}
        self._stopping = threading.Event()
        self.rhythm = Rhythm()

    def run(self) -> None:
        networks, stopping, clock, rhythm = (self._networks, self._stopping,
                                             time.perf_counter, self.rhythm)
        fds = list(networks)
        # select, not epoll: its timeout has microseconds, epoll's milliseconds; but it takes
        # descriptors below FD_SETSIZE only (a process with that many open sleeps in poll
        # until a frame comes, and keeps no rhythm)
        timed = max(fds, default=0) < SELECT_FDS
        if not timed:
            poller = select.poll()
            for fd in fds:
                poller.register(fd, select.POLLIN)
        while not stopping.is_set():
            now = clock()
            if timed:
                wait = rhythm.due - AHEAD - now
                ready = select.select(fds, (), (), min(wait, POLL_TIMEOUT) if wait > 0 else 0)[0]
            else:
                ready = [fd for fd, _ in poller.poll(POLL_TIMEOUT * 1e3)]
            if not ready:
                if now > rhythm.due + AHEAD:
                    rhythm.missed()
                continue
            now = clock()
            synced = False
            for fd in ready:
                synced |= networks[fd].receive_ready()
            if synced:
                rhythm.sync(now)

    def stop(self) -> None:
        self._stopping.set()
        if self.ident is not None:
            self.join()
