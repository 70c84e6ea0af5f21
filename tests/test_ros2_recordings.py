"""`recorder export --ros2`: a recording as a ROS 2 bag that readers the project did not write
(`rosbags`, `mcap-ros2-support`) open as sensor_msgs/msg/JointState: the messages, the names,
the count and the stamps."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from protocol import telemetry
from recorder.mcap_io import McapRecorder
from recorder.recording import RecordingError
from recorder.ros2_export import export_ros2

CYCLES = 300


def single_joint_recording(path: Path) -> list:
    """An experiment's recording as the recorder writes it (State and Command at 1 kHz)."""
    writer = McapRecorder(path, {"payload_mass": 5.0, "experiment": "synthetic"})
    record = writer.subscriber(("state", "command"), telemetry.DEFAULT_PREFIX)
    states = []
    for k in range(1, CYCLES + 1):
        t = k * 1e-3
        state = telemetry.message_class("State")(
            t=t, position=-1.2 + np.sin(t), velocity=np.cos(t), motor_current=1.5,
            joint_torque=-9 + t, drive_state="OPERATION_ENABLED")
        record(state)
        record(telemetry.message_class("Command")(t=t, current=1.5))
        states.append(state)
    writer.close()
    return states


def robot_recording(path: Path, names: list[str]) -> None:
    """A robot's telemetry as `recorder --zenoh` keeps it: JointStates under robots/NAME."""
    writer = McapRecorder(path, {"source": "zenoh robots/arm/**"})
    joint_states = telemetry.message_class("JointStates")
    for k in range(1, CYCLES + 1):
        message = joint_states(t=k * 1e-3, name=names, position=[0.1 * k, -0.1 * k],
                               velocity=[1.0, -1.0], effort=[2.0, -2.0])
        writer.write_sample("robots/arm/joints", message.SerializeToString(),
                            1_700_000_000_000_000_000 + 3 * k)  # arrivals bunched together
    writer.close()


def read_bag(path: Path) -> list[tuple]:
    with AnyReader([path]) as reader:
        assert [(c.topic, c.msgtype) for c in reader.connections] == [
            ("/joint_states", "sensor_msgs/msg/JointState")]
        assert reader.connections[0].msgcount == CYCLES
        return [(timestamp, reader.deserialize(raw, connection.msgtype))
                for connection, timestamp, raw in reader.messages()]


@pytest.mark.subprocess
def test_an_experiment_exports_as_a_ros2_bag_rosbags_reads(tmp_path):
    source, bag = tmp_path / "run.mcap", tmp_path / "run_ros2.mcap"
    states = single_joint_recording(source)
    proc = subprocess.run([sys.executable, "-m", "commands.recorder", "export", "--ros2",
                           str(source), "-o", str(bag)], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert f"{CYCLES} sensor_msgs/msg/JointState on /joint_states (elbow" in proc.stdout
    messages = read_bag(bag)
    assert len(messages) == CYCLES
    for (timestamp, message), state in zip(messages, states, strict=True):
        assert list(message.name) == ["elbow"]
        assert message.position.tolist() == [state.position]
        assert message.velocity.tolist() == [state.velocity]
        assert message.effort.tolist() == [state.joint_torque]  # N.m, the torque sensor
        stamp = message.header.stamp.sec * 10**9 + message.header.stamp.nanosec
        assert stamp == timestamp
    stamps = [timestamp for timestamp, _ in messages]
    assert set(np.diff(stamps)) == {1_000_000}  # the drive's 1 kHz

    # a second, independent reader: mcap-ros2-support decodes the same messages
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(bag, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        decoded = [message for *_, message in reader.iter_decoded_messages()]
    assert len(decoded) == CYCLES
    assert decoded[-1].position == [states[-1].position]


def test_a_robot_recording_exports_every_joint_on_its_drive_time(tmp_path):
    source, bag = tmp_path / "robot.mcap", tmp_path / "robot_ros2.mcap"
    robot_recording(source, ["arm_left_1_joint", "arm_left_2_joint"])
    exported = export_ros2(source, bag)
    assert exported.messages == CYCLES
    assert exported.joints == ["arm_left_1_joint", "arm_left_2_joint"]
    messages = read_bag(bag)
    assert {tuple(m.name) for _, m in messages} == {("arm_left_1_joint", "arm_left_2_joint")}
    assert messages[-1][1].position.tolist() == pytest.approx([0.1 * CYCLES, -0.1 * CYCLES])
    # stamped at drive time (1 ms apart), not at the bunched arrivals
    assert set(np.diff([timestamp for timestamp, _ in messages])) == {1_000_000}


def test_a_recording_without_joint_states_is_refused_naming_it(tmp_path):
    source = tmp_path / "faults.mcap"
    writer = McapRecorder(source)
    writer.write(writer.channel("actuators/elbow/fault", "Fault"),
                 telemetry.message_class("Fault")(t=1.0, cause="x").SerializeToString(),
                 publish_time_ns=10**9)
    writer.close()
    with pytest.raises(RecordingError, match=f"{source}: no actuator.State or "
                                             "actuator.JointStates messages"):
        export_ros2(source, tmp_path / "out.mcap")
    assert not (tmp_path / "out.mcap").exists()


@pytest.mark.subprocess
def test_a_csv_is_refused_for_the_ros2_export_in_one_line(tmp_path):
    source = tmp_path / "run.csv"
    source.write_text("t,q,current,joint_torque\n0.001,0,0,0\n0.002,0,0,0\n")
    proc = subprocess.run([sys.executable, "-m", "commands.recorder", "export", "--ros2",
                           str(source), "-o", str(tmp_path / "out.mcap")],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        f"recorder: error: --ros2: {source} is CSV; the ROS 2 export reads MCAP recordings "
        "(CSV carries no velocity)"]
