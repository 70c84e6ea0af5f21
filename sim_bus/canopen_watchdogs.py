"""The virtual drive's CANopen watchdogs: its own heartbeat (0x1017), and its watch over the
master: the consumer heartbeat (0x1016) and SYNC/RPDO silence, which end in the device's
abort-connection reaction.

Real time: both run on the wall clock. Lock-step: the drive's time *is* the SYNC count, so the
heartbeats (its own and the master's, `driver.canopen_health`) are produced and judged in
cycles, and they fall on the same cycles in every run. A wall-clock producer in a lock-step run
beats at a rate unrelated to the drive's time (ten drive seconds pass in one wall second, or one
wall second passes on a busy host without a single cycle), so no consumer could judge it
deterministically. SYNC silence has no lock-step form: without SYNC the drive's time stands
still, so there is nothing to count; a lock-step link has its master in the same process anyway.
"""

import math
import threading
import time
from collections.abc import Callable

from protocol import cia301, objects

# the master's cycle can stall this long before the drive stops the joint: five times the
# master's heartbeat period (driver.canopen_health), and within the 1 s for SIGKILL
DEFAULT_SILENCE_TIMEOUT = 0.5  # s
WATCH_POLL = 0.01  # s between wall-clock checks


class HeartbeatProducer:
    """0x1017 heartbeat of node `node_id`: a wall-clock thread in real time, every N cycles in
    lock-step. The first beat comes one period after the boot-up message, as on real devices:
    a beat right behind the boot-up can overtake it in a master waiting for the boot-up
    (canopen's own wait_for_bootup reads the latest state)."""

    def __init__(self, send: Callable[[int, bytes], None], node_id: int,
                 nmt_state: Callable[[], int], lockstep: bool):
        self._send, self._cob_id = send, cia301.HEARTBEAT_BASE + node_id
        self._nmt_state = nmt_state
        self._lockstep = lockstep
        self._stop: threading.Event | None = None
        self._cycles_per_beat = 0
        self._cycles = 0

    def start(self, period_ms: int, cycle_period: float) -> None:
        self.stop()
        if period_ms <= 0:
            return
        if self._lockstep:
            self._cycles_per_beat = max(1, round(period_ms * 1e-3 / cycle_period))
            self._cycles = 0
            return
        self._stop = stop = threading.Event()
        threading.Thread(target=self._run, args=(stop, period_ms * 1e-3), daemon=True,
                         name=f"heartbeat-0x{self._cob_id:X}").start()

    def stop(self) -> None:
        self._cycles_per_beat = 0
        if self._stop is not None:
            self._stop.set()
            self._stop = None

    def count_cycle(self) -> None:
        if self._cycles_per_beat:
            self._cycles += 1
            if self._cycles >= self._cycles_per_beat:
                self._cycles = 0
                self._beat()

    def _run(self, stop: threading.Event, period: float) -> None:
        while not stop.wait(period):
            self._beat()

    def _beat(self) -> None:
        state = self._nmt_state()
        # a beat never carries 0: that is the boot-up message, sent once by the reset itself.
        # A beat that read the state while a reset ran (this thread preempted on a busy host
        # between the read and the send) would reach the master as a second boot-up, and a
        # master that is already driving takes that for a reboot
        if state != cia301.NMT_BOOT_UP:
            self._send(self._cob_id, bytes([state]))


