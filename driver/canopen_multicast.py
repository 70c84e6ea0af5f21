"""The master's CANopen networks on python-can's `udp_multicast` buses, lean: udp_multicast
stands in for CAN where a machine has no SocketCAN (the master and the virtual drives in two
processes), and through python-can it cost the master more than the cycle.

Measured on talos_arm (7 joints on 4 buses) across processes: about 0.9 of a core, one
`can.Notifier` thread per bus, each frame through `UdpMulticastBus.recv` (select, recvmsg,
msgpack, a checked `can.Message`), canopen's listener and node scanner, about 40 frames a
millisecond including the echoes of the master's own SYNCs and RPDOs, and sending
(`can.Message`, `pack_message`, a socket timeout set, sendto) about 60 % of the loop thread;
bus-bench missed about 290 % of cycles. Here the cycle's thread reads every udp_multicast bus
of the process while it waits for its TPDOs, one thread of its own otherwise
(`MulticastReceiver`), a frame is one recvmsg and one decode in place in
(`protocol.can_datagram.decode`), one join of bytes and one send out, and the kernel drops
the master's own frames by their sender address before they are queued.

Own frames: python-can's socket is bound to the group's port and every process on the group
sends from that same port, so an echo cannot be told by its source. Frames here leave from a
socket of the network's own (an ephemeral port, connected to the group), whose address,
as the receivers see it, names this network alone. The receiving socket is python-can's
(group joined, loopback on, SO_TIMESTAMPNS), used through a descriptor of our own, so a
frame's stamp is the kernel's receive time, as python-can gives it: the freshness window in
`driver.canopen_cycle` relies on it.
"""

import logging
import os
import select
import socket
import struct
import threading
import time
from collections.abc import Callable, Sequence

import can
import canopen

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

log = logging.getLogger(__name__)

POLL_TIMEOUT = 0.05  # s: how long stopping waits for the receive thread at most
# s without the cycle reading the buses after which the receive thread reads them again (a
# loop between cycles reads again within a period; a cold solve or a stop takes longer)
STALL = 0.005
POLL_SLICE = 0.001  # s: how often a cycle waiting for frames asks whether to stop waiting
# s a cycle looks for its TPDOs without sleeping before it sleeps until they come: a thread
# asleep on a virtual machine's idle CPU wakes 50-150 us after its datagram came, p99 0.3-1.7
# ms (a UDP round trip between two processes on two CPUs of this 2-core host: 100-165 us
# median asleep, 15 us looking), which the cycle paid on every exchange. A SOEM master looks
# too (its socket's receive timeout is 1 us). Half a period at 1 kHz: the drives' answers
# come within it, and the cycle keeps the rest.
LOOK_FOR_ANSWERS = 0.0005
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux's value where Python lacks it
_TIMESPEC = struct.Struct("@ll")  # the kernel's struct timespec: seconds, nanoseconds
_ANCILLARY = socket.CMSG_SPACE(_TIMESPEC.size)


