"""The CANopen master's watch over one drive: its boot-up, its heartbeat, its emergencies, and
the load on the bus.

Heartbeat consumer (CiA 301, 0x1016 semantics): the drive is lost when no heartbeat came for
`timeout_factor` producer periods. In real time that is measured on the wall clock by a
polling thread. In lock-step it is measured in drive time, counted in cycles at each
`count_cycle()`: the virtual drive's producer then beats every N of its cycles
(`sim_bus.canopen_node`), so both sides count the same thing, and the verdict falls on the
same cycle in every run, however slow or busy the host. A wall-clock consumer in lock-step
judges a clock the drive does not keep: on a busy host one wall second may hold no cycle
at all (the drive could not beat) and it trips ("heartbeat missing for 272 ms" while nothing
was wrong); on an idle one ten drive seconds pass in a wall second and a dead producer goes
unnoticed for thousands of cycles.
"""

import logging
import threading
import time
from collections.abc import Callable

import canopen
from canopen.emcy import EmcyError

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


def master_node_id(drive_node_id: int) -> int:
    """The id the master's heartbeat uses: 127, the top of the range, unless the drive has it."""
    return 127 if drive_node_id != 127 else 126


class BusWatch:
    """What the master does once per CAN bus, whatever the number of drives on it: count the
    frames the network receives (one wrap of canopen's entry point for received frames),
    judge the load once a cycle, produce the master's heartbeat (once per master id, however
    many drives consume it), and in real time poll every drive's heartbeat from one thread.
    Each drive's `Health` joins the watch of its network (`BusWatch.of`); the jobs used to
    run once per drive: on talos_32's 32-drive link every received frame passed 32 nested
    counting wrappers and the bus carried 32 copies of the master's heartbeat."""

    @classmethod
    def of(cls, network: canopen.Network, lockstep: bool) -> "BusWatch":
        """The network's watch, made with its first drive. Kept on the network itself (a
        canopen Network is a mapping, so it cannot key a dictionary), and gone with it."""
        watch = getattr(network, _ATTRIBUTE, None)
        if watch is None:
            watch = cls(network, lockstep)
            setattr(network, _ATTRIBUTE, watch)
        return watch

    def __init__(self, network: canopen.Network, lockstep: bool):
        self.network = network
        self.lockstep = lockstep
        self.frames = 0  # every frame this network received, ours echoed or not
        # the receive stamp of the last frame through (the kernel's on SocketCAN and
        # udp_multicast): how far the receive thread has caught up with the bus
        self.last_stamp = 0.0
        self._frames_at_cycle = 0
        self._cycle = 0  # the last cycle counted (drives report theirs; the first counts)
        # more than this in one cycle is a flood: the bus's cyclic frames plus the margin
        # (`expect_cyclic_frames`; a lone drive's own SYNC and PDOs are well inside it)
        self.frame_limit = FLOOD_MARGIN_FRAMES
        self._healths: list[Health] = []
        self._lock = threading.Lock()
        # master id -> [drives producing it, periodic task (real time), cycles per beat,
        # cycles to the next beat (lock-step)]
        self._beats: dict[int, list] = {}
        self._thread_stop: threading.Event | None = None
        deliver = network.notify

        def counting_notify(can_id: int, data: bytearray, timestamp: float) -> None:
            self.frames += 1
            self.last_stamp = timestamp
            deliver(can_id, data, timestamp)

        network.notify = counting_notify

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

    def count_cycle(self, cycle: int, warnings: list[str]) -> None:
        """Once per cycle of the bus (the first drive to report cycle `cycle` counts it):
        the load, and in lock-step the master's heartbeats in cycles."""
        if cycle <= self._cycle:
            return
        self._cycle = cycle
        for producers in self._beats.values():
            if producers[2]:
                producers[3] -= 1
                if producers[3] <= 0:
                    producers[3] = producers[2]
                    self.network.send_message(producers[4], bytes([cia301.NMT_OPERATIONAL]))
        frames, self._frames_at_cycle = self.frames - self._frames_at_cycle, self.frames
        if frames > self.frame_limit:
            warnings.append(f"bus overloaded: {frames} frames in one cycle (at most "
                            f"{self.frame_limit} expected)")

    def start_producing(self, master_id: int, period: float) -> None:
        """Beat as node `master_id` (NMT operational) every MASTER_HEARTBEAT_MS: on the wall
        clock in real time (canopen's periodic send), every N cycles in lock-step; once for
        every drive that asks."""
        with self._lock:
            producers = self._beats.get(master_id)
            if producers is not None:
                producers[0] += 1
                return
            cob_id = cia301.HEARTBEAT_BASE + master_id
            if self.lockstep:
                cycles = max(1, round(MASTER_HEARTBEAT_MS * 1e-3 / period))
                self._beats[master_id] = [1, None, cycles, cycles, cob_id]
            else:
                task = self.network.send_periodic(cob_id, bytes([cia301.NMT_OPERATIONAL]),
                                                  MASTER_HEARTBEAT_MS * 1e-3)
                self._beats[master_id] = [1, task, 0, 0, cob_id]

    def stop_producing(self, master_id: int) -> None:
        with self._lock:
            producers = self._beats.get(master_id)
            if producers is None:
                return
            producers[0] -= 1
            if producers[0] <= 0:
                del self._beats[master_id]
                if producers[1] is not None:
                    producers[1].stop()

    def watch_clock(self) -> None:
        """Real time: one thread polls every drive's heartbeat (started with the first)."""
        with self._lock:
            if self._thread_stop is not None:
                return
            stop = self._thread_stop = threading.Event()
        threading.Thread(target=self._watch_clock, args=(stop,), daemon=True,
                         name="heartbeat-watch").start()

    def _watch_clock(self, stop: threading.Event) -> None:
        while True:
            with self._lock:
                healths = list(self._healths)
            periods = [h.heartbeat_ms for h in healths if h.heartbeat_ms > 0]
            # a quarter of the shortest producer period
            if stop.wait(min(periods, default=MASTER_HEARTBEAT_MS) / 4000.0):
                return
            now = time.monotonic()
            for health in healths:
                health.check_clock(now)


