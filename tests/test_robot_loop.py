"""Many joints in one cycle, in lock-step: one SYNC per bus, every joint in every telemetry
message, every joint tracking, a refused bus, and one joint's fault stopping them all."""

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zenoh

from controller.messages import JointStates
from driver import Sample
from driver.clock import DriveClock
from driver.drive_group import EthercatLine
from driver.ethercat_transport import EthercatTransport
from driver.interface import SAMPLE_POSITION, SAMPLE_STATUSWORD, SAMPLE_T
from protocol import cia301, telemetry
from protocol.cia402 import State, state_from_statusword
from robot.description import load_robot
from robot.wiring import open_robot
from sim_bus.faults import Fault
from sim_bus.plant import SensorNoise
from tests.conftest import free_port

ROBOTS = Path(__file__).resolve().parent.parent / "robots"
ARM = ROBOTS / "talos_arm.toml"
SETTLE = 1.0  # s, as actuatord's TRACKING_SETTLE: the approach from rest is not tracking
# rad: the wrists' soft friction model leaves 30..50 mrad on the exact model (talos_arm.toml);
# the sensor noise and the 19-bit encoder add well under 1 mrad. Twice the worst is the bound.
TRACKING_BOUND = 0.1


class _SyncCounter:
    """A peer on the master's side of an embedded link: counts the SYNCs the master sends."""

    def __init__(self):
        self.syncs = 0

    def notify(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if can_id == cia301.SYNC_COB_ID:
            self.syncs += 1


def test_sim_keeps_an_ethercat_line_on_ethercat_one_image_a_cycle():
    """--sim links talos_32's line of virtual slaves to the master's process image in this
    process: every joint is driven through the EtherCAT transport (CoE bring-up, cyclic
    synchronous torque through the ESI), each cycle is one exchange of the whole image, and
    each drive's physics advances exactly one period per cycle. (It used to turn the line into
    one CANopen link carrying 129 frames a cycle, which no real bus could.)"""
    connection = open_robot(load_robot(ROBOTS / "talos_32.toml"), sim=True, clock=DriveClock(),
                            seed=0, period=1e-3, response_timeout=1.0)
    try:
        group = connection.group
        [line] = group.segments
        assert isinstance(line, EthercatLine) and len(line.joints) == 32
        assert all(isinstance(drive.transport, EthercatTransport) for drive in group.drives)
        group.start()
        image = group.drives[0].transport.line
        frames, cycles = image.frames, {d.cycle_count for d in connection.devices.values()}
        assert len(cycles) == 1
        for _ in range(25):
            table = group.sync()
            group.command_currents(np.zeros(len(group)))
        assert group.warnings() == []
        assert image.frames == frames + 25
        assert {d.cycle_count for d in connection.devices.values()} == {cycles.pop() + 25}
        assert table.shape == (32, len(Sample._fields))
        assert set(table[:, SAMPLE_T]) == {25e-3}
        # in operation enabled, each joint where its drive says it is
        assert all(state_from_statusword(int(word)) is State.OPERATION_ENABLED
                   for word in table[:, SAMPLE_STATUSWORD])
        for row, name in zip(table, group.names, strict=True):
            device = connection.devices[name]
            assert abs(row[SAMPLE_POSITION] - device.plant.position) < 1e-5, name
    finally:
        connection.close()


def test_one_sync_per_bus_per_cycle_and_every_joint_sampled_in_it():
    robot = load_robot(ARM)
    connection = open_robot(robot, sim=True, clock=DriveClock(), seed=0, period=1e-3,
                            response_timeout=1.0)
    counters = []
    try:
        for link in connection.sim:
            counters.append(_SyncCounter())
            link.master_network.peers.append(counters[-1])
        group = connection.group
        group.start()
        for _ in range(20):
            samples = group.sync()
            group.command_currents([0.0] * len(group))
        assert [c.syncs for c in counters] == [20, 20, 20, 20]  # four buses, one SYNC each
        # one row per joint, all sampled in the same cycle
        assert samples.shape == (len(robot.joints), len(Sample._fields))
        assert set(samples[:, SAMPLE_T]) == {20e-3}
        devices = connection.devices
        assert {d.cycle_count for d in devices.values()} == {20}
        # each drive commissioned for its joint: the wrists' 3 A, the shoulders' 6 A
        assert [d.current_limit for d in group.drives] == [
            j.model.limits.current_max for j in robot.joints]
        wrist = devices["arm_left_7_joint"]
        assert math.isclose(wrist.position_window[1], 0.68 + 0.1, abs_tol=1e-5)
        assert math.isclose(wrist.trip_current, 4.0)
        states = group.quick_stop_all()
        assert [name for name, _ in states] == [j.name for j in robot.joints]
        assert all(d.state is not State.OPERATION_ENABLED for d in devices.values())
    finally:
        connection.close()


def test_a_fault_on_one_joint_names_it_and_the_group_stops_every_drive():
    robot = load_robot(ARM)
    connection = open_robot(robot, sim=True, clock=DriveClock(), seed=0, period=1e-3,
                            response_timeout=1.0,
                            faults=[("arm_left_3_joint", Fault.OVERCURRENT_TRIP, 0.01)])
    try:
        group = connection.group
        group.start()
        failure = None
        for _ in range(50):
            try:
                group.sync()
                group.command_currents([0.0] * len(group))
            except Exception as exc:
                failure = exc
                break
        assert failure is not None and failure.joint == "arm_left_3_joint"
        assert "0x2310" in str(failure)
        group.quick_stop_all()
        assert all(d.state is not State.OPERATION_ENABLED for d in connection.devices.values())
    finally:
        connection.close()


def _actuatord(*args: str, timeout: float = 900) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "commands.actuatord", "--sim", "--lockstep",
                           "--no-multicast-scouting", *args],
                          capture_output=True, text=True, timeout=timeout)


