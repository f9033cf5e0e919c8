"""End an MCAP file whose writer never closed it, as that writer would have closed it.

A recorder killed mid-recording leaves the records it wrote, the last one perhaps cut short,
and neither the summary (schemas, channels, chunk indexes, statistics) nor the footer a reader
looks for. :func:`end_mcap` reads the data section once, cuts the file after its last complete
chunk, writes the message indexes of that chunk if the crash took them (they follow the chunk
in the file, a write later), and appends what rosbags' writer appends when it closes: the
``rosbag2`` metadata record, the data-end record, the summary and the footer. The result is an
indexed file every reader opens as if its recorder had closed it: indexed readers also merge
its messages in time order, which a scan of an unindexed file requires of the file itself
(messages of two topics received on two threads reach the writer out of order by microseconds).
"""

from __future__ import annotations

import os
import struct
from collections import defaultdict
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import Any, BinaryIO

from .errors import BagReadError
from .mcap_records import (MESSAGE_HEAD, OP_CHANNEL, OP_CHUNK, OP_DATA_END, OP_FOOTER,
                           OP_HEADER, OP_MESSAGE, OP_MESSAGE_INDEX, OP_SCHEMA, RECORD)

__all__ = ["MCAP_MAGIC", "McapContents", "channel_metadata", "chunk_index", "end_mcap",
           "is_closed"]

MCAP_MAGIC = b"\x89MCAP0\r\n"
_U16, _U32, _U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")
_CHUNK_TIMES = struct.Struct("<QQQI")  # start, end, uncompressed size, uncompressed CRC
_FOOTER_SIZE = RECORD.size + 20


@dataclass
class _Chunk:
    start: int
    length: int  # the whole record's
    start_time: int
    end_time: int
    compression: str
    compressed_size: int
    uncompressed_size: int
    messages: dict[int, list[tuple[int, int]]]  # channel -> (log time, offset in the content)
    index_offsets: dict[int, int] = field(default_factory=dict)  # channel -> its index record
    index_end: int = 0

    @property
    def end(self) -> int:
        return self.start + self.length


@dataclass
class McapContents:
    """What an MCAP file's data section holds (rosbags' ``Schema`` and ``Channel`` tuples)."""

    schemas: dict[int, Any] = field(default_factory=dict)
    channels: dict[int, Any] = field(default_factory=dict)
    chunks: list[_Chunk] = field(default_factory=list)

    def message_counts(self) -> dict[int, int]:
        """Messages per channel, every channel listed."""
        counts = dict.fromkeys(self.channels, 0)
        for chunk in self.chunks:
            for channel, entries in chunk.messages.items():
                counts[channel] = counts.get(channel, 0) + len(entries)
        return counts

    def time_span(self) -> tuple[int, int]:
        """First and last log time (rosbags' empty values when there is no message)."""
        stamps = [t for c in self.chunks for e in c.messages.values() for t, _ in e]
        return (min(stamps), max(stamps)) if stamps else (2**63 - 1, 0)


def channel_metadata(raw: bytes) -> dict[str, str]:
    """A channel record's metadata map (``offered_qos_profiles``, ``topic_type_hash``)."""
    from rosbags.rosbag2.storage_mcap import read_string

    body, found = BytesIO(raw), {}
    while body.tell() < len(raw):
        key = read_string(body)
        found[key] = read_string(body)
    return found


def is_closed(file: BinaryIO, size: int) -> bool:
    """Whether the file ends with a footer and the magic (closed by its writer)."""
    if size < 2 * len(MCAP_MAGIC) + _FOOTER_SIZE:
        return False
    file.seek(size - len(MCAP_MAGIC))
    return file.read() == MCAP_MAGIC


def end_mcap(path: Path, metadata_text: Any) -> tuple[int, McapContents]:
    """End the unclosed MCAP file ``path`` (see the module); ``metadata_text(contents)`` gives
    the text of its ``rosbag2`` metadata record (the bag's ``metadata.yaml``). Returns the bytes
    cut off and what the file holds. :class:`BagReadError` when it is no MCAP file."""
    with path.open("r+b") as file:
        size = os.fstat(file.fileno()).st_size
        if not MCAP_MAGIC.startswith(file.read(len(MCAP_MAGIC))[:size]):
            raise BagReadError(f"{path} is not an MCAP file")
        contents, end = _scan(file, size, path)
        if end < len(MCAP_MAGIC):  # killed before its header reached the file: nothing recorded
            file.truncate(0)
            file.seek(0)
            file.write(MCAP_MAGIC + _header())
            _close(file, contents, metadata_text(contents))
            return size, contents
        named = {schema.name for schema in contents.schemas.values()}
        if any(channel.schema not in named for channel in contents.channels.values()):
            raise BagReadError(f"{path} has a channel without its schema: not reindexed")
        last = contents.chunks[-1] if contents.chunks else None
        lost_indexes = last is not None and set(last.index_offsets) != set(last.messages)
        if lost_indexes:
            end = last.end  # its index records, some cut off: written again, whole
        file.truncate(end)
        file.seek(end)
        if lost_indexes:
            _write_message_indexes(file, last)
        _close(file, contents, metadata_text(contents))
    return size - end, contents


