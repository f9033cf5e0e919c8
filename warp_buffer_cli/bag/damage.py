"""Find damage inside a closed MCAP file cheaply: its records checked against its own index.

rosbags writes no checksums, and its reader trusts a chunk's records as they come: a changed
byte inside a closed bag surfaces mid-playback as whatever exception the parse hits
(``OverflowError``, ``struct.error``, ``ReaderError``), or as messages silently skipped (a
message whose channel or time was changed). :func:`check_mcap` compares what the summary
promises with the records it points at, reading record heads only (never a payload): each
chunk's head against its chunk index, each message index record, every record head of an
uncompressed chunk (they must tile it, each message where its index says, with its channel and
time), the message records outside chunks (a file written without chunks), and the message
counts against the statistics. A changed payload byte is not seen (no
checksum to compare); a compressed chunk is checked by its head and indexes only. A checksum a
writer did put in a chunk is verified by rosbags' reader when the chunk is read.
"""

from __future__ import annotations

import struct
from collections import Counter
from typing import Any, BinaryIO

from .errors import BagDamagedError
from .mcap_records import (MESSAGE_HEAD, OP_CHANNEL, OP_CHUNK, OP_MESSAGE, OP_MESSAGE_INDEX,
                           OP_SCHEMA, RECORD)
from .storage_messages import top_level_messages

__all__ = ["check_mcap"]

_CHUNK_HEAD = struct.Struct("<QQQII")  # start, end, uncompressed size, CRC, compression length
_INDEX_HEAD = struct.Struct("<HI")  # channel, bytes of (log time, offset) entries
_ENTRY = struct.Struct("<QQ")


def check_mcap(storage: Any) -> None:
    """Raise :class:`BagDamagedError` (naming the file, the byte and what is wrong) when the
    records of ``storage``, an open rosbags ``McapReader`` of a closed file, disagree with its
    summary (see the module for what is and is not seen)."""
    counts: Counter[int] = Counter()
    with storage.path.open("rb") as file:
        for chunk in storage.chunks:
            try:
                problem = _chunk_problem(file, chunk, set(storage.channels), counts)
            except (struct.error, ValueError) as exc:  # a head cut short, a length past the file
                problem = f"a record cannot be read: {exc}"
            if problem:
                raise BagDamagedError(f"the bag file {storage.path} is damaged at byte "
                                      f"{chunk.chunk_start_offset}: {problem}")
        statistics = storage.statistics
        expected = {k: v for k, v in (statistics.channel_message_counts if statistics else {})
                    .items() if v}
        if statistics is not None and dict(counts) != expected:
            # Messages outside chunks (rosbag2's fastwrite preset writes no chunk at all): their
            # record heads, walked once, count them (only when the chunks alone fall short).
            loose = top_level_messages(file, storage.data_start, storage.data_end)
            if loose is None or any(c not in storage.channels for _, _, c in loose):
                raise BagDamagedError(f"the bag file {storage.path} is damaged: the records "
                                      "outside its chunks do not tile its data section")
            counts.update(channel for _, _, channel in loose)
    if statistics is not None and dict(counts) != expected:
        raise BagDamagedError(f"the bag file {storage.path} is damaged: its message indexes "
                              f"count {sum(counts.values())} messages, its statistics "
                              f"{sum(expected.values())}")


def _read(file: BinaryIO, at: int, size: int) -> bytes:
    file.seek(at)
    data = file.read(size)
    if len(data) != size:
        raise ValueError(f"{size} bytes at byte {at} run past the end of the file")
    return data


def _chunk_problem(file: BinaryIO, chunk: Any, channels: set[int],
                   counts: Counter[int]) -> str | None:
    """What is wrong with one chunk and its message indexes (None: nothing seen)."""
    start = chunk.chunk_start_offset
    opcode, length = RECORD.unpack(_read(file, start, RECORD.size))
    if opcode != OP_CHUNK or RECORD.size + length != chunk.chunk_length:
        return "no chunk record where the index puts one"
    head = _read(file, start + RECORD.size, _CHUNK_HEAD.size)
    first, last, uncompressed, _, name_length = _CHUNK_HEAD.unpack(head)
    compression = chunk.compression.encode()
    at = start + RECORD.size + _CHUNK_HEAD.size
    if ((first, last, uncompressed, name_length) != (chunk.message_start_time,
                                                     chunk.message_end_time,
                                                     chunk.uncompressed_size, len(compression))
            or _read(file, at, len(compression)) != compression
            or struct.unpack("<Q", _read(file, at + len(compression), 8))[0]
            != chunk.compressed_size):
        return "the chunk's head disagrees with its index"
    indexed = _message_indexes(file, chunk)
    if indexed is None:
        return "its message index records are damaged"
    for channel, entries in indexed.items():
        counts[channel] += len(entries)
    if compression:
        return None  # (its records would need the whole chunk decompressed)
    data_start = at + len(compression) + 8
    found = _message_heads(file, data_start, uncompressed)
    if found is None:
        return "its records do not tile it (a record's head was changed)"
    wanted = {(channel, stamp, offset) for channel, entries in indexed.items()
              for stamp, offset in entries}
    if found != wanted:
        return "its messages disagree with its message index (a channel, time or kind changed)"
    if any(channel not in channels or not first <= stamp <= last for channel, stamp, _ in found):
        return "a message of an unknown channel or outside the chunk's time span"
    return None


def _message_indexes(file: BinaryIO, chunk: Any) -> dict[int, list[tuple[int, int]]] | None:
    """Each channel's (log time, offset) entries from the chunk's message index records."""
    found: dict[int, list[tuple[int, int]]] = {}
    for channel, at in chunk.message_index_offsets.items():
        opcode, length = RECORD.unpack(_read(file, at, RECORD.size))
        body = _read(file, at + RECORD.size, length) if opcode == OP_MESSAGE_INDEX else b""
        if len(body) < _INDEX_HEAD.size:
            return None
        channel_id, size = _INDEX_HEAD.unpack_from(body)
        if channel_id != channel or size != length - _INDEX_HEAD.size or size % _ENTRY.size:
            return None
        found[channel] = list(_ENTRY.iter_unpack(body[_INDEX_HEAD.size:]))
    return found


def _message_heads(file: BinaryIO, data_start: int,
                   size: int) -> set[tuple[int, int, int]] | None:
    """(channel, log time, offset) of every message record of an uncompressed chunk's
    content, as a reader walks it; None when the records do not end exactly at its end."""
    found = set()
    offset = 0
    while offset < size:
        if offset + RECORD.size > size:
            return None
        opcode, length = RECORD.unpack(_read(file, data_start + offset, RECORD.size))
        end = offset + RECORD.size + length
        if end > size or opcode not in (OP_SCHEMA, OP_CHANNEL, OP_MESSAGE):
            return None
        if opcode == OP_MESSAGE:
            if length < MESSAGE_HEAD.size + 8:
                return None
            channel, _, stamp = MESSAGE_HEAD.unpack(
                _read(file, data_start + offset + RECORD.size, MESSAGE_HEAD.size))
            found.add((channel, stamp, offset))
        offset = end
    return found
