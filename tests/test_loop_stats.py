"""What the loop reports as it runs costs the cycle little however long the run: LoopStats'
percentiles cover the cycles since the last LoopStats (the last message: the run's), and a
Plan is built from its arrays' bytes, the same message as field by field."""

import contextlib
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from controller import messages
from controller.loop import ControlLoop, LoopOptions, LoopReport
from controller.mpc import BatchMpc, JointProblem
from controller.policy import PlanSnapshot
from controller.problem import OcpSettings
from driver.clock import DriveClock, RingStats
from driver.drive_group import DriveGroup
from model.parameters import load_model
from robot.description import JointSpec, RobotSpec, default_reference
from robot.wiring import open_robot

MODEL = load_model()


def test_recent_percentiles_are_those_of_the_last_values_across_the_ring_wrap():
    ring = RingStats(window=10)
    values = np.arange(1.0, 24.0) ** 1.5  # 23 values: the ring wrapped twice
    for value in values:
        ring.add(value)
    for last in (1, 3, 7, 10):
        assert ring.recent_percentiles((50, 99), last) == np.percentile(
            values[-last:], [50, 99]).tolist()
    assert ring.recent_percentiles((50,), 50) == [float(np.percentile(values[-10:], 50))]
    assert np.isnan(ring.recent_percentiles((99,), 0)[0])


@contextlib.contextmanager
def _elbow_in_lockstep() -> Iterator[tuple[DriveGroup, BatchMpc]]:
    """A robot of one joint on its virtual drive, started on drive time, and its MPC."""
    spec = RobotSpec(name="stats", period_us=1000,
                     joints=(JointSpec("elbow", "can0", 1, MODEL, None, {},
                                       default_reference(MODEL.limits)),),
                     bitrates={}, source=Path("<test>"))
    connection = open_robot(spec, sim=True, clock=DriveClock(), seed=0, period=1e-3,
                            response_timeout=1.0)
    try:
        connection.group.start()
        yield connection.group, BatchMpc([JointProblem(MODEL, OcpSettings(horizon=10))])
    finally:
        connection.close()


def test_loop_stats_cover_the_cycles_since_the_last_and_the_last_the_run():
    stats = []
    with _elbow_in_lockstep() as (group, batch):
        loop = ControlLoop(group, batch,
                           LoopOptions(clock=DriveClock(), duration=0.25, stats_every=0.1),
                           [lambda m: stats.append(m) if type(m) is messages.LoopStats else None])
        report = loop.run()
    assert report.cycles == 250 and [m.cycles for m in stats] == [100, 200, 250]
    solve = report.solve.recent()  # every cycle's but the cold first
    since = 0
    for message in stats[:-1]:
        until = message.cycles - 1
        median, p99 = np.percentile(solve[since:until], [50, 99])
        assert (message.solve_median_us, message.solve_p99_us) == (median, p99)
        assert message.solve_max_us == solve[:until].max()
        since = until
    last = stats[-1]
    assert (last.solve_median_us, last.solve_p99_us) == tuple(np.percentile(solve, [50, 99]))


def test_a_lockstep_run_reports_the_wall_time_of_its_whole_cycle():
    """On drive time the loop never sleeps, so the run's wall time over its cycles is what a
    whole cycle costs (drives, MPC, master, telemetry): within the run's own wall time,
    above its MPC tick, in the summary and the report."""
    with _elbow_in_lockstep() as (group, batch):
        loop = ControlLoop(group, batch, LoopOptions(clock=DriveClock(), duration=0.3))
        before = time.perf_counter()
        report = loop.run()
        run_wall = time.perf_counter() - before
    wall = report.wall_per_cycle_us
    assert report.cycles == 300
    assert report.solve.percentile(50) < wall <= run_wall / (report.cycles - 1) * 1e6
    assert report.figures()["wall_per_cycle_us"] == wall
    assert f"wall time a cycle {wall:.1f} us" in report.summary()
    # a run that ended before its second cycle has no such figure
    assert LoopReport().figures()["wall_per_cycle_us"] is None


def test_a_wire_subscriber_gets_the_one_joint_view_as_the_bytes_of_its_messages():
    """A subscriber that sends bytes (actuatord's publisher) gets each cycle's State, Command
    and SolverStats as one `EncodedJointView` and each Plan as `Encoded`, a subscriber of
    messages the messages: the same bytes, cycle for cycle; every other message reaches both
    as itself."""
    views, wire = [], []
    with _elbow_in_lockstep() as (group, batch):
        loop = ControlLoop(group, batch, LoopOptions(clock=DriveClock(), duration=0.05),
                           [views.append], wire_subscribers=[wire.append])
        loop.run()
    encoded = [m for m in wire if type(m) is messages.EncodedJointView]
    assert len(encoded) == 50
    own = [m for m in views if type(m) in messages.VIEW_CLASSES]
    assert [part for m in encoded for part in m.parts()] == [m.SerializeToString()
                                                            for m in own]
    assert [m.t for m in encoded] == [m.t for m in own[::3]]
    # the plans as their bytes too, every other message as itself
    plans = [m for m in wire if type(m) is messages.Encoded]
    assert [m.kind for m in plans] == [messages.Plan] * 5
    assert [m.decoded() for m in plans] == [m for m in views if type(m) is messages.Plan]
    others = [m for m in wire if type(m) not in (messages.EncodedJointView, messages.Encoded)]
    assert {type(m) for m in others} == {messages.LoopStats}
    assert others == [m for m in views if type(m) is messages.LoopStats]


