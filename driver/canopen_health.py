"""The CANopen master's watch over its drives: their boot-up, heartbeats and emergencies, the
master's own heartbeat, and the load on the bus.

Heartbeat consumer (CiA 301, 0x1016 semantics): the drive is lost when no heartbeat came for
`timeout_factor` producer periods, measured on the clock the bus is given
(`driver.clock`): the wall clock in real time, drive time in lock-step. One code path judges
both, once each cycle of the bus; on a clock that runs alone (the wall clock) one thread per
bus also judges between cycles, so a drive lost while no cycle runs is still found. In
lock-step drive time only passes as the bus sends SYNCs, and the virtual drive's producer
beats every N of its cycles (`sim_bus.canopen_node`), so both sides count the same thing and
the verdict falls on the same cycle in every run, however slow or busy the host. A
wall-clock consumer in lock-step judges a clock the drive does not keep: on a busy host one
wall second may hold no cycle at all (the drive could not beat) and it trips ("heartbeat
missing for 272 ms" while nothing was wrong); on an idle one ten drive seconds pass in a wall
second and a dead producer goes unnoticed for thousands of cycles. The master's heartbeat is
produced the same way: due on the bus's clock, sent by the cycle or the thread that sees it
due.
"""

import logging
import math
import threading
from collections.abc import Callable

import canopen
from canopen.emcy import EmcyError

from driver.clock import SAME_TIME, Clock
from driver.interface import DriveError, DriveLost
from protocol import cia301

log = logging.getLogger(__name__)

# frames a cycle beyond the bus's own cyclic traffic: a 1 Mbit/s CAN bus carries at most ~8
# full frames per millisecond, so far more is a flood
FLOOD_MARGIN_FRAMES = 32
MASTER_HEARTBEAT_MS = 100  # the master's own heartbeat period
# the drive's consumer time for it (0x1016): eight periods, so a host that starves the
# producer thread for a few hundred ms is not taken for a dead master, while a dead one is
# noticed within the 1 s (SYNC silence, sim_bus.canopen_watchdogs, is quicker)
MASTER_HEARTBEAT_CONSUMER_MS = 8 * MASTER_HEARTBEAT_MS
_ATTRIBUTE = "_actuator_link_bus_watch"  # where a network keeps its BusWatch
_OPERATIONAL = bytes([cia301.NMT_OPERATIONAL])  # the master's heartbeat's data


def master_node_id(drive_node_id: int) -> int:
    """The id the master's heartbeat uses: 127, the top of the range, unless the drive has it."""
    return 127 if drive_node_id != 127 else 126