def test_the_arm_runs_five_seconds_with_every_joint_in_every_message_and_tracking():
    robot = load_robot(ARM)
    names = [j.name for j in robot.joints]
    port = free_port()
    prefix = "test/arm"
    received: list[bytes] = []
    # the test's session listens and subscribes first, actuatord connects to it: its
    # publisher knows the subscriber from its first message on (a lock-step run of 5 s is
    # over in about that: subscribing after actuatord started missed all but its last 200)
    config = zenoh.Config()
    config.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    config.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(config)
    proc = None
    try:
        subscriber = session.declare_subscriber(
            telemetry.key_expr(prefix, "joints"),
            lambda sample: received.append(sample.payload.to_bytes()))
        proc = subprocess.Popen(
            [sys.executable, "-m", "commands.actuatord", "--sim", "--lockstep", "--robot",
             str(ARM), "--duration", "5", "--prefix", prefix, "--connect",
             f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        out, err = proc.communicate(timeout=900)
        subscriber.undeclare()
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
        session.close()
    assert proc.returncode == 0, err
    assert "5000 cycles" in out
    messages = [telemetry.decode("JointStates", data) for data in received]
    assert len(messages) > 1000, f"only {len(messages)} joints messages arrived"
    assert all(list(m.name) == names and len(m.position) == len(m.current) == 7
               and len(m.solver_status) == 7 for m in messages)
    assert isinstance(messages[0], JointStates)
    tracked = [m for m in messages if m.t >= SETTLE]
    for j, name in enumerate(names):
        rms = math.sqrt(sum((m.position[j] - m.reference_position[j]) ** 2 for m in tracked)
                        / len(tracked))
        assert rms < TRACKING_BOUND, f"{name}: RMS tracking error {rms:.3f} rad"
    assert all(state == "operation enabled" for m in messages for state in m.drive_state)


def _robot(tmp_path: Path, buses: list[str]) -> Path:
    """The arm's first joint model eight times: (bus) per joint, node ids 1.. per bus."""
    text = '[robot]\nname = "eight"\nperiod_us = 1000\n'
    count: dict[str, int] = {}
    for k, bus in enumerate(buses):
        count[bus] = count.get(bus, 0) + 1
        text += (f'\n[[joints]]\nname = "j{k}"\nbus = "{bus}"\nnode_id = {count[bus]}\n'
                 f'model = "{ROBOTS / "models" / "talos_arm_shoulder.toml"}"\n')
    path = tmp_path / "eight.toml"
    path.write_text(text)
    return path


def test_eight_joints_on_one_bus_are_refused_and_on_four_buses_run(tmp_path):
    one = _actuatord("--robot", str(_robot(tmp_path, ["can0"] * 8)), "--duration", "0.1")
    assert one.returncode == 2
    assert one.stderr.count("\n") == 1 and "bus can0: 8 joints" in one.stderr
    assert "316 % of 1 Mbit/s" in one.stderr and "3530 us" in one.stderr
    four = _actuatord("--robot", str(_robot(tmp_path, [f"can{k // 2}" for k in range(8)])),
                      "--duration", "0.2")
    assert four.returncode == 0, four.stderr
    assert "8 joints" in four.stdout and "200 cycles" in four.stdout


def test_one_joints_drive_faulted_mid_run_stops_every_joint_and_exits_1():
    result = _actuatord("--robot", str(ARM), "--duration", "3",
                        "--inject-fault", "arm_left_5_joint:overcurrent_trip@1.5")
    assert result.returncode == 1, result.stderr
    assert "joint arm_left_5_joint" in result.stderr and "0x2310" in result.stderr
    stop_line = next(line for line in result.stdout.splitlines() if "quick stop:" in line)
    for joint in load_robot(ARM).joints:
        assert joint.name in stop_line
    assert "operation enabled" not in stop_line
    # the fault fires in the drive's 1500th cycle (1.5 s / 1 ms): the loop completed the 1499
    # before it, and stopped in that very cycle
    assert "1499 cycles" in result.stdout


def test_robot_options_are_checked_in_one_line():
    bad_fault = _actuatord("--robot", str(ARM), "--inject-fault", "no_such_joint:silent@1")
    assert bad_fault.returncode == 2 and "no_such_joint" in bad_fault.stderr
    assert bad_fault.stderr.count("\n") == 1
    with_model = _actuatord("--robot", str(ARM), "--model", "x.toml")
    assert with_model.returncode == 2 and "--model" in with_model.stderr


@pytest.mark.real_time
def test_sim_bus_serves_every_drive_of_a_robot_file_on_its_bus(tmp_path):
    """`sim-bus --robot`: each joint's drive on its bus at its node id, commissioned for its
    joint (rated current = the joint's current_max), answering a master's SDO."""
    import canopen

    from driver.canopen_transport import open_network
    from protocol import eds_path, objects

    port = free_port()
    buses = [f"udp_multicast:239.0.7.1:{port}", f"udp_multicast:239.0.7.2:{port}"]
    models = ROBOTS / "models"
    text = '[robot]\nname = "two_buses"\nperiod_us = 1000\n'
    for k, (bus, node_id, model) in enumerate([
            (buses[0], 1, "talos_wrist.toml"), (buses[0], 2, "talos_arm_shoulder.toml"),
            (buses[1], 1, "talos_wrist_pitch.toml")]):
        text += (f'\n[[joints]]\nname = "j{k}"\nbus = "{bus}"\nnode_id = {node_id}\n'
                 f'model = "{models / model}"\n')
    robot_file = tmp_path / "robot.toml"
    robot_file.write_text(text)
    proc = subprocess.Popen([sys.executable, "-m", "commands.sim_bus", "--robot",
                             str(robot_file)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    networks = []
    try:
        assert "3 drives of two_buses" in proc.stdout.readline()
        rated = {}
        for bus, node_ids in ((buses[0], (1, 2)), (buses[1], (1,))):
            network = open_network(bus)
            networks.append(network)
            for node_id in node_ids:
                node = canopen.RemoteNode(node_id, str(eds_path()))
                network.add_node(node)
                node.sdo.RESPONSE_TIMEOUT = 5.0
                rated[(bus, node_id)] = node.sdo[objects.RATED_CURRENT].raw
    finally:
        for network in networks:
            network.disconnect()
        proc.terminate()
        out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert rated == {(buses[0], 1): 3000, (buses[0], 2): 6000, (buses[1], 1): 3000}
    assert "stopped" in out


def test_recorder_records_one_joint_of_a_robot_file_over_its_own_range(tmp_path):
    """`recorder --robot --joint`: the wrist's drive (commissioned for its 3 A and its
    +-1.37 rad) runs the exciting trajectory fitted to its range, not the elbow's."""
    from recorder.reader import load_recording

    output = tmp_path / "wrist.mcap"
    result = subprocess.run(
        [sys.executable, "-m", "commands.recorder", "--exciting-trajectory", "--robot", str(ARM),
         "--joint", "arm_left_6_joint", "--sim", "--lockstep", "--steps", "1", "--no-progress",
         "-o", str(output)], capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr
    recording = load_recording(output)
    assert recording.metadata["joint"] == "arm_left_6_joint"
    # the elbow's defaults (-2.2..-0.15 rad) would leave the wrist's -1.37..1.37 rad
    assert min(recording.q) < -1.0 and max(recording.q) > 1.0
    # the measured current (sensor noise std 0.01 A, sim_bus.plant.SensorNoise) never goes
    # above the wrist's 3 A by more than the noise
    assert max(abs(c) for c in recording.current) <= 3.0 + 5 * SensorNoise.current
    refused = subprocess.run(
        [sys.executable, "-m", "commands.recorder", "--exciting-trajectory", "--robot", str(ARM),
         "--joint", "no_such_joint", "--sim", "-o", str(tmp_path / "x.mcap")],
        capture_output=True, text=True, timeout=300)
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1
    assert "--joint no_such_joint" in refused.stderr