@pytest.mark.subprocess
def test_a_fresh_loop_has_its_encoders_loaded_before_its_first_cycle():
    """Built, a one-joint loop has loaded the view's and the plan's encoders, and a robot's
    loop the JointStates' encoder: loaded from numba's cache in the first cycles instead, they
    held a real-time cycle 15-20 ms (14-23 cycles missed a start, one joint across two
    processes). A fresh process: none loaded before, and each loop loads its own only."""
    probe = ("from controller import messages; from controller.loop import ControlLoop, "
             "LoopOptions; from controller.mpc import BatchMpc, JointProblem; "
             "from controller.problem import OcpSettings; from driver.clock import DriveClock; "
             "from model.parameters import load_model; "
             "kernels = (messages._encode_view, messages._encode_plan, "
             "messages._encode_joint_states); "
             "assert not any(k.signatures for k in kernels); "
             "problem = JointProblem(load_model(), OcpSettings(horizon=5)); "
             "loop = lambda names: ControlLoop(type('Joints', (), {'names': names})(), "
             "BatchMpc([problem] * len(names)), LoopOptions(clock=DriveClock())); "
             "loop(['elbow']); print(*(len(k.signatures) for k in kernels)); "
             "loop(['shoulder', 'elbow']); print(*(len(k.signatures) for k in kernels))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines() == ["1 1 0", "1 1 1"]


def test_a_plan_from_its_arrays_bytes_is_the_plan_field_by_field():
    rng = np.random.default_rng(1)
    states = rng.normal(size=(101, 3))  # strided columns, as the solver's trajectories give
    snapshot = PlanSnapshot(0.25, 1e-3, states[:, 0], states[:, 1], rng.normal(size=100),
                            rng.normal(size=101))
    expected = messages.Plan(
        t=0.25, dt=1e-3, position=states[:, 0].tolist(), velocity=states[:, 1].tolist(),
        current=snapshot.current.tolist(),
        reference_position=snapshot.reference_position.tolist())
    assert messages.plan(snapshot) == expected
    # what a Zenoh publisher sends: protobuf's own bytes
    assert messages.plan_bytes(snapshot) == expected.SerializeToString()
    empty = np.zeros(0)
    assert messages.plan(PlanSnapshot(0.0, 1e-3, empty, empty, empty, empty)) == messages.Plan(
        dt=1e-3)
    for t in (0.0, -0.0):  # proto3 leaves 0.0 out, not -0.0
        at_zero = PlanSnapshot(t, 1e-3, empty, empty, snapshot.current, empty)
        assert messages.plan_bytes(at_zero) == messages.Plan(
            t=t, dt=1e-3, current=snapshot.current.tolist()).SerializeToString()
    long = np.arange(3000.0)  # a length of two varint bytes and more
    assert list(messages.plan(PlanSnapshot(0.0, 1e-3, long, long, long, long)).current) == (
        long.tolist())


def test_a_wire_subscriber_gets_a_robots_joint_states_as_their_bytes():
    """A robot of several joints: a subscriber that sends bytes gets each cycle's JointStates
    as `Encoded`, a subscriber of messages the message: the same bytes, cycle for cycle."""
    spec = RobotSpec(name="wire", period_us=1000,
                     joints=tuple(JointSpec(name, "can0", node, MODEL, None, {},
                                            default_reference(MODEL.limits))
                                  for node, name in enumerate(("shoulder", "elbow"), start=1)),
                     bitrates={}, source=Path("<test>"))
    views, wire = [], []
    connection = open_robot(spec, sim=True, clock=DriveClock(), seed=0, period=1e-3,
                            response_timeout=1.0)
    try:
        connection.group.start()
        batch = BatchMpc([JointProblem(MODEL, OcpSettings(horizon=10))] * 2)
        ControlLoop(connection.group, batch, LoopOptions(clock=DriveClock(), duration=0.05),
                    [views.append], wire_subscribers=[wire.append]).run()
    finally:
        connection.close()
    states = [m for m in views if type(m) is messages.JointStates]
    encoded = [m for m in wire if type(m) is messages.Encoded]
    assert len(states) == 50 and list(states[0].name) == ["shoulder", "elbow"]
    assert [m.kind for m in encoded] == [messages.JointStates] * 50
    assert [m.data for m in encoded] == [m.SerializeToString() for m in states]
    assert [m.t for m in encoded] == [m.t for m in states]
