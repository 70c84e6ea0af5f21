"""The heartbeat consumer (`driver.canopen_health.Health`) judges silence on what its bus's
receive path has handled: frames are handled in order, so a silence is the drive's once a
frame received past the deadline went through, and a receive path that lags (a thread held up
with its process, resuming with the beats queued meanwhile) gets the clock's `receive_grace`
to catch up before a verdict. A clock of the test's own makes every step exact: no wall
time, no thread."""

import canopen

from driver.canopen_health import Health
from driver.clock import WallClock
from driver.interface import DriveLost
from protocol import cia301

NODE = 2
HEARTBEAT_MS = 100  # the drive's producer time: a timeout of 200 ms (the factor of 2)
BEAT = cia301.HEARTBEAT_BASE + NODE
TPDO = 0x182  # another frame of the bus (the drive's or another drive's)
OPERATIONAL = bytes([cia301.NMT_OPERATIONAL])


class StoppedWallClock(WallClock):
    """The wall clock's rules (its `receive_grace`) at the times the test sets, with no
    thread of its own (`runs_alone` off: the test calls `tick`)."""

    runs_alone = False

    def __init__(self) -> None:
        self.t = 0.0

    def now(self) -> float:
        return self.t


def watched() -> tuple[canopen.Network, StoppedWallClock, Health, list[DriveLost]]:
    network = canopen.Network()
    clock = StoppedWallClock()
    lost: list[DriveLost] = []
    node = canopen.RemoteNode(NODE, canopen.ObjectDictionary())
    health = Health(network, node, "node 2", clock=clock, on_failure=lost.append,
                    on_emergency=lambda code, register: None, warnings=[])
    health.watch(HEARTBEAT_MS, 1e-3)
    return network, clock, health, lost


def handled(network: canopen.Network, clock: StoppedWallClock, at: float, can_id: int,
            received: float) -> None:
    """A frame received at `received` (its stamp) handled by the receive path at `at`."""
    clock.t = at
    network.notify(can_id, OPERATIONAL if can_id == BEAT else b"\x00" * 8, received)


def look(health: Health, clock: StoppedWallClock, at: float) -> None:
    clock.t = at
    health.bus.tick()


def test_beats_queued_behind_a_held_up_receive_path_are_no_loss():
    network, clock, health, lost = watched()
    handled(network, clock, 0.0, BEAT, 0.0)
    # the receive path held up from 0.05 on; the drive beats at 0.1 and 0.2 meanwhile
    look(health, clock, 0.205)  # past the timeout: nothing handled past it, grace runs
    assert lost == []
    handled(network, clock, 0.21, BEAT, 0.1)  # the path resumes with what queued
    handled(network, clock, 0.21, BEAT, 0.2)
    look(health, clock, 0.23)
    assert lost == []


def test_a_silent_drive_on_a_busy_bus_is_lost_at_the_timeout():
    network, clock, health, lost = watched()
    handled(network, clock, 0.0, BEAT, 0.0)
    for k in range(1, 206):  # the bus's other frames, handled as they come
        handled(network, clock, k * 1e-3, TPDO, k * 1e-3)
    look(health, clock, 0.205)
    assert len(lost) == 1 and "heartbeat missing for 205 ms" in str(lost[0])


def test_a_silent_drive_on_a_silent_bus_is_lost_after_the_grace():
    network, clock, health, lost = watched()
    handled(network, clock, 0.0, BEAT, 0.0)
    look(health, clock, 0.2 + WallClock.receive_grace - 0.001)
    assert lost == []
    look(health, clock, 0.2 + WallClock.receive_grace + 0.001)
    assert len(lost) == 1 and "heartbeat missing for 221 ms" in str(lost[0])


def test_a_drive_that_never_beats_counts_from_the_watch():
    network, clock, health, lost = watched()
    for k in range(1, 206):
        handled(network, clock, k * 1e-3, TPDO, k * 1e-3)
    look(health, clock, 0.205)
    assert len(lost) == 1