class Health:
    """Boot-up, heartbeat and EMCY of node `node_id`; the bus's jobs through its `BusWatch`.

    `on_failure(error)` is called once when the drive is lost; `on_emergency(code, register)`
    for every EMCY. Both run in the network's receive thread (or the watchdog's).
    """

    def __init__(self, network: canopen.Network, node: canopen.RemoteNode, name: str, *,
                 lockstep: bool, on_failure: Callable[[DriveError], None],
                 on_emergency: Callable[[int, int], None], warnings: list[str],
                 timeout_factor: float = 2.0):
        self.network = network
        self.bus = BusWatch.of(network, lockstep)
        self.name = name
        self.lockstep = lockstep
        self.timeout_factor = timeout_factor
        self.warnings = warnings
        self.heartbeat_ms = 0
        self.last_heartbeat: float | None = None  # time.monotonic() of the last beat
        self.booted = threading.Event()  # set by the boot-up message (heartbeat state 0)
        self._cycles = 0
        self._cycles_silent = 0
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

    def watch(self, heartbeat_ms: int) -> None:
        """Consume the drive's heartbeat from now on (its producer time is `heartbeat_ms`)."""
        self.heartbeat_ms = heartbeat_ms
        self.last_heartbeat = time.monotonic()
        self._cycles_silent = 0
        self._in_use = True
        self.bus.restart_count()  # bring-up traffic is not load
        if not self.lockstep and heartbeat_ms > 0:
            self.bus.watch_clock()

    def expect_cyclic_frames(self, frames: int) -> None:
        """The bus carries `frames` a cycle by design (SYNC and every drive's PDOs): an
        in-process link with many drives on it is not flooded by their PDOs."""
        self.bus.expect_cyclic_frames(frames)

    def restart_count(self) -> None:
        """Bus load counts from now: the bring-up of the other drives on a shared bus is not
        load (`driver.drive_group.CanOpenBus.started`)."""
        self.bus.restart_count()

    def _on_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if data and data[0] == cia301.NMT_BOOT_UP:
            self.booted.set()
            if self._in_use:
                self._on_failure(DriveLost(f"{self.name}: drive rebooted (boot-up message) "
                                           "while in use"))
        self.last_heartbeat = time.monotonic()
        self._cycles_silent = 0

    def count_cycle(self, period: float) -> None:
        """After each cycle: the bus's jobs (once per bus), and in lock-step the drive's
        heartbeat judged in cycles."""
        self._cycles += 1
        self.bus.count_cycle(self._cycles, self.warnings)
        if self.lockstep and self._in_use and self.heartbeat_ms > 0:
            self._cycles_silent += 1
            limit = round(self.timeout_factor * self.heartbeat_ms * 1e-3 / period)
            if self._cycles_silent > limit:
                self._lost(f"{self._cycles_silent} cycles ({self._cycles_silent * period:.3f} s "
                           "of drive time)")

    def check_clock(self, now: float) -> None:
        """Real time, from the bus's watch thread: lost when silent past the timeout."""
        last = self.last_heartbeat
        if last is None or not self._in_use or self.heartbeat_ms <= 0:
            return
        silent = now - last
        if silent > self.timeout_factor * self.heartbeat_ms / 1000.0:
            self._lost(f"{silent * 1e3:.0f} ms")

    def _lost(self, how_long: str) -> None:
        self._in_use = False  # one verdict per loss
        error = DriveLost(f"{self.name}: heartbeat missing for {how_long} (producer period "
                          f"{self.heartbeat_ms} ms)")
        log.error("%s", error)
        self._on_failure(error)

    # --- the master's own heartbeat ---------------------------------------------------------

    def start_producing(self, master_id: int, period: float) -> None:
        """The master's heartbeat this drive consumes (the bus produces it once)."""
        self.stop_producing()
        self._master_id = master_id
        self.bus.start_producing(master_id, period)

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
