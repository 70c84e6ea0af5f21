"""`actuatord --ros2`: its `/joint_states` seen by an implementation of rmw_zenoh's side the
project did not write (`zenoh-ros2-sdk`: its own type hash, key expression, liveliness parsing
and CDR decoding by rosbags), as `ros2 topic info -v` and `ros2 topic echo` would see it."""

import os
import subprocess
import sys
import threading
import time

import pytest
import zenoh_ros2_sdk as sdk
from zenoh_ros2_sdk import discovery, message_registry
from zenoh_ros2_sdk.attachment import Attachment
from zenoh_ros2_sdk.qos import QosProfile
from zenoh_ros2_sdk.session import ZenohSession

from tests.conftest import free_port

DOMAIN = 7
# the ROS 2 message definitions (comments left out: they do not enter the type hash), where
# the SDK would otherwise clone them from ROS's repositories
MESSAGES = {
    "sensor_msgs/msg/JointState": "std_msgs/Header header\nstring[] name\nfloat64[] position\n"
                                  "float64[] velocity\nfloat64[] effort\n",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec\n",
}


@pytest.fixture
def ros2_messages(tmp_path, monkeypatch):
    for name, text in MESSAGES.items():
        path = tmp_path.joinpath(*name.split("/")).with_suffix(".msg")
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    monkeypatch.setattr(message_registry, "_registry",
                        message_registry.MessageRegistry(str(tmp_path)))


@pytest.mark.subprocess
def test_joint_states_reach_a_ros2_subscriber_on_rmw_zenoh(ros2_messages):
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "commands.actuatord", "--sim", "--lockstep", "--duration", "30",
         "--prefix", "test/elbow", "--listen", f"tcp/127.0.0.1:{port}",
         "--no-multicast-scouting", "--ros2"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "ROS_DOMAIN_ID": str(DOMAIN)})
    received, attachments = [], []
    got = threading.Event()

    def on_message(message) -> None:
        received.append(message)
        if len(received) >= 50:
            got.set()

    subscriber = None
    try:
        assert "enabled" in proc.stdout.readline()
        # the SDK computes the type hash from the definitions and builds rmw_zenoh's key
        subscriber = sdk.ROS2Subscriber("/joint_states", "sensor_msgs/msg/JointState",
                                        on_message, domain_id=DOMAIN, router_port=port)
        session = ZenohSession.get_instance("127.0.0.1", port)
        raw = session.session.declare_subscriber(
            subscriber.keyexpr, lambda sample: attachments.append(sample.attachment.to_bytes()))
        assert got.wait(20), f"no JointState on {subscriber.keyexpr}"
        info = discovery.get_topic_info("/joint_states", domain_id=DOMAIN, router_port=port,
                                        timeout=2.0, verbose=True)
        raw.undeclare()
    finally:
        if subscriber is not None:
            subscriber.close()
        if ZenohSession._instance is not None:
            ZenohSession._instance.close()
        proc.terminate()
        proc.communicate(timeout=30)

    assert subscriber.keyexpr.startswith(
        f"{DOMAIN}/joint_states/sensor_msgs::msg::dds_::JointState_/RIHS01_")
    # `ros2 topic info -v /joint_states`: one publisher, node actuatord, the default QoS
    assert info is not None and info.publisher_count == 1
    assert info.topic_types == ["sensor_msgs/msg/JointState"]
    endpoint = info.publishers[0]
    assert endpoint.node_name.lstrip("/") == "actuatord"
    assert endpoint.type_hash == subscriber.type_hash
    assert QosProfile.decode(endpoint.qos) == QosProfile()
    # `ros2 topic echo /joint_states`: the joint, its state, stamps 1 ms apart in drive time
    for message in received:
        assert list(message.name) == ["elbow"]
        assert len(message.position) == len(message.velocity) == len(message.effort) == 1
        assert -3.2 < message.position[0] < 3.2
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in received]
    steps = {b - a for a, b in zip(stamps, stamps[1:], strict=False)}
    assert steps == {1_000_000}, sorted(steps)[:5]
    assert abs(stamps[0] - time.time_ns()) < 60e9  # on the wall clock's epoch, not 1970
    # the attachment rmw_zenoh reads: sequence numbers counting up, one GID of 16 bytes
    decoded = [Attachment.from_bytes(a) for a in attachments]
    assert decoded and {len(a.gid) for a in decoded} == {16}
    assert len({a.gid for a in decoded}) == 1
    sequence = [a.sequence_id for a in decoded]
    assert sequence == list(range(sequence[0], sequence[0] + len(sequence)))


@pytest.mark.parametrize("path", ["ros2 publisher", "telemetry publisher"])
def test_a_robots_joint_states_carry_every_joint_by_name(ros2_messages, path):
    """`actuatord --robot --ros2`: one JointState per cycle with every joint of the robot file,
    as the SDK's subscriber decodes it (here from the publishers alone, in this process):
    given the message (the ROS 2 publisher), or as actuatord's telemetry publisher gets it
    from a robot's loop, the message's wire bytes (`messages.Encoded`)."""
    import json

    import zenoh

    from controller import messages
    from controller.ros2 import JointStatePublisher
    from controller.telemetry import TelemetryPublisher
    from protocol import telemetry

    port = free_port()
    config = zenoh.Config()
    config.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    config.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(config)
    if path == "ros2 publisher":
        publisher = JointStatePublisher(session, DOMAIN, "unused for a robot")
        publish, sent = publisher.publish, lambda: publisher.sent
    else:
        publisher = TelemetryPublisher(session, "test/arm", telemetry.topics(3),
                                       ros2_domain=DOMAIN)
        publish, sent = publisher.publish, None
    received = []
    subscriber = None
    try:
        subscriber = sdk.ROS2Subscriber("/joint_states", "sensor_msgs/msg/JointState",
                                        received.append, domain_id=DOMAIN, router_port=port)
        names = ["arm_left_1_joint", "arm_left_2_joint", "arm_left_3_joint"]
        deadline = time.monotonic() + 10
        k = 0
        while len(received) < 5 and time.monotonic() < deadline:
            k += 1
            message = messages.JointStates(t=k * 1e-3, name=names, position=[0.1, 0.2, 0.3],
                                           velocity=[1.0, 2.0, 3.0],
                                           effort=[-1.0, -2.0, -3.0])
            publish(message if sent is not None else
                    messages.Encoded(messages.JointStates, message.t,
                                     message.SerializeToString()))
            publish(messages.Fault(t=k * 1e-3))  # not a joint state
            time.sleep(0.01)
    finally:
        if subscriber is not None:
            subscriber.close()
        if ZenohSession._instance is not None:
            ZenohSession._instance.close()
        publisher.close()
        session.close()
    assert len(received) >= 5
    if sent is not None:
        assert sent() == k  # the faults were not published
    message = received[-1]
    assert list(message.name) == names
    assert message.position.tolist() == [0.1, 0.2, 0.3]
    assert message.effort.tolist() == [-1.0, -2.0, -3.0]
