"""`actuatord --ros2`: its `/joint_states` seen by an implementation of rmw_zenoh's side the
project did not write (`zenoh-ros2-sdk`: its own type hash, key expression, liveliness parsing
and CDR decoding by rosbags), as `ros2 topic info -v` and `ros2 topic echo` would see it."""

import os
import subprocess
import sys
import threading
import time

import pytest

from tests.conftest import free_port

sdk = pytest.importorskip("zenoh_ros2_sdk")
from zenoh_ros2_sdk import discovery, message_registry  # noqa: E402
from zenoh_ros2_sdk.attachment import Attachment  # noqa: E402
from zenoh_ros2_sdk.qos import QosProfile  # noqa: E402
from zenoh_ros2_sdk.session import ZenohSession  # noqa: E402

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
