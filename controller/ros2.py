"""`/joint_states` for ROS 2 nodes on rmw_zenoh, beside the native telemetry: the same Zenoh
session, the key expression, liveliness tokens, attachment and CDR payload rmw_zenoh uses
(`protocol.ros2`), so `ros2 topic echo /joint_states` on a machine whose rmw_zenoh router this
session reaches shows the robot. Fed from the telemetry publisher's thread, never the loop's."""

import time
import uuid

import zenoh
from zenoh.ext import Int64, z_serialize

from protocol import ros2
from protocol.telemetry import TimeBase


def attachment(sequence: int, timestamp_ns: int, gid: bytes) -> bytes:
    """rmw_zenoh's per-sample attachment, serialised with Zenoh's own serialiser: int64
    sequence number, int64 source timestamp (ns), the GID as a length-prefixed buffer."""
    return z_serialize((Int64(sequence), Int64(timestamp_ns), gid)).to_bytes()


class JointStatePublisher:
    """Publishes `sensor_msgs/msg/JointState` on `/joint_states` of a ROS domain for each
    telemetry `State` (one joint, named `joint_name`) or `JointStates` (every joint) it is
    given; other messages are ignored. Header stamps are on the run's time base: the wall
    clock at the first message, advanced by drive time (in lock-step the stamps keep the
    drive's 1 kHz however fast the run goes)."""

    def __init__(self, session: zenoh.Session, domain: int, joint_name: str,
                 topic: str = ros2.JOINT_STATES_TOPIC):
        self.joint_name = joint_name
        self.sent = 0
        self._gid = uuid.uuid4().bytes  # unique per publisher, as rmw_zenoh's GIDs are
        self._time_base = TimeBase()
        zid = str(session.info.zid())
        node_id, entity_id = 0, 1  # this session's only node and its only publisher
        self._publisher = session.declare_publisher(
            ros2.topic_key(domain, topic, ros2.JOINT_STATE),
            encoding=zenoh.Encoding.APPLICATION_CDR,
            congestion_control=zenoh.CongestionControl.DROP)
        liveliness = session.liveliness()
        self._tokens = [
            liveliness.declare_token(ros2.node_token(domain, zid, node_id)),
            liveliness.declare_token(ros2.publisher_token(domain, zid, node_id, entity_id,
                                                          topic, ros2.JOINT_STATE))]

    def publish(self, message) -> None:
        fields = ros2.joint_state_fields(message, self.joint_name)
        if fields is None:
            return
        data = ros2.joint_state_cdr(self._time_base.stamp(message.t), *fields)
        self.sent += 1
        self._publisher.put(data, attachment=attachment(self.sent, time.time_ns(), self._gid))

    def close(self) -> None:
        for entity in [self._publisher, *self._tokens]:
            entity.undeclare()
