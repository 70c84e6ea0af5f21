"""A recording as a ROS 2 bag: an MCAP file of profile `ros2` with `sensor_msgs/msg/JointState`
on `/joint_states` (CDR from rosbags, the message definition as ROS 2 writes it), which
`rosbags`, `ros2 bag play`, `mcap-ros2-support` and Foxglove read as ROS 2 data.

Native recordings stay protobuf (one message format for Zenoh, MCAP and Foxglove); this is
the export for the ROS 2 tools, in the spirit of `recorder export` to CSV.
"""

from dataclasses import dataclass
from pathlib import Path

from google.protobuf.message import DecodeError
from mcap.writer import CompressionType, Writer

from protocol import ros2, telemetry
from recorder.mcap_io import CHUNK_SIZE, METADATA_NAME, iter_mcap, recording_metadata
from recorder.mcap_records import DamagedMcap
from recorder.recording import RecordingError

# the telemetry messages that carry joint states: one joint's State, a robot's JointStates
SOURCES = {telemetry.schema_name("State"): "State",
           telemetry.schema_name("JointStates"): "JointStates"}


@dataclass
class Ros2Export:
    messages: int
    joints: list[str]

    def summary(self) -> str:
        return (f"{self.messages} sensor_msgs/msg/JointState on {ros2.JOINT_STATES_TOPIC} "
                f"({', '.join(self.joints)}, ROS 2 {ros2.DISTRIBUTION})")


def _joint_name(topic: str, metadata: dict[str, str]) -> str:
    """A single joint's name: the robot file's (`recorder --robot --joint`), else the last
    segment of the telemetry prefix (`actuators/elbow/state` -> `elbow`)."""
    if metadata.get("joint"):
        return metadata["joint"]
    prefix = topic.rpartition("/")[0]
    return prefix.rpartition("/")[2] or topic


def export_ros2(source: str | Path, output: str | Path) -> Ros2Export:
    """Write every State (one joint) and JointStates (robot) message of `source` as a
    JointState in a ROS 2 MCAP at `output`, stamped (header, log and publish time) at the
    message's publish time, the drive time on the run's time base. RecordingError (the file
    named) when the source is damaged or carries no joint states; OSError when the output
    cannot be written."""
    source, output = Path(source), Path(output)
    try:
        metadata = recording_metadata(source)
        messages = [m for m in iter_mcap(source) if m.schema in SOURCES]
    except DamagedMcap as exc:
        raise RecordingError(f"{exc}; `recorder repair {source} -o REPAIRED.mcap` keeps what "
                             "is sound") from None
    if not messages:
        raise RecordingError(f"{source}: no {' or '.join(SOURCES)} messages to export")
    joints: list[str] = []
    stamped: list[tuple[int, bytes]] = []  # everything converted before the output is opened
    for number, item in enumerate(messages, start=1):
        try:
            message = telemetry.decode(SOURCES[item.schema], item.data)
        except DecodeError:
            raise RecordingError(f"{source}: {item.schema} message {number} on {item.topic} "
                                 "does not parse") from None
        names, position, velocity, effort = ros2.joint_state_fields(
            message, _joint_name(item.topic, metadata))
        joints.extend(name for name in names if name not in joints)
        stamped.append((item.publish_time, ros2.joint_state_cdr(
            item.publish_time, names, position, velocity, effort)))
    with open(output, "wb") as stream:
        writer = Writer(stream, chunk_size=CHUNK_SIZE, compression=CompressionType.ZSTD)
        writer.start(profile="ros2", library="actuator-link recorder export --ros2")
        schema = writer.register_schema(ros2.JOINT_STATE, "ros2msg",
                                        ros2.message_definition(ros2.JOINT_STATE).encode())
        channel = writer.register_channel(ros2.JOINT_STATES_TOPIC, "cdr", schema)
        for sequence, (stamp, data) in enumerate(stamped):
            writer.add_message(channel, stamp, data, stamp, sequence)
        if metadata:
            writer.add_metadata(METADATA_NAME, metadata)
        writer.finish()
    return Ros2Export(len(messages), joints)
