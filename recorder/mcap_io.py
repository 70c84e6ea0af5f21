"""MCAP recordings: the telemetry's protobuf schemas (the same bytes as on Zenoh), chunked
and indexed, flushed chunk by chunk so a killed writer loses at most the open chunk.

Chunks are 16 KiB of messages: at 1 kHz (State + Command, ~130 bytes a cycle) a chunk closes
and reaches the file about every 0.12 s. SIGINT/SIGTERM finish the file properly (nothing
lost); after SIGKILL the file has no summary, and `read_mcap` still reads every complete chunk.
"""

import struct
from collections.abc import Collection
from pathlib import Path

import numpy as np
from mcap.exceptions import McapError
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from controller.messages import Subscriber, topic_of
from protocol import telemetry
from recorder.recording import Recording, RecordingError

CHUNK_SIZE = 16 * 1024
METADATA_NAME = "recording"


class McapRecorder:
    """Writes telemetry messages to an MCAP file, one channel per topic."""

    def __init__(self, path: str | Path, metadata: dict[str, str] | None = None):
        self.path = Path(path)
        self._file = open(self.path, "wb")
        self._writer = Writer(self._file, chunk_size=CHUNK_SIZE,
                              compression=CompressionType.ZSTD)
        self._writer.start(profile="", library="actuator-link recorder")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._sequence = 0
        self.messages = 0
        if metadata:
            self._writer.add_metadata(METADATA_NAME, {k: str(v) for k, v in metadata.items()})
        self._file.flush()

    def channel(self, topic: str, message: str) -> int:
        """The channel id for `topic` carrying telemetry message `message` (e.g. 'State')."""
        if topic not in self._channels:
            if message not in self._schemas:
                self._schemas[message] = self._writer.register_schema(
                    telemetry.schema_name(message), "protobuf", telemetry.file_descriptor_set())
            self._channels[topic] = self._writer.register_channel(
                topic, "protobuf", self._schemas[message])
        return self._channels[topic]

    def write(self, channel_id: int, log_time_ns: int, data: bytes) -> None:
        before = self._file.tell()
        self._writer.add_message(channel_id, log_time_ns, data, log_time_ns, self._sequence)
        self._sequence += 1
        self.messages += 1
        if self._file.tell() != before:  # a chunk was closed: get it to the file now
            self._file.flush()

    def subscriber(self, topics: Collection[str]) -> Subscriber:
        """A control-loop subscriber that writes the messages on `topics` (e.g. 'state'), each
        on its topic's channel, logged at its drive time."""
        channels = {topic: self.channel(topic, telemetry.TOPICS[topic]) for topic in topics}

        def write(message) -> None:
            channel = channels.get(topic_of(message))
            if channel is not None:
                log_time = int(round(message.t * 1e9))
                self.write(channel, log_time, message.SerializeToString())

        return write

    def close(self) -> None:
        self._writer.finish()
        self._file.close()


def iter_mcap(path: Path):
    """(topic, schema name, log_time_ns, data) for every message, plus metadata records as
    ('metadata', name, 0, dict). A file whose writer was killed (no summary, ending at a record
    boundary) reads up to its last complete chunk; a file cut inside a record is refused."""
    size = path.stat().st_size
    with open(path, "rb") as fh:
        schemas: dict[int, str] = {}
        channels: dict[int, tuple[str, str]] = {}
        good = 0
        try:
            for record in StreamReader(fh, skip_magic=False).records:
                good = fh.tell()
                if isinstance(record, Schema):
                    schemas[record.id] = record.name
                elif isinstance(record, Channel):
                    channels[record.id] = (record.topic, schemas.get(record.schema_id, ""))
                elif isinstance(record, Message):
                    topic, schema = channels[record.channel_id]
                    yield topic, schema, record.log_time, record.data
                elif isinstance(record, Metadata):
                    yield "metadata", record.name, 0, dict(record.metadata)
        except (McapError, struct.error, EOFError, ValueError) as exc:
            if good < 8:
                raise RecordingError(f"{path}: not an MCAP file ({exc or type(exc).__name__})") \
                    from None
            if fh.tell() < size or good != size:
                raise RecordingError(f"{path}: truncated MCAP: ends inside a record (last "
                                     f"complete record at byte {good} of {size})") from None


def read_mcap(path: Path) -> Recording:
    """The contract's columns from the State messages of a recording."""
    t, q, current, torque = [], [], [], []
    metadata: dict[str, str] = {}
    state_class = telemetry.message_class("State")
    for topic, schema, _, data in iter_mcap(path):
        if topic == "metadata":
            if schema == METADATA_NAME:
                metadata.update(data)
            continue
        if schema != telemetry.schema_name("State"):
            continue
        state = state_class()
        try:
            state.ParseFromString(data)
        except Exception:
            raise RecordingError(f"{path}: a {schema} message on {topic} does not parse") \
                from None
        t.append(state.t)
        q.append(state.position)
        current.append(state.motor_current)
        torque.append(state.joint_torque)
    if not t:
        raise RecordingError(f"{path}: no {telemetry.schema_name('State')} messages")
    return Recording(np.array(t), np.array(q), np.array(current), np.array(torque), metadata,
                     str(path))