class MulticastNetwork(canopen.Network):
    """A connected canopen Network on the udp_multicast bus python-can's `config` names
    (interface "udp_multicast", its group as channel, its port), received by the process's
    `MulticastReceiver` from construction until `disconnect`.

    It counts the frames it receives itself (`frames`, `last_stamp`, what
    `driver.canopen_health.BusWatch` judges the bus by: `counts_frames`) and hands each to its
    subscribers without canopen's node scanner (the master scans no bus: its drives are named
    in the robot file): a TPDO went through a counting wrap, canopen's `notify` and the
    scanner, three Python calls of the 11 us a frame cost the master's cycle (talos_arm across
    processes: the master received the drives' 21 TPDOs slower than they sent them)."""

    counts_frames = True

    def __init__(self, config: dict):
        super().__init__(None)
        self.frames = 0  # received
        self.last_stamp = 0.0  # of the last frame received
        self.bus = can.Bus(ignore_config=True, **config)
        try:
            self.channel = config["channel"]
            self._socket = socket.socket(fileno=os.dup(self.bus.fileno()))
            self._socket.setblocking(False)
            group = (self.channel, self._socket.getsockname()[1])
            self._sender = _sender_socket(self._socket.family, group,
                                          config.get("hop_limit", HOP_LIMIT))
            self._source = self._sender.getsockname()[:2]
            self._filtered = _drop_from(self._socket, *self._source)
            _own_group_only(self._socket)
        except Exception:
            self.bus.shutdown()
            raise
        self._send_lock = threading.Lock()
        RECEIVER.attach(self)

    def fileno(self) -> int:
        return self._socket.fileno()

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        """One frame: one pack, one send (python-can's datagram, see protocol.can_datagram)."""
        datagram = encode(can_id, bytes(data), time.time(), remote)
        with self._send_lock:  # the loop, the heartbeat thread and SDOs send
            self._sender.send(datagram)

    def send_slices(self, data: bytes, frames: Sequence[tuple[int, int, int]]) -> None:
        """Several frames, each `(can_id, start, stop)` a slice of `data` (the cycle's RPDOs
        cut from its output image, `driver.canopen_cycle.BusCycle.send_frames`), packed
        together and sent in order, with one stamp and one hold of the lock."""
        send = self._sender.send
        with self._send_lock:
            for datagram in encode_slices(data, frames, time.time()):
                send(datagram)

    def notify(self, can_id: int, data: bytes, timestamp: float) -> None:
        """A frame received: counted, then to its subscribers (no node scanner)."""
        self.frames += 1
        self.last_stamp = timestamp
        for callback in self.subscribers.get(can_id, ()):
            callback(can_id, data, timestamp)

    def receive_ready(self) -> None:
        """Hand every datagram waiting on the socket, but our own, to its subscribers (as
        `notify`, inline: a call fewer a frame), stamped with the kernel's receive time;
        error and remote frames ignored, as canopen's listener does."""
        recvmsg, source, subscribers = self._socket.recvmsg, self._source, self.subscribers
        # where the kernel drops our own frames (`_drop_from`), no look at the sender
        check = not self._filtered
        while True:
            try:
                datagram, ancillary, _, sender = recvmsg(DATAGRAM_MAX, _ANCILLARY)
            except BlockingIOError:
                return
            except OSError:  # closed under us by disconnect: the receiver forgets it
                return
            if check and sender[:2] == source:
                continue
            try:
                frame = decode(datagram)
            except ValueError as exc:
                log.warning("bus %s: datagram dropped: %s", self.channel, exc)
                continue
            if frame is None:
                continue
            # the socket's one ancillary item: SO_TIMESTAMPNS
            if ancillary and ancillary[0][1] == SO_TIMESTAMPNS:
                seconds, nanoseconds = _TIMESPEC.unpack_from(ancillary[0][2])
                stamp = seconds + nanoseconds * 1e-9
            else:
                stamp = time.time()
            self.frames += 1
            self.last_stamp = stamp
            can_id, data = frame
            for callback in subscribers.get(can_id, ()):
                try:
                    callback(can_id, data, stamp)
                except Exception:  # one handler's failure must not stop the bus
                    log.exception("bus %s: handler of 0x%03X failed", self.channel, can_id)

    def receive_until(self, done: Callable[[], bool], timeout: float) -> None:
        """Handle the frames of every bus of the process in the calling thread until
        `done()`, at most `timeout` s (`MulticastReceiver.receive_until`): the cycle waiting
        for its TPDOs reads them itself."""
        RECEIVER.receive_until(done, timeout)

    def disconnect(self) -> None:
        RECEIVER.detach(self)
        for node in self.nodes.values():
            if hasattr(node, "pdo"):
                node.pdo.stop()
        self._sender.close()
        self._socket.close()
        if self.bus is not None:
            self.bus.shutdown()
        self.bus = None


def _sender_socket(family: socket.AddressFamily, group: tuple[str, int],
                   hop_limit: int) -> socket.socket:
    """A socket that sends to `group` from an address of its own (an ephemeral port), its
    frames looped back to this host's receivers, `hop_limit` its TTL (`HOP_LIMIT`: they stay
    on this host)."""
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


def _drop_from(receiver: socket.socket, address: str, port: int) -> bool:
    """Have the kernel drop, before queueing, what `receiver` gets from `address`:`port` (our
    own frames, looped back): about a third of a bus's datagrams (its SYNC and RPDOs), each a
    wake-up of the receive thread, which then takes the interpreter from the loop thread in
    the middle of its cycle. The program (IPv4 only; the kernel copies it): source port (UDP
    header) and source address (IP header) ours: drop, else keep. Whether the kernel
    took it (else `receive_ready` drops them by their sender)."""
    if receiver.family != socket.AF_INET:
        return False
    program, fprog = own_frames_fprog(address, port)  # the program lives through the call
    try:
        receiver.setsockopt(socket.SOL_SOCKET, SO_ATTACH_FILTER, fprog)
    except OSError as exc:  # the check in receive_ready drops them instead
        log.info("own frames dropped in user space (socket filter refused: %s)", exc)
        return False
    return True


