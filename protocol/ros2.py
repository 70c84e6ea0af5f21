"""ROS 2 on the wire without ROS installed: `sensor_msgs/msg/JointState` as rmw_zenoh puts it
on Zenoh, and as a ROS 2 MCAP recording carries it.

Target: ROS 2 Jazzy (the current LTS; Kilted and Rolling use the same JointState, so the same
type hash). The CDR bytes, the type hash (RIHS01) and the message definition all come from
`rosbags`' type store for that distribution; nothing here encodes CDR by hand.

rmw_zenoh (its `docs/design.md`, and the `zenoh-ros2-sdk` that follows it) names things so:
    data          <domain>/<topic without leading />/<dds type>/<type hash>
    node token    @ros2_lv/<domain>/<zid>/<node id>/<node id>/NN/<enclave>/<namespace>/<node>
    publisher     @ros2_lv/<domain>/<zid>/<node id>/<entity id>/MP/<enclave>/<namespace>/<node>/
                  <topic>/<dds type>/<type hash>/<qos>
with `/` in names mangled to `%` (an empty namespace or enclave is `%`), and every sample
carries an attachment: int64 sequence number, int64 source timestamp (ns), the publisher's
16-byte GID as a length-prefixed buffer (Zenoh's own serialisation).
"""

from collections.abc import Sequence
from functools import cache

import numpy as np
from rosbags.typesys import Stores, get_typestore

DISTRIBUTION = "jazzy"
JOINT_STATE = "sensor_msgs/msg/JointState"
JOINT_STATES_TOPIC = "/joint_states"
NODE_NAME = "actuatord"
# rmw_zenoh's encoding of the default QoS (reliable, volatile, keep last 10): fields equal to
# the default are left empty, the history depth is always written
DEFAULT_QOS = "::,10:,:,:,,"
GID_SIZE = 16  # RMW_GID_STORAGE_SIZE


@cache
def typestore():
    """The message types of the targeted distribution (rosbags)."""
    return get_typestore(Stores.ROS2_JAZZY)


def dds_type_name(msgtype: str) -> str:
    """'sensor_msgs/msg/JointState' -> 'sensor_msgs::msg::dds_::JointState_' (as DDS and
    rmw_zenoh name it)."""
    package, kind, name = msgtype.split("/")
    return f"{package}::{kind}::dds_::{name}_"


@cache
def type_hash(msgtype: str) -> str:
    """The RIHS01 type hash ROS 2 (Iron and later) puts in key expressions and bags."""
    return typestore().hash_rihs01(msgtype)


@cache
def message_definition(msgtype: str) -> str:
    """The concatenated .msg definition (with its dependencies) a ROS 2 MCAP schema holds."""
    return typestore().generate_msgdef(msgtype, ros_version=2)[0]


def mangle(name: str) -> str:
    """A name inside a liveliness token: `/` becomes `%`, an empty name or `/` is `%`."""
    return "%" if name in ("", "/") else name.replace("/", "%")


def topic_key(domain: int, topic: str, msgtype: str) -> str:
    """The key expression rmw_zenoh publishes a topic's samples on."""
    return f"{domain}/{topic.lstrip('/')}/{dds_type_name(msgtype)}/{type_hash(msgtype)}"


def node_token(domain: int, zid: str, node_id: int, node: str = NODE_NAME,
               namespace: str = "/") -> str:
    """The liveliness token by which `ros2 node list` sees a node."""
    return (f"@ros2_lv/{domain}/{zid}/{node_id}/{node_id}/NN/%/{mangle(namespace)}/"
            f"{mangle(node)}")


def publisher_token(domain: int, zid: str, node_id: int, entity_id: int, topic: str,
                    msgtype: str, node: str = NODE_NAME, namespace: str = "/",
                    qos: str = DEFAULT_QOS) -> str:
    """The liveliness token by which `ros2 topic list/info/echo` find a publisher."""
    return (f"@ros2_lv/{domain}/{zid}/{node_id}/{entity_id}/MP/%/{mangle(namespace)}/"
            f"{mangle(node)}/{mangle(topic)}/{dds_type_name(msgtype)}/{type_hash(msgtype)}/"
            f"{qos}")


def joint_state(stamp_ns: int, names: Sequence[str], position: Sequence[float],
                velocity: Sequence[float], effort: Sequence[float]):
    """A rosbags `sensor_msgs/msg/JointState` (effort: joint torque, N.m)."""
    store = typestore()
    time_type = store.types["builtin_interfaces/msg/Time"]
    header_type = store.types["std_msgs/msg/Header"]
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return store.types[JOINT_STATE](
        header=header_type(stamp=time_type(sec=sec, nanosec=nanosec), frame_id=""),
        name=list(names), position=np.asarray(position, dtype=np.float64),
        velocity=np.asarray(velocity, dtype=np.float64),
        effort=np.asarray(effort, dtype=np.float64))


def joint_state_cdr(stamp_ns: int, names: Sequence[str], position: Sequence[float],
                    velocity: Sequence[float], effort: Sequence[float]) -> bytes:
    """The CDR bytes of a JointState (little endian, with its encapsulation header), what
    rmw_zenoh sends and a ROS 2 bag stores."""
    message = joint_state(stamp_ns, names, position, velocity, effort)
    return bytes(typestore().serialize_cdr(message, JOINT_STATE))


def joint_state_fields(message, joint_name: str):
    """(names, position, velocity, effort) of a telemetry `State` (one joint, called
    `joint_name`) or `JointStates` (its own names); None for any other message."""
    kind = type(message).__name__
    if kind == "State":
        return ([joint_name], [message.position], [message.velocity], [message.joint_torque])
    if kind == "JointStates":
        return (list(message.name), list(message.position), list(message.velocity),
                list(message.effort))
    return None