class MasterWatch:
    """Declares the master lost (`on_lost(reason)`) when a consumer heartbeat of 0x1016 stops
    (monitoring starts with the first beat of that node, CiA 301), or when no SYNC and no
    RPDO came for `silence_timeout` s since the first one after NMT start (None: no silence
    watch). Once per loss: `rearm()` after a reset. `on_idle(now)` runs at every look (real
    time), for the drive's own time once its master is gone (`Cia402Device.run_alone`)."""

    def __init__(self, subscribe: Callable, read: Callable[[int, int], int], has_1016: bool,
                 on_lost: Callable[[str], None], lockstep: bool,
                 silence_timeout: float | None, name: str,
                 on_idle: Callable[[float], None] | None = None):
        self._subscribe, self._read = subscribe, read
        self._has_1016 = has_1016
        self._on_lost = on_lost
        self._on_idle = on_idle
        self._lockstep = lockstep
        self._silence_timeout = None if lockstep else silence_timeout
        self._name = name
        self._lock = threading.Lock()
        self._consumers: dict[int, float] = {}  # node id -> consumer time (s)
        self._beats: dict[int, float] = {}  # node id -> last beat (monotonic s, or cycles)
        self._subscribed: set[int] = set()
        self._last_activity: float | None = None
        self._cycle = 0
        self._first_due = 0.0  # lock-step: no beat can be late before this cycle
        self._period = 1e-3
        self._lost = False
        self._stop = threading.Event()
        if not lockstep:
            threading.Thread(target=self._run, daemon=True, name=f"master-watch-{name}").start()

    def configure(self, cycle_period: float) -> None:
        """(Re)read 0x1016 after a reset or a write to it."""
        consumers = {}
        if self._has_1016:
            for sub in range(1, self._read(objects.CONSUMER_HEARTBEAT, 0) + 1):
                entry = self._read(objects.CONSUMER_HEARTBEAT, sub)
                node = entry >> cia301.HEARTBEAT_CONSUMER_NODE_SHIFT & 0xFF
                time_ms = entry & cia301.HEARTBEAT_CONSUMER_TIME_MASK
                if 1 <= node <= 127 and time_ms > 0:
                    consumers[node] = time_ms * 1e-3
        with self._lock:
            self._consumers = consumers
            self._beats = {node: when for node, when in self._beats.items() if node in consumers}
            self._period = cycle_period
            self._first_due = 0
        for node in consumers:
            if node not in self._subscribed:
                self._subscribed.add(node)
                self._subscribe(cia301.HEARTBEAT_BASE + node, self._on_beat)

    def rearm(self) -> None:
        with self._lock:
            self._lost = False
            self._beats.clear()
            self._last_activity = None

    def stop_silence_watch(self) -> None:
        """The PDOs stopped (NMT pre-operational or stopped): no silence to judge."""
        with self._lock:
            self._last_activity = None

    def activity(self) -> None:
        """A SYNC or an RPDO arrived."""
        self._last_activity = time.monotonic()

    def _on_beat(self, can_id: int, data: bytes, timestamp: float) -> None:
        node = can_id - cia301.HEARTBEAT_BASE
        with self._lock:
            if node in self._consumers:
                if node not in self._beats:
                    self._first_due = 0  # a newly watched beat: look at the next cycle
                self._beats[node] = self._cycle if self._lockstep else time.monotonic()

    def count_cycle(self) -> None:
        """Lock-step: one cycle of drive time passed. The beats are looked at only from the
        first cycle at which one of them could be late (a beat only moves that later)."""
        with self._lock:
            self._cycle += 1
            if self._cycle < self._first_due:
                return
            late = [(node, self._cycle - last) for node, last in self._beats.items()
                    if (self._cycle - last) * self._period > self._consumers[node]]
            self._first_due = min((last + self._consumers[node] / self._period
                                   for node, last in self._beats.items()), default=math.inf)
        if late:
            node, cycles = late[0]
            self._lose(f"master heartbeat (node {node}) missing for {cycles} cycles "
                       f"({cycles * self._period:.3f} s of drive time)")

    def _run(self) -> None:
        while not self._stop.wait(WATCH_POLL):
            now = time.monotonic()
            with self._lock:
                late = [(node, now - last) for node, last in self._beats.items()
                        if now - last > self._consumers[node]]
                last_activity = self._last_activity
            if late:
                node, silent = late[0]
                self._lose(f"master heartbeat (node {node}) missing for {silent * 1e3:.0f} ms")
            elif (self._silence_timeout is not None and last_activity is not None
                  and now - last_activity > self._silence_timeout):
                self._lose(f"no SYNC or RPDO for {(now - last_activity) * 1e3:.0f} ms")
            if self._on_idle is not None:
                self._on_idle(now)

    def _lose(self, reason: str) -> None:
        with self._lock:
            if self._lost:
                return
            self._lost = True
            self._beats.clear()
            self._last_activity = None
        self._on_lost(f"{self._name}: {reason}")

    def close(self) -> None:
        self._stop.set()
