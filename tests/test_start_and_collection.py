"""A cold solve of every joint at start and a full garbage collection mid-run cost no watchdog,
in lock-step and in real time (issue 23).

The robot is TALOS's arm (7 joints on four CAN buses, a virtual drive per joint in this
process): its first cycle solves every joint cold at once, and halfway through the run a
subscriber (it runs in the loop's thread, as a collection would stop it) makes a heap of
cyclic garbage and forces a full collection, the worst the collector can do in a cycle. The
watchdogs a stall between cycles meets are the drives' SYNC-silence watch (0.5 s) and their
consumer of the master's heartbeat (0.8 s), and the master's consumer of each drive's
heartbeat (2 producer periods, 200 ms): on the wall clock in real time, counted in cycles in
lock-step. Passing means the run reached its duration with no drive
failed and every drive still enabled (read back). The start-up heap is frozen as actuatord
runs (`driver.clock.collector_off_the_cycle`), so the collection walks the garbage and what
the loop made, not the process's few hundred thousand long-lived objects."""

import gc
import time

import pytest

from controller.loop import ControlLoop, LoopOptions
from controller.messages import JointStates
from controller.mpc import BatchMpc, JointProblem
from controller.problem import OcpSettings
from driver.clock import clock_for, collector_off_the_cycle
from driver.interface import SAMPLE_POSITION
from protocol.cia402 import State
from robot.description import load_robot, robot_path
from robot.wiring import open_robot
from tests.conftest import as_a_real_time_master

DURATION = 1.0  # s of drive time
COLLECT_AT = 0.5  # s of drive time
# reference cycles made before the collection (each a list holding itself): 100 000 made the
# stall 37-49 ms at load 4, and beside two CPU-bound loops the making and collecting held the
# interpreter past 200 ms, which the virtual drives of this process (their heartbeat thread
# needs the interpreter too) cannot ride through, where hardware would; 20 000 is still
# several times what a loop leaves between two of the collector's own passes
GARBAGE = 20_000
# s: the collection stops the loop this long at least, a stall the run must ride through
STALL_AT_LEAST = 0.002


class ForcedCollection:
    """A subscriber that, once at COLLECT_AT, makes GARBAGE cycles and collects them all."""

    def __init__(self):
        self.seconds: float | None = None
        self.collected = 0

    def __call__(self, message) -> None:
        if self.seconds is None and isinstance(message, JointStates) and message.t >= COLLECT_AT:
            gc.disable()  # all of it waits for the one collection
            try:
                for _ in range(GARBAGE):
                    cycle: list = []
                    cycle.append(cycle)
                start = time.perf_counter()
                self.collected = gc.collect()
                self.seconds = time.perf_counter() - start
            finally:
                gc.enable()


@pytest.mark.parametrize("lockstep", [True, False], ids=["lockstep", "real_time"])
@pytest.mark.real_time
def test_a_cold_start_of_every_joint_and_a_full_collection_cost_no_watchdog(lockstep):
    robot = load_robot(robot_path("talos_arm"))
    connection = open_robot(robot, sim=True, clock=clock_for(lockstep), seed=0, period=1e-3,
                            response_timeout=1.0 if lockstep else 0.1)
    collection = ForcedCollection()
    try:
        group = connection.group
        batch = BatchMpc([JointProblem(joint.model, OcpSettings(), reference=joint.reference)
                          for joint in robot.joints])
        loop = ControlLoop(group, batch, LoopOptions(period=1e-3, clock=clock_for(lockstep),
                                                   duration=DURATION), [collection])
        with as_a_real_time_master(), collector_off_the_cycle():
            group.start()
            report = loop.run()
        # read back, not assumed: every drive still obeys its master
        states = [drive.state() for drive in group.drives]
    finally:
        connection.close()
    assert report.exit_code == 0, (report.reason, states)
    assert report.cycles == round(DURATION / 1e-3), report.summary()
    assert states == [State.OPERATION_ENABLED] * len(robot.joints), states
    # the first decision solved all seven joints cold, and it was timed on its own
    assert report.cold_solve_us > 0
    # the collection happened mid-run, found the garbage, and stopped the loop for real
    assert collection.seconds is not None and collection.collected >= GARBAGE - 1
    assert collection.seconds >= STALL_AT_LEAST, collection.seconds


def test_the_first_plans_are_solved_from_where_the_joints_are_before_any_drive_is_enabled():
    """`DriveGroup.start(configured=loop.solve_first)`, as actuatord starts: every joint's
    cold solve runs between configuring and enabling, from the measured positions, and the
    run keeps its time as the cold solve (the first cycle then starts warm)."""
    robot = load_robot(robot_path("talos_arm"))
    connection = open_robot(robot, sim=True, clock=clock_for(True), seed=0, period=1e-3)
    seen: dict = {}
    try:
        group = connection.group
        batch = BatchMpc([JointProblem(joint.model, OcpSettings(), reference=joint.reference)
                          for joint in robot.joints])
        loop = ControlLoop(group, batch, LoopOptions(period=1e-3, clock=clock_for(True),
                                                   duration=0.05))

        def configured(table):
            seen["states"] = [drive.state() for drive in group.drives]
            seen["measured"] = table[:, SAMPLE_POSITION].copy()
            seen["actual"] = [connection.devices[joint.name].plant.position
                              for joint in robot.joints]
            loop.solve_first(table)
            seen["cold_solve_us"] = loop.report.cold_solve_us

        group.start(configured=configured)
        report = loop.run()
    finally:
        connection.close()
    assert State.OPERATION_ENABLED not in seen["states"], seen["states"]
    # the encoder's reading of where each joint rests (a count's resolution)
    assert seen["measured"] == pytest.approx(seen["actual"], abs=1e-4)
    assert report.exit_code == 0, report.reason
    assert seen["cold_solve_us"] > 0 and report.cold_solve_us == seen["cold_solve_us"]