class BusWatch:
    """What the master does once per CAN bus, whatever the number of drives on it: count the
    frames the network receives (one wrap of canopen's entry point for received frames),
    judge the load once a cycle, produce the master's heartbeat (once per master id, however
    many drives consume it) and judge every drive's heartbeat, on the bus's `clock`. Each
    drive's `Health` joins the watch of its network (`BusWatch.of`); the jobs used to run
    once per drive: on talos_32's 32-drive link every received frame passed 32 nested
    counting wrappers and the bus carried 32 copies of the master's heartbeat."""

    @classmethod
    def of(cls, network: canopen.Network, clock: Clock) -> "BusWatch":
        """The network's watch, made with its first drive (whose clock it keeps). Kept on the
        network itself (a canopen Network is a mapping, so it cannot key a dictionary), and
        gone with it."""
        watch = getattr(network, _ATTRIBUTE, None)
        if watch is None:
            watch = cls(network, clock)
            setattr(network, _ATTRIBUTE, watch)
        return watch

    def __init__(self, network: canopen.Network, clock: Clock):
        self.network = network
        self.clock = clock
        self._frames_at_cycle = 0
        # more than this in one cycle is a flood: the bus's cyclic frames plus the margin
        # (`expect_cyclic_frames`; a lone drive's own SYNC and PDOs are well inside it)
        self.frame_limit = FLOOD_MARGIN_FRAMES
        self._healths: list[Health] = []
        self._lock = threading.Lock()
        # master id -> [drives producing it, when the next beat is due (on the clock)]
        self._beats: dict[int, list] = {}
        # before this time on the clock nothing is due (no beat, no drive's deadline): a
        # cycle's look is one comparison. A beat received only moves a deadline later, so an
        # early `_due` costs one look too many, never a late verdict
        self._due = -math.inf
        self._thread_stop: threading.Event | None = None
        # what counts the frames received (`frames`, `last_stamp`): the network itself where
        # it does (`counts_frames`: the in-process link, the lean udp_multicast network of
        # `driver.canopen_multicast`), else this watch, through one wrap
        # of the network's entry point for received frames
        self._counts: BusWatch | canopen.Network = self
        if getattr(network, "counts_frames", False):
            self._counts = network
            return
        self._frames = 0
        self._last_stamp = 0.0
        deliver = network.notify

        def counting_notify(can_id: int, data: bytearray, timestamp: float) -> None:
            self._frames += 1
            self._last_stamp = timestamp
            deliver(can_id, data, timestamp)

        network.notify = counting_notify

    @property
    def frames(self) -> int:
        """Every frame this network received: ours too where the interface echoes them
        (python-can's udp_multicast; the lean path, driver.canopen_multicast, drops them)."""
        counts = self._counts
        return counts._frames if counts is self else counts.frames

    @property
    def last_stamp(self) -> float:
        """The receive stamp of the last frame through (the kernel's on SocketCAN and
        udp_multicast): how far the receive thread has caught up with the bus."""
        counts = self._counts
        return counts._last_stamp if counts is self else counts.last_stamp

    def join(self, health: "Health") -> None:
        with self._lock:
            self._healths.append(health)

    def leave(self, health: "Health") -> None:
        with self._lock:
            if health in self._healths:
                self._healths.remove(health)
            if not self._healths and self._thread_stop is not None:
                self._thread_stop.set()
                self._thread_stop = None

    def expect_cyclic_frames(self, frames: int) -> None:
        """The bus carries `frames` a cycle by design (SYNC and every drive's PDOs)."""
        self.frame_limit = frames + FLOOD_MARGIN_FRAMES

    def restart_count(self) -> None:
        """Bus load counts from now: bring-up traffic is not load."""
        self._frames_at_cycle = self.frames

    def count_cycle(self, warnings: list[str]) -> None:
        """Once per cycle of the bus, after its TPDOs: the load, then the clock's jobs."""
        total = self.frames
        frames, self._frames_at_cycle = total - self._frames_at_cycle, total
        if frames > self.frame_limit:
            warnings.append(f"bus overloaded: {frames} frames in one cycle (at most "
                            f"{self.frame_limit} expected)")
        self.tick()

    def tick(self) -> None:
        """What is due on the clock now: the master's heartbeats, every drive's heartbeat
        judged. From the bus's cycle, and between cycles from the thread (`_run_alone`)."""
        now = self.clock.now()
        if now < self._due:
            return
        with self._lock:
            due = math.inf
            for beat in self._beats.values():
                if now >= beat[1] - SAME_TIME:
                    beat[1] = now + MASTER_HEARTBEAT_MS * 1e-3
                    self.network.send_message(beat[2], _OPERATIONAL)
                due = min(due, beat[1])
            healths = list(self._healths)
        for health in healths:
            due = min(due, health.check(now))
        self._due = due - SAME_TIME

    def look_soon(self) -> None:
        """A deadline was set: the next `tick` looks at everything."""
        self._due = -math.inf

    def start_producing(self, master_id: int) -> None:
        """Beat as node `master_id` (NMT operational) every MASTER_HEARTBEAT_MS of the bus's
        clock, from now; once for every drive that asks."""
        with self._lock:
            producers = self._beats.get(master_id)
            if producers is not None:
                producers[0] += 1
                return
            self._beats[master_id] = [1, self.clock.now(), cia301.HEARTBEAT_BASE + master_id]
        self.look_soon()
        self.tick()  # the first beat now
        self._run_alone()

    def stop_producing(self, master_id: int) -> None:
        with self._lock:
            producers = self._beats.get(master_id)
            if producers is None:
                return
            producers[0] -= 1
            if producers[0] <= 0:
                del self._beats[master_id]

    def _run_alone(self) -> None:
        """On a clock that runs alone (the wall clock), one thread for the bus runs `tick`
        between cycles: a drive lost, or a beat due, while no cycle runs (bring-up, a loop
        that stopped). Drive time does not pass between cycles: no thread then."""
        if not self.clock.runs_alone:
            return
        with self._lock:
            if self._thread_stop is not None:
                return
            stop = self._thread_stop = threading.Event()
        threading.Thread(target=self._watch_clock, args=(stop,), daemon=True,
                         name="heartbeat-watch").start()

    def _watch_clock(self, stop: threading.Event) -> None:
        while True:
            with self._lock:
                periods = [h.heartbeat_ms for h in self._healths if h.heartbeat_ms > 0]
                producing = bool(self._beats)
            # a quarter of the shortest period, the drives' or the master's own
            shortest = min(periods + [MASTER_HEARTBEAT_MS] if producing else periods,
                           default=MASTER_HEARTBEAT_MS)
            if stop.wait(shortest / 4000.0):
                return
            self.tick()


