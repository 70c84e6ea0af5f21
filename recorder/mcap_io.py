"""MCAP recordings: the telemetry's protobuf schemas (the same bytes as on Zenoh), chunked
and indexed, flushed chunk by chunk so a killed writer loses at most the open chunk.

Chunks are 16 KiB of messages: at 1 kHz (State + Command, ~130 bytes a cycle) a chunk closes
and reaches the file about every 0.12 s. SIGINT/SIGTERM finish the file properly (nothing
lost). After every flushed chunk the file ends in a provisional DataEnd (with the data-section
CRC so far), an empty Footer and the magic, which the next chunk overwrites: a file whose writer
was SIGKILLed is still a valid MCAP without summary, which any MCAP reader opens and this
reader checks; `recorder repair` adds the summary and indexes. (A SIGKILL inside a chunk's
write can stop it between pages: that chunk is then cut short, the file refused naming the cut,
and `recorder repair` keeps every complete chunk.)

Times (ns since the Unix epoch): `publish_time` is the time the message speaks for, its `t`
(drive time) on the run's time base (`protocol.telemetry.TimeBase`: the wall clock at drive
time 0). An experiment's `log_time` is the same, so viewers and `mcap info` show the
experiment's true duration and 1 kHz rate even when lock-step ran it eight times faster than
real time; a Zenoh recording's `log_time` is the wall clock when each sample arrived.
"""

import time
import zlib
from collections.abc import Callable, Collection, Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np
from google.protobuf.message import DecodeError
from mcap.data_stream import RecordBuilder
from mcap.records import Channel, Chunk, DataEnd, Footer, Message, Metadata, Schema
from mcap.writer import CompressionType, Writer

from controller import messages
from controller.messages import Encoded, EncodedJointView, WireSubscriber, topic_of
from protocol import telemetry
from protocol.telemetry import TimeBase
from recorder.mcap_records import MAGIC, DamagedMcap, DataSection, chunk_records
from recorder.recording import Recording, RecordingError

CHUNK_SIZE = 16 * 1024
# Holds a whole closed chunk with its message indexes and the provisional end, so that all of
# it reaches the file in one write.
WRITE_BUFFER = 4 * CHUNK_SIZE
METADATA_NAME = "recording"
# what a Zenoh recording keeps: every telemetry topic of one joint or of a robot
SAMPLE_SCHEMAS = telemetry.TOPICS


class _DataFile:
    """The file under the mcap Writer, keeping the CRC of the data section written so far."""

    def __init__(self, path: Path):
        self.file = open(path, "wb", buffering=WRITE_BUFFER)
        self.crc = 0
        self.written = False  # since the recorder last cleared it: a chunk was closed

    def write(self, data: bytes) -> int:
        self.crc = zlib.crc32(data, self.crc)
        self.written = True
        return self.file.write(data)

    def tell(self) -> int:
        return self.file.tell()

    def flush(self) -> None:
        self.file.flush()


def _provisional_end(data_section_crc: int) -> bytes:
    builder = RecordBuilder()
    DataEnd(data_section_crc).write(builder)
    Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(builder)
    return builder.end() + MAGIC