def _scan(file: BinaryIO, size: int, path: Path) -> tuple[McapContents, int]:
    """The data section's contents, and where its last complete record ends."""
    from rosbags.rosbag2.errors import ReaderError
    from rosbags.rosbag2.storage_mcap import Channel, Schema

    contents = McapContents()
    if size < len(MCAP_MAGIC):
        return contents, 0
    end = len(MCAP_MAGIC)
    first = True
    while end + RECORD.size <= size:
        file.seek(end)
        opcode, length = RECORD.unpack(file.read(RECORD.size))
        if first and opcode != OP_HEADER:
            raise BagReadError(f"{path} does not start with an MCAP header record")
        if opcode == 0 and not _zeros_to_end(file, end, size):
            raise BagReadError(f"{path}: zeroed bytes at byte {end} before records that follow "
                               "(nothing was changed)")
        if opcode in (0, OP_DATA_END, OP_FOOTER) or length > size - end - RECORD.size:
            break  # what the writer's end began, a record the crash cut short, zeroed pages
        first = False
        if opcode in (OP_CHUNK, OP_MESSAGE_INDEX, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE):
            body = file.read(length)
            last = end + RECORD.size + length == size
            try:
                if opcode == OP_CHUNK:
                    contents.chunks.append(_read_chunk(body, end, contents, Schema, Channel))
                elif opcode == OP_MESSAGE_INDEX:
                    if contents.chunks:
                        chunk = contents.chunks[-1]
                        chunk.index_offsets[_U16.unpack_from(body)[0]] = end
                        chunk.index_end = end + RECORD.size + length
                elif opcode == OP_MESSAGE:
                    raise BagReadError(f"{path} holds a message outside a chunk, which this "
                                       "recorder never writes: not reindexed")
                else:
                    _read_definition(opcode, BytesIO(body), contents, Schema, Channel)
            except (struct.error, UnicodeDecodeError, ValueError, ReaderError) as exc:
                if last:
                    break  # the crash's damage: cut off like a record it cut short
                raise BagReadError(f"{path}: a damaged record at byte {end} (nothing was "
                                   f"changed): {exc}") from None
        end += RECORD.size + length
    return contents, 0 if first else end  # (0: not even the header is whole)


def _zeros_to_end(file: BinaryIO, start: int, size: int) -> bool:
    """Whether everything from ``start`` on is zero (pages a power cut left unwritten)."""
    file.seek(start)
    while block := file.read(min(1 << 20, size - file.tell())):
        if block.count(0) != len(block):
            return False
    return True


def _header() -> bytes:
    """The header record rosbags' writer begins a file with."""
    from importlib.metadata import version

    body = b"".join(_U32.pack(len(text)) + text for text in (
        b"ros2", f"rosbags-{version('rosbags')}".encode()))
    return RECORD.pack(OP_HEADER, len(body)) + body