class Health:
    """Boot-up, heartbeat and EMCY of node `node_id`; the bus's jobs through its `BusWatch`.

    `on_failure(error)` is called once when the drive is lost; `on_emergency(code, register)`
    for every EMCY. Both run in the network's receive thread (or the bus's watch thread).
    """

    def __init__(self, network: canopen.Network, node: canopen.RemoteNode, name: str, *,
                 clock: Clock, on_failure: Callable[[DriveError], None],
                 on_emergency: Callable[[int, int], None], warnings: list[str],
                 timeout_factor: float = 2.0):
        self.network = network
        self.bus = BusWatch.of(network, clock)
        self.clock = self.bus.clock
        self.name = name
        self.timeout_factor = timeout_factor
        self.warnings = warnings
        self.heartbeat_ms = 0
        self.period = 1e-3  # s, the cycle's (set by `watch`), for reports in cycles
        self.last_heartbeat: float | None = None  # the clock's time of the last beat
        # the last beat's receive stamp (the interface's: the kernel's on SocketCAN and
        # udp_multicast), held against the bus's `last_stamp` in `check`
        self.beat_stamp = 0.0
        self.booted = threading.Event()  # set by the boot-up message (heartbeat state 0)
        self._timeout = math.inf
        self._in_use = False
        self._on_failure = on_failure
        self._on_emergency = on_emergency
        self._master_id: int | None = None
        network.subscribe(cia301.HEARTBEAT_BASE + node.id, self._on_heartbeat)
        node.emcy.add_callback(self._on_emcy)
        self.bus.join(self)

    @property
    def frames(self) -> int:
        """Every frame this drive's network received."""
        return self.bus.frames

    @property
    def frame_limit(self) -> int:
        return self.bus.frame_limit

    # --- boot-up and heartbeat --------------------------------------------------------------

    def expect_boot(self) -> None:
        self.booted.clear()
        self._in_use = False

    def watch(self, heartbeat_ms: int, period: float) -> None:
        """Consume the drive's heartbeat from now on (its producer time is `heartbeat_ms`; 0:
        none), the cycle's period being `period` s."""
        self.heartbeat_ms = heartbeat_ms
        self.period = period
        self._timeout = (self.timeout_factor * heartbeat_ms * 1e-3 + SAME_TIME
                         if heartbeat_ms > 0 else math.inf)
        self.last_heartbeat = self.clock.now()
        self.beat_stamp = self.bus.last_stamp  # silence counts from the frames handled now
        self._in_use = True
        self.bus.look_soon()
        self.bus.restart_count()  # bring-up traffic is not load
        self.bus._run_alone()

    def _on_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if data and data[0] == cia301.NMT_BOOT_UP:
            self.booted.set()
            if self._in_use:
                self._on_failure(DriveLost(f"{self.name}: drive rebooted (boot-up message) "
                                           "while in use"))
        self.beat_stamp = timestamp
        self.last_heartbeat = self.clock.now()

    def check(self, now: float) -> float:
        """Lost when silent past the timeout at `now` (on the bus's clock), once the bus's
        receive path has handled a frame received more than the timeout after the last beat
        (frames are handled in order: a beat before it would have been seen), or, where it
        has not (a bus silent but for this drive, or a receive thread still catching up
        with what queued while the host held it), the clock's `receive_grace` later.
        Returns when this drive is next due to be judged (inf: not watched)."""
        last = self.last_heartbeat
        if last is None or not self._in_use:
            return math.inf
        if now - last <= self._timeout:
            return last + self._timeout
        overdue = last + self._timeout + self.clock.receive_grace
        if now < overdue and self.bus.last_stamp - self.beat_stamp <= self._timeout:
            return overdue
        self._in_use = False  # one verdict per loss
        error = DriveLost(f"{self.name}: heartbeat missing for "
                          f"{self.clock.span(now - last, self.period)} (producer period "
                          f"{self.heartbeat_ms} ms)")
        log.error("%s", error)
        self._on_failure(error)
        return math.inf

    # --- the master's own heartbeat ---------------------------------------------------------

    def start_producing(self, master_id: int) -> None:
        """The master's heartbeat this drive consumes (the bus produces it once)."""
        self.stop_producing()
        self._master_id = master_id
        self.bus.start_producing(master_id)

    def stop_producing(self) -> None:
        if self._master_id is not None:
            self.bus.stop_producing(self._master_id)
            self._master_id = None

    # --- emergencies ------------------------------------------------------------------------

    def _on_emcy(self, error: EmcyError) -> None:
        self._on_emergency(error.code, error.register)

    def close(self) -> None:
        self._in_use = False
        self.stop_producing()
        self.bus.leave(self)
