"""Checked reading of MCAP records, for files that may be damaged.

The mcap library parses the record bodies; the framing, the decompression and the CRC checks
are here because the library trusts what a file says: a flipped bit in a length field becomes a
read of 2**60 bytes (MemoryError, OverflowError) and chunk CRCs are not checked unless asked,
and then without saying where. Here every length is checked against the bytes really left before
anything is read, decompression grows piece by piece instead of allocating the size a chunk
claims, chunk CRCs and the data-section CRC are verified, and every way a damaged file fails is
one `RecordingError` line naming the file, the record and its byte offset.
"""

import io
import struct
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import lz4.frame
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile, McapError
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

from recorder.recording import RecordingError

MAGIC = b"\x89MCAP0\r\n"
RECORD_HEAD = struct.Struct("<BQ")  # opcode, body length
MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
PIECE = 1 << 20  # decompression output step, bytes
PRIVATE_OPCODES = 0x80  # 0x80-0xFF are user records (MCAP spec): skipped, everything else known

READERS: dict[int, Callable[[ReadDataStream, int], McapRecord]] = {
    Opcode.HEADER: lambda s, n: Header.read(s),
    Opcode.FOOTER: lambda s, n: Footer.read(s),
    Opcode.SCHEMA: lambda s, n: Schema.read(s),
    Opcode.CHANNEL: lambda s, n: Channel.read(s),
    Opcode.MESSAGE: Message.read,
    Opcode.CHUNK: lambda s, n: Chunk.read(s),
    Opcode.MESSAGE_INDEX: lambda s, n: MessageIndex.read(s),
    Opcode.CHUNK_INDEX: lambda s, n: ChunkIndex.read(s),
    Opcode.ATTACHMENT: lambda s, n: Attachment.read(s),
    Opcode.ATTACHMENT_INDEX: lambda s, n: AttachmentIndex.read(s),
    Opcode.STATISTICS: lambda s, n: Statistics.read(s),
    Opcode.METADATA: lambda s, n: Metadata.read(s),
    Opcode.METADATA_INDEX: lambda s, n: MetadataIndex.read(s),
    Opcode.SUMMARY_OFFSET: lambda s, n: SummaryOffset.read(s),
    Opcode.DATA_END: lambda s, n: DataEnd.read(s),
}
# Records that belong after DataEnd: meeting one in the data section means the framing slipped
# (a damaged length skipped DataEnd), never that the file is fine.
SUMMARY_ONLY = (Statistics, ChunkIndex, AttachmentIndex, MetadataIndex, SummaryOffset, Footer)
IN_CHUNK = (Schema, Channel, Message)
# What a record's parser may raise on bytes that are not what the format says.
PARSE_ERRORS = (McapError, struct.error, ValueError, OverflowError, MemoryError)


class DamagedMcap(RecordingError):
    """An MCAP file that is damaged (truncated, a CRC that does not match, a record that does
    not parse): unlike a file that is no MCAP at all, `recorder repair` can save its sound
    part."""


class _Body(io.BytesIO):
    """A record body whose reads are never silently short: a length field pointing past the
    end of its record is damage, not a shorter string."""

    def read(self, size: int | None = -1) -> bytes:
        data = super().read(size)
        if size is not None and size >= 0 and len(data) != size:
            raise EndOfFile()
        return data


def _parse(opcode: int, body: bytes, where: str) -> McapRecord | None:
    reader = READERS.get(opcode)
    if reader is None:
        if opcode >= PRIVATE_OPCODES:
            return None
        raise DamagedMcap(f"{where}: unknown record opcode 0x{opcode:02X}")
    if opcode == Opcode.MESSAGE and len(body) < MESSAGE_HEAD.size:
        raise DamagedMcap(f"{where}: Message record of {len(body)} bytes, shorter than "
                          "its fixed fields")
    try:
        return reader(ReadDataStream(_Body(body)), len(body))
    except PARSE_ERRORS as exc:
        name = Opcode(opcode).name.title().replace("_", "")
        raise DamagedMcap(f"{where}: malformed {name} record "
                          f"({str(exc) or type(exc).__name__})") from None


