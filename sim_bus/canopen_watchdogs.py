"""The virtual drive's CANopen watchdogs: its own heartbeat (0x1017), and its watch over the
master: the consumer heartbeat (0x1016) and SYNC/RPDO silence, which end in the device's
abort-connection reaction.

Each runs on the drive's own time, which it is given (`driver.clock`: `WallClock.timers()` or
`DriveClock.timers()`), with one code path: a real drive keeps its own clock whatever its
master does. In real time that is the wall clock, each job a thread of its own. In lock-step
it is the SYNCs the drive took times the period: the heartbeats (its own and the master's,
`driver.canopen_health`) are produced and judged in cycles and fall on the same cycles in every
run, where a wall-clock producer would beat at a rate unrelated to the drive's time (ten drive
seconds pass in one wall second, or one wall second passes on a busy host without a single
cycle) and no consumer could judge it deterministically. SYNC silence cannot happen on drive
time: without SYNC it stands still (a lock-step link has its master in the same process anyway).
"""

import threading
from collections.abc import Callable
from typing import Protocol

from protocol import cia301, objects

# the master's cycle can stall this long before the drive stops the joint: five times the
# master's heartbeat period (driver.canopen_health), and within the 1 s for SIGKILL
DEFAULT_SILENCE_TIMEOUT = 0.5  # s
WATCH_POLL = 0.01  # s of the drive's time between looks at the master


class OwnTime(Protocol):
    """A party's own time (`driver.clock.WallTimers` or `DriveTimers`; this layer sits below
    the driver, so it names only what it uses)."""

    def now(self) -> float: ...

    def tick(self, period: float) -> None: ...

    def every(self, interval: float, job: Callable[[float], None]) -> Callable[[], None]: ...

    def later(self, delay: float, job: Callable[[], None]) -> None: ...


class Clock(Protocol):
    """What a virtual drive is given (`driver.clock.clock_for`): it makes the drive's own
    time."""

    def timers(self) -> OwnTime: ...


class HeartbeatProducer:
    """0x1017 heartbeat of node `node_id`, every period of the drive's own `time`. The first
    beat comes one period after the boot-up message, as on real devices: a beat right behind
    the boot-up can overtake it in a master waiting for the boot-up (canopen's own
    wait_for_bootup reads the latest state)."""

    def __init__(self, send: Callable[[int, bytes], None], node_id: int,
                 nmt_state: Callable[[], int], time: OwnTime):
        self._send, self._cob_id = send, cia301.HEARTBEAT_BASE + node_id
        self._nmt_state = nmt_state
        self._time = time
        self._stop: Callable[[], None] | None = None
        # a (re)start comes from the SDO server's thread (0x1017 written) and from the boot
        # after a reset (its own thread in real time) at once: without the lock both beat,
        # and the stop of one of them is lost (a drive whose heartbeat "stops" beats on)
        self._lock = threading.Lock()

    def start(self, period_ms: int) -> None:
        with self._lock:
            self._stop_beating()
            if period_ms > 0:
                self._stop = self._time.every(period_ms * 1e-3, self._beat)

    def stop(self) -> None:
        with self._lock:
            self._stop_beating()

    def _stop_beating(self) -> None:
        if self._stop is not None:
            self._stop()
            self._stop = None

    def _beat(self, now: float) -> None:
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
    watch), judged every WATCH_POLL of the drive's own `time`. Once per loss: `rearm()` after a
    reset. `on_idle(now)` runs at every look, for the drive's own cycles once its master is
    gone (`Cia402Device.run_alone`)."""

    def __init__(self, subscribe: Callable, read: Callable[[int, int], int], has_1016: bool,
                 on_lost: Callable[[str], None], time: OwnTime,
                 silence_timeout: float | None, name: str,
                 on_idle: Callable[[float], None] | None = None):
        self._subscribe, self._read = subscribe, read
        self._has_1016 = has_1016
        self._on_lost = on_lost
        self._on_idle = on_idle
        self._time = time
        self._silence_timeout = silence_timeout
        # whether `activity` is worth calling: without a silence watch nothing reads it
        self.watches_silence = silence_timeout is not None
        self._name = name
        self._lock = threading.Lock()
        self._consumers: dict[int, float] = {}  # node id -> consumer time (s)
        self._beats: dict[int, float] = {}  # node id -> last beat (s of the drive's time)
        self._subscribed: set[int] = set()
        self._last_activity: float | None = None
        self._lost = False
        self._stop = time.every(WATCH_POLL, self._look)

    def configure(self) -> None:
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
        self._last_activity = self._time.now()

    def _on_beat(self, can_id: int, data: bytes, timestamp: float) -> None:
        node = can_id - cia301.HEARTBEAT_BASE
        with self._lock:
            if node in self._consumers:
                self._beats[node] = self._time.now()

    def _look(self, now: float) -> None:
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
        self._stop()
