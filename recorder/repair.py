"""Repair a recording: rewrite what is sound in a killed, truncated or damaged MCAP file as a
complete one (summary, chunk and message indexes, statistics, CRCs) that every MCAP tool
opens, as the official `mcap recover` does, so users need no other tool.

Everything this project's reader would read is kept: the header, metadata, attachments and
every message of every chunk that decompresses and matches its CRC. A damaged chunk is
dropped and named; reading stops at a record whose framing is broken (a truncated tail or a
damaged length), since nothing after it can be located. The source is never modified; the
destination appears only when complete (written beside it, then renamed).
"""

import os
from dataclasses import dataclass, field
from pathlib import Path

from mcap.records import Attachment, Channel, Chunk, Header, Message, Metadata, Schema
from mcap.writer import CompressionType, Writer

from protocol.input_files import RECORDING_MAX, InputFileError, check_input_file, present
from recorder.mcap_records import DataSection, chunk_records
from recorder.recording import RecordingError


@dataclass
class RepairReport:
    """What was kept and what was lost, for the one line `recorder repair` prints."""

    messages: int = 0
    chunks: int = 0  # chunks read whole
    dropped_chunks: list[str] = field(default_factory=list)  # one line each: where and why
    orphan_messages: int = 0  # on channels whose definition was in a dropped chunk
    ending: str = ""  # how reading the source ended

    def summary(self) -> str:
        text = f"{self.messages} messages kept from {self.chunks} chunks"
        if self.dropped_chunks:
            text += f"; {len(self.dropped_chunks)} damaged chunks dropped (first: " \
                    f"{self.dropped_chunks[0]})"
        if self.orphan_messages:
            text += f"; {self.orphan_messages} messages on channels defined only in a dropped " \
                    "chunk dropped"
        return f"{text}; source {self.ending}"


class _Copy:
    """Re-registers schemas and channels in the new file under the ids its Writer gives."""

    def __init__(self, writer: Writer, report: RepairReport):
        self.writer, self.report = writer, report
        self.schemas: dict[int, int] = {0: 0}
        self.channels: dict[int, int] = {}

    def add(self, record) -> None:
        if isinstance(record, Schema):
            if record.id not in self.schemas:
                self.schemas[record.id] = self.writer.register_schema(
                    record.name, record.encoding, record.data)
        elif isinstance(record, Channel):
            if record.id not in self.channels and record.schema_id in self.schemas:
                self.channels[record.id] = self.writer.register_channel(
                    record.topic, record.message_encoding, self.schemas[record.schema_id],
                    record.metadata)
        elif isinstance(record, Message):
            if record.channel_id not in self.channels:
                self.report.orphan_messages += 1
                return
            self.writer.add_message(self.channels[record.channel_id], record.log_time,
                                    record.data, record.publish_time, record.sequence)
            self.report.messages += 1
        elif isinstance(record, Metadata):
            self.writer.add_metadata(record.name, record.metadata)
        elif isinstance(record, Attachment):
            self.writer.add_attachment(record.create_time, record.log_time, record.name,
                                       record.media_type, record.data)


def repair_recording(source: str | Path, destination: str | Path) -> RepairReport:
    """Write the sound part of `source` to `destination` as a complete MCAP file.

    Raises RecordingError when `source` is not an MCAP file or holds not even its header,
    or when `destination` is `source`; OSError when `destination` cannot be written."""
    source, destination = Path(source), Path(destination)
    try:
        if present(source):  # stat'ed before opening: a FIFO or a device is never read
            check_input_file(source, "an MCAP recording", RECORDING_MAX)
    except InputFileError as exc:
        raise RecordingError(str(exc)) from None
    if destination.exists() and source.exists() and os.path.samefile(source, destination):
        raise RecordingError(f"{destination}: is the file being repaired; write the repaired "
                             "copy to another file")
    section = DataSection(source)
    records = section.records()
    try:
        _, header = next(records)
    except StopIteration:
        raise RecordingError(f"{source}: holds no MCAP header; nothing to repair") from None
    assert isinstance(header, Header)  # DataSection refuses a file that starts otherwise
    report = RepairReport()
    temporary = destination.with_name(f".{destination.name}.{os.getpid()}.repairing")
    try:
        with open(temporary, "xb") as out:
            writer = Writer(out, compression=CompressionType.ZSTD, enable_data_crcs=True)
            writer.start(header.profile, header.library)
            copy = _Copy(writer, report)
            chunks = 0
            try:
                for offset, record in records:
                    if not isinstance(record, Chunk):
                        copy.add(record)
                        continue
                    chunks += 1
                    try:
                        inner = chunk_records(f"chunk {chunks} at byte {offset}", record)
                    except RecordingError as exc:
                        report.dropped_chunks.append(str(exc))
                        continue
                    report.chunks += 1
                    for item in inner:
                        copy.add(item)
                report.ending = ("was complete" if section.summary else
                                 "had no summary (its writer did not finish: killed?)")
            except RecordingError as exc:
                report.ending = f"stopped at byte {section.end}: {exc}"
            writer.finish()
        os.replace(temporary, destination)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
    return report