class MulticastReceiver:
    """Reads every `MulticastNetwork` of the process, in one of two threads, never both at
    once (a bus's frames are handled in the order they came):

    - the cycle's own (`receive_until`, from `driver.canopen_cycle.BusCycle.collect`), which
      reads every bus while it waits for its TPDOs: measured on talos_arm across processes,
      a receive thread woke four times a cycle and handed each bus's last TPDO to the
      waiting loop through a Condition, and the loop had the sample 157 us median (418 us
      p90) after the kernel had its last frame, each hand-over a wake-up and a contention
      for the interpreter on a host of two cores that the drives' process shares;
    - a thread of its own, started by the first network opened, while the cycle does not
      read: at bring-up (SDO, NMT) and whenever the cycle has not read for `STALL` s (a
      stalled or ended loop: heartbeats, emergencies and SDO answers are still handled
      within STALL). While the cycle reads, it takes the sockets out of the thread's epoll,
      so the thread sleeps through the cycle's frames and wakes only every STALL to look.

    The thread is started after `apply_real_time` in the commands, so it inherits the
    real-time priority of the thread that opens the buses."""

    def __init__(self) -> None:
        self._forget()
        # a forked child has none of the parent's threads: its first network starts one
        os.register_at_fork(after_in_child=self._forget)

    def _forget(self) -> None:
        self._lock = threading.Lock()  # the networks, the epolls, who reads
        # held by whichever thread is reading the sockets (the cycle's or the receiver's)
        self._reading = threading.Lock()
        self._networks: dict[int, MulticastNetwork] = {}
        self._poll: select.epoll | None = None  # the thread's: the sockets while it reads
        self._pump: select.epoll | None = None  # the cycle's: every socket
        self._thread: threading.Thread | None = None
        self._cycle_reads = False
        self._pumped = 0.0  # time.monotonic() the cycle last stopped reading

    def attach(self, network: MulticastNetwork) -> None:
        with self._lock:
            if self._thread is None:
                self._poll, self._pump = select.epoll(), select.epoll()
                self._cycle_reads = False
                self._thread = threading.Thread(target=self._run, args=(self._poll,),
                                                daemon=True, name="multicast-receiver")
                self._thread.start()
            fd = network.fileno()
            self._networks[fd] = network
            # epoll takes a descriptor at once, even while a thread waits on it
            self._pump.register(fd, select.EPOLLIN)
            if not self._cycle_reads:
                self._poll.register(fd, select.EPOLLIN)

    def detach(self, network: MulticastNetwork) -> None:
        with self._lock:
            fd = network.fileno()
            if self._networks.get(fd) is not network:
                return
            del self._networks[fd]
            self._pump.unregister(fd)
            if not self._cycle_reads:
                self._poll.unregister(fd)
            if self._networks:
                return
            thread, self._thread = self._thread, None
            poll, pump, self._poll, self._pump = self._poll, self._pump, None, None
        if thread is not threading.current_thread():
            thread.join()  # it sees its poll gone within POLL_TIMEOUT
        poll.close()
        pump.close()

    def receive_until(self, done: Callable[[], bool], timeout: float) -> None:
        """Read every bus in the calling thread (the cycle's) until `done()` or `timeout` s
        have passed, looking without sleeping for the first LOOK_FOR_ANSWERS s; `done` is
        asked again at least every POLL_SLICE s (a drive's failure, raised by another thread,
        ends the wait that soon)."""
        monotonic = time.monotonic
        start = monotonic()
        deadline, look_until = start + timeout, start + min(timeout, LOOK_FOR_ANSWERS)
        with self._reading:
            if not self._cycle_reads:
                self._hand_over(to_cycle=True)
            pump, networks = self._pump, self._networks
            try:
                while not done():
                    now = monotonic()
                    remaining = deadline - now
                    if remaining <= 0 or pump is None:
                        return
                    wait = 0.0 if now < look_until else min(remaining, POLL_SLICE)
                    for fd, _ in pump.poll(wait):
                        network = networks.get(fd)
                        if network is not None:
                            network.receive_ready()
            except (OSError, ValueError):  # closed: the last network left
                return
            finally:
                self._pumped = time.monotonic()

    def _hand_over(self, to_cycle: bool) -> None:
        """The sockets out of the thread's epoll (the cycle reads them) or back in (the
        thread does). The caller holds `_reading`."""
        with self._lock:
            if self._poll is None or self._cycle_reads == to_cycle:
                return
            for fd in self._networks:
                if to_cycle:
                    self._poll.unregister(fd)
                else:
                    self._poll.register(fd, select.EPOLLIN)
            self._cycle_reads = to_cycle

    def _run(self, poll: select.epoll) -> None:
        networks, reading = self._networks, self._reading
        while self._poll is poll:
            try:
                events = poll.poll(STALL if self._cycle_reads else POLL_TIMEOUT)
            except (OSError, ValueError):  # closed: the last network left
                return
            if self._cycle_reads:
                # no sockets in the epoll: a look whether the cycle still reads them
                if (time.monotonic() - self._pumped > STALL
                        and reading.acquire(blocking=False)):  # not while it reads
                    try:
                        if time.monotonic() - self._pumped > STALL:
                            self._hand_over(to_cycle=False)
                    finally:
                        reading.release()
                continue
            if not events:
                continue
            with reading:
                if self._cycle_reads:  # the cycle took the sockets meanwhile: its frames
                    continue
                for fd, _ in events:
                    network = networks.get(fd)
                    if network is not None:
                        network.receive_ready()


RECEIVER = MulticastReceiver()  # the process's one