class McapRecorder:
    """Writes telemetry messages to an MCAP file, one channel per topic. Opening raises OSError
    when the file cannot be created.

    A write that fails later (a full disk) does not raise into the control loop: the recorder
    keeps the error in `failure`, calls `on_failure` once (the command stops the run) and
    writes nothing more, so the file ends at its last flushed chunk, which `recorder repair`
    keeps."""

    def __init__(self, path: str | Path, metadata: dict[str, str] | None = None,
                 on_failure: Callable[[], None] = lambda: None):
        self.path = Path(path)
        self.failure: OSError | None = None
        self._on_failure = on_failure
        self._file = _DataFile(self.path)
        self._writer = Writer(self._file, chunk_size=CHUNK_SIZE,
                              compression=CompressionType.ZSTD, enable_data_crcs=True)
        self._writer.start(profile="", library="actuator-link recorder")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._counts: dict[int, int] = {}
        self._sequence = 0
        self.messages = 0
        self.time_base = TimeBase()
        self._time_bases: dict[str, TimeBase] = {}  # Zenoh samples: one per key prefix
        if metadata:
            self._writer.add_metadata(METADATA_NAME, {k: str(v) for k, v in metadata.items()})
        self._end_here()

    def channel(self, topic: str, message: str) -> int:
        """The channel id for `topic` carrying telemetry message `message` (e.g. 'State')."""
        if topic not in self._channels:
            if message not in self._schemas:
                self._schemas[message] = self._writer.register_schema(
                    telemetry.schema_name(message), "protobuf", telemetry.file_descriptor_set())
            self._channels[topic] = self._writer.register_channel(
                topic, "protobuf", self._schemas[message])
            self._counts[self._channels[topic]] = 0
        return self._channels[topic]

    def write(self, channel_id: int, data: bytes, *, publish_time_ns: int,
              log_time_ns: int | None = None) -> None:
        """One message. `publish_time_ns`: the time the message speaks for (drive time for an
        experiment); `log_time_ns`: when it was logged, the wall clock now unless given (a
        Zenoh recording passes the time the sample arrived)."""
        if self.failure is not None:
            return
        log_time = time.time_ns() if log_time_ns is None else log_time_ns
        self._file.written = False
        try:
            self._writer.add_message(channel_id, log_time, data, publish_time_ns,
                                     self._sequence)
            self._sequence += 1
            self.messages += 1
            self._counts[channel_id] += 1
            if self._file.written:  # a chunk was closed: get it to the file now
                self._end_here()
        except OSError as exc:
            self._failed(exc)

    def _failed(self, exc: OSError) -> None:
        self.failure = exc
        self._on_failure()

    def write_sample(self, key: str, data: bytes, arrival_ns: int) -> bool:
        """A telemetry sample received on Zenoh key `key`: logged at its arrival, published at
        its drive time on the time base of its prefix (each actuatord has its own drive clock,
        anchored at the first sample that arrives from it). A sample that does not parse is
        kept as it came, published at its arrival. False (nothing written) for a key whose
        last segment names no telemetry message."""
        prefix, _, topic = key.rpartition("/")
        message = SAMPLE_SCHEMAS.get(topic)
        if message is None:
            return False
        try:
            t = telemetry.decode(message, data).t
        except DecodeError:
            publish = arrival_ns
        else:
            if prefix not in self._time_bases:
                self._time_bases[prefix] = TimeBase(arrival_ns - int(round(t * 1e9)))
            publish = self._time_bases[prefix].stamp(t)
        self.write(self.channel(key, message), data, publish_time_ns=publish,
                   log_time_ns=arrival_ns)
        return True

    def messages_on(self, channel_id: int) -> int:
        """Messages written on a channel so far (those in the open chunk included)."""
        return self._counts[channel_id]

    def _end_here(self) -> None:
        """Write the provisional end after what the Writer wrote, flush, and step back over it
        so the Writer's next records replace it."""
        position = self._file.tell()
        self._file.file.write(_provisional_end(self._file.crc))
        self._file.flush()
        self._file.file.seek(position)

    def subscriber(self, topics: Collection[str], prefix: str) -> WireSubscriber:
        """A control loop's wire subscriber that writes the messages on `topics` (e.g.
        'state'), each on the channel named as its Zenoh key under `prefix` (so one Foxglove
        layout serves the live bridge and every recording), logged and published at its drive
        time on the run's time base. A joint's State and Command come as the bytes the loop
        encoded them to in one call (`EncodedJointView`): written as they are, no message is
        built or serialised for them (a 9.5 s exciting trajectory in lock-step took 1.0-1.1 s of
        wall time instead of 1.2-1.5)."""
        channels = {topic: self.channel(telemetry.key_expr(prefix, topic),
                                        telemetry.TOPICS[topic]) for topic in topics}
        # the channel of each part of a view, in the view's order (None: not recorded)
        view_channels = tuple(channels.get(messages.topic_of_kind(kind))
                              for kind in messages.VIEW_CLASSES)

        def write(message) -> None:  # a telemetry message, or one or three as bytes
            kind = type(message)
            if kind is EncodedJointView:
                stamp = self.time_base.stamp(message.t)
                for channel, data in zip(view_channels, message.parts(), strict=True):
                    if channel is not None:
                        self.write(channel, data, publish_time_ns=stamp, log_time_ns=stamp)
                return
            channel = channels.get(messages.topic_of_kind(message.kind) if kind is Encoded
                                   else topic_of(message))
            if channel is not None:
                stamp = self.time_base.stamp(message.t)
                self.write(channel, message.data if kind is Encoded
                           else message.SerializeToString(), publish_time_ns=stamp,
                           log_time_ns=stamp)

        return write

    def close(self) -> None:
        """Finish the file: the last chunk, the real DataEnd, summary, indexes, statistics.
        After a failed write (or if finishing fails) the file is left as it stands, ending at
        its last flushed chunk: `failure` says why."""
        try:
            if self.failure is None:
                self._writer.finish()
        except OSError as exc:
            self._failed(exc)
        try:
            self._file.file.close()
        except OSError as exc:  # what was buffered could not be flushed
            if self.failure is None:
                self._failed(exc)

    def discard(self) -> None:
        """Close and delete the file: for a run that failed before its first message, so no
        file is left that claims to be a recording."""
        try:
            self._file.file.close()
        except OSError:  # what was buffered could not be flushed: the file goes anyway
            pass
        self.path.unlink(missing_ok=True)