def _read_chunk(body: bytes, start: int, contents: McapContents, schema: Any,
                channel: Any) -> _Chunk:
    from rosbags.rosbag2.storage_mcap import decompress

    start_time, end_time, uncompressed_size, crc = _CHUNK_TIMES.unpack_from(body)
    at = _CHUNK_TIMES.size
    compression, at = _string(body, at)
    (compressed_size,) = _U64.unpack_from(body, at)
    at += 8
    data = decompress(body[at:at + compressed_size], compression, uncompressed_size, crc)
    messages: dict[int, list[tuple[int, int]]] = defaultdict(list)
    offset = 0
    # Without a checksum (rosbags writes none) damage shows only in the structure: the records
    # a writer puts in a chunk, tiling it exactly, each message inside the chunk's time span.
    while offset < len(data):
        opcode, length = RECORD.unpack_from(data, offset)
        record = offset + RECORD.size
        if record + length > len(data):
            raise ValueError(f"a record runs past the end of the chunk at byte {start}")
        if opcode == OP_MESSAGE and length >= MESSAGE_HEAD.size + 8:
            channel_id, _, log_time = MESSAGE_HEAD.unpack_from(data, record)
            if channel_id not in contents.channels or not start_time <= log_time <= end_time:
                raise ValueError(f"a message the chunk at byte {start} cannot hold")
            messages[channel_id].append((log_time, offset))
        elif opcode in (OP_SCHEMA, OP_CHANNEL):
            _read_definition(opcode, BytesIO(data[record:record + length]), contents, schema,
                             channel)
        else:
            raise ValueError(f"a record of kind {opcode:#x} inside the chunk at byte {start}")
        offset = record + length
    return _Chunk(start, RECORD.size + len(body), start_time, end_time, compression,
                  compressed_size, uncompressed_size, dict(messages))


def _read_definition(opcode: int, body: BytesIO, contents: McapContents, schema: Any,
                     channel: Any) -> None:
    """A schema or channel record, as rosbags' reader keeps it."""
    from rosbags.rosbag2.storage_mcap import read_bytes, read_string

    (key,) = _U16.unpack(body.read(2))
    if opcode == OP_SCHEMA:
        contents.schemas[key] = schema(key, read_string(body), read_string(body),
                                       read_string(body))
        return
    (schema_id,) = _U16.unpack(body.read(2))
    known = contents.schemas.get(schema_id)
    contents.channels[key] = channel(key, known.name if known else "__schemaless__",
                                     read_string(body), read_string(body), read_bytes(body))


def _string(data: bytes, at: int) -> tuple[str, int]:
    (length,) = _U32.unpack_from(data, at)
    at += 4
    return data[at:at + length].decode(), at + length


def _write_message_indexes(file: BinaryIO, chunk: _Chunk) -> None:
    """The message index records of ``chunk``, one per channel, after it (as rosbags writes)."""
    chunk.index_offsets = {}
    for channel, entries in chunk.messages.items():
        chunk.index_offsets[channel] = file.tell()
        body = _U16.pack(channel) + _U32.pack(16 * len(entries)) + b"".join(
            struct.pack("<QQ", stamp, offset) for stamp, offset in entries)
        file.write(RECORD.pack(OP_MESSAGE_INDEX, len(body)) + body)
    chunk.index_end = file.tell()


def _close(file: BinaryIO, contents: McapContents, metadata: str) -> None:
    """Append what rosbags' MCAP writer appends when it closes (its own ``close``, given the
    schemas, channels, chunk indexes and statistics read from the file)."""
    from rosbags.rosbag2.storage_mcap import McapWriter, PendingChunk

    writer = McapWriter.__new__(McapWriter)  # (its __init__ creates a new file)
    writer.bio = file
    writer.schemas = list(contents.schemas.values())
    writer.channels = list(contents.channels.values())
    writer.chunks = [_chunk_index(chunk) for chunk in contents.chunks]
    writer.chunk = PendingChunk(2**63 - 1, 0, BytesIO(), defaultdict(list))
    writer.channel_stats = contents.message_counts()
    writer.message_start_time, writer.message_end_time = contents.time_span()
    writer.close(0, metadata)  # (closes the file: the caller's ``with`` then does nothing)


def _chunk_index(chunk: _Chunk) -> BytesIO:
    return chunk_index(chunk.start_time, chunk.end_time, chunk.start, chunk.length,
                       chunk.index_offsets, max(chunk.index_end - chunk.end, 0),
                       chunk.compression, chunk.compressed_size, chunk.uncompressed_size)


def chunk_index(start_time: int, end_time: int, start: int, length: int,
                index_offsets: dict[int, int], index_length: int, compression: str,
                compressed_size: int, uncompressed_size: int) -> BytesIO:
    """A chunk index record's body, as rosbags' writer keeps it until it writes the summary."""
    record = BytesIO()
    offsets = sorted(index_offsets.items())
    record.write(struct.pack("<QQQQI", start_time, end_time, start, length, 10 * len(offsets)))
    for channel, offset in offsets:
        record.write(struct.pack("<HQ", channel, offset))
    record.write(_U64.pack(index_length))
    record.write(_U32.pack(len(compression)) + compression.encode())
    record.write(struct.pack("<QQ", compressed_size, uncompressed_size))
    return record
