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


def master_node_id(drive_node_id: int) -> int:
    """The id the master's heartbeat uses: 127, the top of the range, unless the drive has it."""
    return 127 if drive_node_id != 127 else 126


class Health:
    """Boot-up, heartbeat and EMCY of node `node_id`, and the frame count of the bus.

    `on_failure(error)` is called once when the drive is lost; `on_emergency(code, register)`
    for every EMCY. Both run in the network's receive thread (or the watchdog's).
    """

    def __init__(self, network: canopen.Network, node: canopen.RemoteNode, name: str, *,
                 lockstep: bool, on_failure: Callable[[DriveError], None],
                 on_emergency: Callable[[int, int], None], warnings: list[str],
                 timeout_factor: float = 2.0):
        self.network = network
        self.name = name
        self.lockstep = lockstep
        self.timeout_factor = timeout_factor
        self.warnings = warnings
        self.heartbeat_ms = 0
        self.last_heartbeat: float | None = None  # time.monotonic() of the last beat
        self.booted = threading.Event()  # set by the boot-up message (heartbeat state 0)
        self.frames = 0  # every frame this network received, ours echoed or not
        self._frames_at_cycle = 0
        # more than this in one cycle is a flood: the bus's cyclic frames plus the margin
        # (`expect_cyclic_frames`; a lone drive's own SYNC and PDOs are well inside it)
        self.frame_limit = FLOOD_MARGIN_FRAMES
        self._cycles_silent = 0
        self._in_use = False
        self._on_failure = on_failure
        self._on_emergency = on_emergency
        self._watchdog_stop = threading.Event()
        self._watchdog: threading.Thread | None = None
        self._beat_task = None
        self._beat_cob_id = 0
        self._cycles_per_beat = 0
        self._cycles_to_beat = 0
        network.subscribe(cia301.HEARTBEAT_BASE + node.id, self._on_heartbeat)
        node.emcy.add_callback(self._on_emcy)
        # count at canopen's single entry point for received frames (a python-can bus's
        # listener and the embedded link both call notify), so a flood is seen either way
        deliver = network.notify

        def counting_notify(can_id: int, data: bytearray, timestamp: float) -> None:
            self.frames += 1
            deliver(can_id, data, timestamp)

        network.notify = counting_notify

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
        self._frames_at_cycle = self.frames  # bring-up traffic is not load
        if self.lockstep or self._watchdog is not None or heartbeat_ms <= 0:
            return
        self._watchdog = threading.Thread(target=self._watch_clock, daemon=True,
                                          name=f"heartbeat-watch-{self.name}")
        self._watchdog.start()

    def expect_cyclic_frames(self, frames: int) -> None:
        """The bus carries `frames` a cycle by design (SYNC and every drive's PDOs): an
        in-process link with 32 drives on it is not flooded by its 129."""
        self.frame_limit = frames + FLOOD_MARGIN_FRAMES

    def restart_count(self) -> None:
        """Bus load counts from now: the bring-up of the other drives on a shared bus is not
        load (`driver.drive_group.CanOpenBus.started`)."""
        self._frames_at_cycle = self.frames

    def _on_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if data and data[0] == cia301.NMT_BOOT_UP:
            self.booted.set()
            if self._in_use:
                self._on_failure(DriveLost(f"{self.name}: drive rebooted (boot-up message) "
                                           "while in use"))
        self.last_heartbeat = time.monotonic()
        self._cycles_silent = 0

    def count_cycle(self, period: float) -> None:
        """After each cycle: the bus load, and in lock-step the heartbeats in cycles (the
        drive's judged, the master's produced)."""
        if self._cycles_per_beat:
            self._cycles_to_beat -= 1
            if self._cycles_to_beat <= 0:
                self._cycles_to_beat = self._cycles_per_beat
                self.network.send_message(self._beat_cob_id, bytes([cia301.NMT_OPERATIONAL]))
        frames, self._frames_at_cycle = self.frames - self._frames_at_cycle, self.frames
        if frames > self.frame_limit:
            self.warnings.append(f"bus overloaded: {frames} frames in one cycle (at most "
                                 f"{self.frame_limit} expected)")
        if self.lockstep and self._in_use and self.heartbeat_ms > 0:
            self._cycles_silent += 1
            limit = round(self.timeout_factor * self.heartbeat_ms * 1e-3 / period)
            if self._cycles_silent > limit:
                self._lost(f"{self._cycles_silent} cycles ({self._cycles_silent * period:.3f} s "
                           "of drive time)")

    def _watch_clock(self) -> None:
        """Real time: poll at a quarter of the producer period."""
        poll = self.heartbeat_ms / 4000.0
        timeout = self.timeout_factor * self.heartbeat_ms / 1000.0
        while not self._watchdog_stop.wait(poll):
            last = self.last_heartbeat
            if last is None or not self._in_use:
                continue
            silent = time.monotonic() - last
            if silent > timeout:
                self._lost(f"{silent * 1e3:.0f} ms")

    def _lost(self, how_long: str) -> None:
        self._in_use = False  # one verdict per loss
        error = DriveLost(f"{self.name}: heartbeat missing for {how_long} (producer period "
                          f"{self.heartbeat_ms} ms)")
        log.error("%s", error)
        self._on_failure(error)

    # --- the master's own heartbeat ---------------------------------------------------------

    def start_producing(self, master_id: int, period: float) -> None:
        """Beat as node `master_id` (NMT operational) every MASTER_HEARTBEAT_MS: on the wall
        clock in real time (canopen's periodic send), every N cycles in lock-step."""
        self.stop_producing()
        self._beat_cob_id = cia301.HEARTBEAT_BASE + master_id
        if self.lockstep:
            self._cycles_per_beat = max(1, round(MASTER_HEARTBEAT_MS * 1e-3 / period))
            self._cycles_to_beat = self._cycles_per_beat
        else:
            self._beat_task = self.network.send_periodic(
                self._beat_cob_id, bytes([cia301.NMT_OPERATIONAL]), MASTER_HEARTBEAT_MS * 1e-3)

    def stop_producing(self) -> None:
        self._cycles_per_beat = 0
        if self._beat_task is not None:
            self._beat_task.stop()
            self._beat_task = None

    # --- emergencies ------------------------------------------------------------------------

    def _on_emcy(self, error: EmcyError) -> None:
        self._on_emergency(error.code, error.register)

    def close(self) -> None:
        self._watchdog_stop.set()
        self._in_use = False
        self.stop_producing()