@dataclass
class DataSection:
    """Walks the data section of one MCAP file record by record.

    After `records()` is exhausted: `complete` says a DataEnd record ended the section (its CRC,
    when written, checked); otherwise the file ended at a record boundary with no DataEnd, as a
    writer killed between two chunks leaves it (before this project's writer ended each chunk
    with a provisional DataEnd). `summary` says a summary section follows DataEnd. `end` is the
    offset just past the last good record, so a caller that stops on an error knows how much
    was sound."""

    path: Path
    complete: bool = False
    summary: bool = False
    end: int = 0

    def records(self) -> Iterator[tuple[int, McapRecord]]:
        """(offset, record) for the records before DataEnd, chunks not opened."""
        try:
            fh = open(self.path, "rb")
        except OSError as exc:
            raise RecordingError(f"{self.path}: cannot read: {exc.strerror}") from None
        with fh:
            size = fh.seek(0, io.SEEK_END)
            fh.seek(0)
            if fh.read(len(MAGIC)) != MAGIC:
                raise RecordingError(f"{self.path}: not an MCAP file (no MCAP magic bytes)")
            crc = zlib.crc32(MAGIC)
            offset = self.end = len(MAGIC)
            while True:
                head = fh.read(RECORD_HEAD.size)
                if not head:
                    return
                if len(head) < RECORD_HEAD.size:
                    raise self._truncated(offset, size, None)
                opcode, length = RECORD_HEAD.unpack(head)
                if length > size - offset - RECORD_HEAD.size:
                    raise self._truncated(offset, size, length)
                body = fh.read(length)
                # Message indexes serve seeking readers; this one reads in order, and their
                # bytes still count in the data-section CRC.
                record = None if opcode == Opcode.MESSAGE_INDEX else _parse(
                    opcode, body, f"{self.path}: byte {offset}")
                if isinstance(record, DataEnd):
                    if record.data_section_crc not in (0, crc):
                        raise DamagedMcap(
                            f"{self.path}: data section CRC mismatch (stored "
                            f"0x{record.data_section_crc:08X}, computed 0x{crc:08X} over the "
                            f"{offset} bytes before DataEnd): damaged outside the chunks' "
                            "contents")
                    self.complete = True
                    self.end = offset + RECORD_HEAD.size + length
                    following = fh.read(1)
                    self.summary = bool(following) and following[0] != Opcode.FOOTER
                    return
                if offset == len(MAGIC) and not isinstance(record, Header):
                    raise DamagedMcap(f"{self.path}: the first record is not a Header")
                if isinstance(record, SUMMARY_ONLY) or (
                        isinstance(record, Header) and offset != len(MAGIC)):
                    raise DamagedMcap(f"{self.path}: byte {offset}: {type(record).__name__} "
                                      "record inside the data section: damaged record length "
                                      "before it")
                crc = zlib.crc32(body, zlib.crc32(head, crc))
                if record is not None:
                    yield offset, record
                offset = self.end = offset + RECORD_HEAD.size + length

    def _truncated(self, offset: int, size: int, length: int | None) -> DamagedMcap:
        claim = "its header is cut" if length is None else f"it claims {length} bytes"
        return DamagedMcap(f"{self.path}: truncated MCAP: the record at byte {offset} runs past "
                           f"the end ({claim}, {size - offset} bytes are left): file cut short "
                           "or a damaged length")


def chunk_records(where: str, chunk: Chunk) -> list[McapRecord]:
    """The Schema, Channel and Message records of a chunk, after checking that it decompresses
    to the size it states and matches its CRC. `where` names the chunk in errors, e.g.
    'run.mcap: chunk 3 at byte 18234'."""
    data = _decompress(where, chunk)
    if len(data) != chunk.uncompressed_size:
        raise DamagedMcap(f"{where}: decompresses to {len(data)} bytes, its header says "
                          f"{chunk.uncompressed_size}: damaged chunk")
    if chunk.uncompressed_crc != 0 and zlib.crc32(data) != chunk.uncompressed_crc:
        raise DamagedMcap(f"{where}: CRC mismatch (stored 0x{chunk.uncompressed_crc:08X}, "
                          f"computed 0x{zlib.crc32(data):08X}): damaged chunk")
    records: list[McapRecord] = []
    offset = 0
    while offset < len(data):
        if len(data) - offset < RECORD_HEAD.size:
            raise DamagedMcap(f"{where}: ends inside a record header at byte {offset} of "
                              "its contents")
        opcode, length = RECORD_HEAD.unpack_from(data, offset)
        start = offset + RECORD_HEAD.size
        if length > len(data) - start:
            raise DamagedMcap(f"{where}: record at byte {offset} of its contents claims "
                              f"{length} bytes, {len(data) - start} left")
        if opcode == Opcode.MESSAGE and length >= MESSAGE_HEAD.size:
            # the bulk of every file: parsed here, not by the general path, for speed
            channel_id, sequence, log_time, publish_time = MESSAGE_HEAD.unpack_from(data, start)
            records.append(Message(channel_id, log_time,
                                   data[start + MESSAGE_HEAD.size:start + length],
                                   publish_time, sequence))
            offset = start + length
            continue
        record = _parse(opcode, data[start:start + length],
                        f"{where}, byte {offset} of its contents")
        if record is not None:
            if not isinstance(record, IN_CHUNK):
                raise DamagedMcap(f"{where}: {type(record).__name__} record inside a chunk")
            records.append(record)
        offset = start + length
    return records


def _decompress(where: str, chunk: Chunk) -> bytes:
    """The chunk's records, grown a piece at a time so that a damaged size field costs no
    more memory than the data really decompresses to (at most one piece past the stated size)."""
    limit = chunk.uncompressed_size
    if chunk.compression == "":
        return chunk.data
    if chunk.compression not in ("zstd", "lz4"):
        raise DamagedMcap(f"{where}: unknown compression {chunk.compression!r}")
    pieces: list[bytes] = []
    total = 0
    try:
        if chunk.compression == "zstd":
            stream = zstandard.ZstdDecompressor().stream_reader(chunk.data)
            while total <= limit and (piece := stream.read(PIECE)):
                pieces.append(piece)
                total += len(piece)
        else:
            decompressor = lz4.frame.LZ4FrameDecompressor()
            piece = decompressor.decompress(chunk.data, max_length=PIECE)
            while True:
                pieces.append(piece)
                total += len(piece)
                if decompressor.eof or decompressor.needs_input or total > limit:
                    break
                piece = decompressor.decompress(b"", max_length=PIECE)
    except (zstandard.ZstdError, RuntimeError, ValueError, MemoryError) as exc:
        raise DamagedMcap(f"{where}: {chunk.compression} data does not decompress "
                          f"({str(exc) or type(exc).__name__})") from None
    return b"".join(pieces)