class McapMessage(NamedTuple):
    topic: str
    schema: str  # schema name, e.g. 'actuator.State'
    log_time: int  # ns
    data: bytes
    publish_time: int  # ns


def _contents(path: Path) -> Iterator[McapMessage | Metadata]:
    """Messages and metadata records in file order, every chunk checked (chunk_records)."""
    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, str]] = {}
    chunks = 0
    for offset, record in DataSection(path).records():
        if isinstance(record, Chunk):
            chunks += 1
            inner = chunk_records(f"{path}: chunk {chunks} at byte {offset}", record)
        else:
            inner = [record]
        for item in inner:
            if isinstance(item, Schema):
                schemas[item.id] = item.name
            elif isinstance(item, Channel):
                if item.schema_id != 0 and item.schema_id not in schemas:
                    raise RecordingError(f"{path}: channel {item.topic!r} refers to schema "
                                         f"{item.schema_id}, which no Schema record defines")
                channels[item.id] = (item.topic, schemas.get(item.schema_id, ""))
            elif isinstance(item, Message):
                if item.channel_id not in channels:
                    raise RecordingError(f"{path}: a message near byte {offset} is on channel "
                                         f"{item.channel_id}, which no Channel record defines")
                topic, schema = channels[item.channel_id]
                yield McapMessage(topic, schema, item.log_time, item.data, item.publish_time)
            elif isinstance(item, Metadata):
                yield item


def iter_mcap(path: Path) -> Iterator[McapMessage]:
    """Every message of a recording, in file order. A file whose writer was killed reads up to
    its last complete chunk; damage anywhere raises RecordingError."""
    for item in _contents(path):
        if isinstance(item, McapMessage):
            yield item


def recording_metadata(path: Path) -> dict[str, str]:
    """The `recording` metadata record's entries (empty when there is none)."""
    metadata: dict[str, str] = {}
    for item in _contents(path):
        if isinstance(item, Metadata) and item.name == METADATA_NAME:
            metadata.update(item.metadata)
    return metadata


def read_mcap(path: Path) -> Recording:
    """The contract's columns from the State messages of a recording, with its metadata."""
    t, q, current, torque = [], [], [], []
    metadata: dict[str, str] = {}
    state_name = telemetry.schema_name("State")
    state = telemetry.message_class("State")()
    try:
        for item in _contents(path):
            if isinstance(item, Metadata):
                if item.name == METADATA_NAME:
                    metadata.update(item.metadata)
                continue
            if item.schema != state_name:
                continue
            try:
                state.ParseFromString(item.data)
            except DecodeError:
                raise RecordingError(f"{path}: {state_name} message {len(t) + 1} on "
                                     f"{item.topic} does not parse") from None
            t.append(state.t)
            q.append(state.position)
            current.append(state.motor_current)
            torque.append(state.joint_torque)
    except DamagedMcap as exc:
        raise DamagedMcap(f"{exc}; `recorder repair {path} -o REPAIRED.mcap` keeps what is "
                          "sound") from None
    if not t:
        raise RecordingError(f"{path}: no {state_name} messages")
    return Recording(np.array(t), np.array(q), np.array(current), np.array(torque), metadata,
                     str(path))
