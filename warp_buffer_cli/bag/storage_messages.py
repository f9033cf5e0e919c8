"""Read a bag's messages as rosbag2 does: topics taken from the storage files themselves.

rosbags' directory reader pairs a ``metadata.yaml`` topic with a storage file's channel only when
their QoS profiles are exactly equal, and silently skips a channel it cannot pair. Real rosbag2
bags differ there: Foxy wrote deadline 0 to ``metadata.yaml`` and its "infinite" (2147483647 s
4294967295 ns) to the file, which rosbag2 reads as the same (qos.cpp), and rosbag2's player takes
topics from the storage without comparing (player.cpp, mcap_storage.cpp). So a channel is paired
here by topic and type only. An MCAP file without chunks (rosbag2's ``fastwrite`` preset) is read
in log-time order from its record heads: rosbags refuses one whose messages are out of order.
"""

from __future__ import annotations

from collections.abc import Collection, Iterator
from typing import Any, BinaryIO

from .mcap_records import MESSAGE_HEAD, OP_CHUNK, OP_DATA_END, OP_MESSAGE, RECORD

__all__ = ["bag_messages", "top_level_messages"]


def bag_messages(reader: Any, connections: Collection[Any]) -> Iterator[tuple[Any, int, Any]]:
    """(connection, log time, raw CDR) of every message of ``connections`` (the open rosbags
    ``reader``'s), file by file, each file's in time order."""
    from rosbags.rosbag2.storage_mcap import McapReader

    storage = reader.storage
    storages = getattr(storage, "storages", None) or [storage]  # a directory's files, or one
    per_message = getattr(storage.metadata, "compression_mode", None) == "message"
    for file in storages:
        pairs = {c.id: paired for c in file.connections
                 if (paired := _pair(c, connections)) is not None}
        wanted = [c for c in file.connections if c.id in pairs]
        if not wanted:
            continue
        if isinstance(file, McapReader) and not file.chunks:
            items = _unchunked(file, {c.id for c in wanted})
        else:
            items = ((c.id, stamp, data) for c, stamp, data in file.messages(wanted))
        for channel, stamp, data in items:
            yield pairs[channel], stamp, _decompress(data) if per_message else data


def _pair(channel: Any, connections: Collection[Any]) -> Any:
    """The connection of ``connections`` a storage channel's messages are played as: itself
    (a single-file bag), else the one of its topic and type with equal QoS (two of a topic
    stay apart), else the first of its topic and type (QoS and hash not compared)."""
    if channel in connections:
        return channel
    same = [c for c in connections if c.topic == channel.topic and c.msgtype == channel.msgtype]
    return next((c for c in same if c.ext == channel.ext), same[0] if same else None)


def _decompress(data: Any) -> bytes:
    from rosbags.rosbag2.reader import zstd  # (rosbags' own choice of zstd module)

    return zstd.decompress(data)


def top_level_messages(file: BinaryIO, start: int, end: int) -> list[tuple[int, int, int]] | None:
    """(log time, offset, channel) of each message record outside chunks between ``start`` and
    ``end`` (an MCAP data section), in file order; None when the record heads do not tile it."""
    found = []
    at = start
    while at < end:
        file.seek(at)
        head = file.read(RECORD.size)
        if len(head) < RECORD.size:
            return None
        opcode, length = RECORD.unpack(head)
        if opcode == OP_DATA_END:
            break
        if at + RECORD.size + length > end:
            return None
        if opcode == OP_MESSAGE:
            body = file.read(MESSAGE_HEAD.size)
            if length < MESSAGE_HEAD.size + 8 or len(body) < MESSAGE_HEAD.size:
                return None
            channel, _, stamp = MESSAGE_HEAD.unpack(body)
            found.append((stamp, at, channel))
        elif opcode == OP_CHUNK:
            pass  # (its messages are counted from its index)
        at += RECORD.size + length
    return found


def _unchunked(storage: Any, channels: set[int]) -> Iterator[tuple[int, int, bytes]]:
    """(channel, log time, payload) of an unchunked MCAP file's messages, sorted by log time
    (file order among equal times), as an indexed reader yields them."""
    from .errors import BagDamagedError

    bio = storage.bio
    heads = top_level_messages(bio, storage.data_start, storage.data_end)
    if heads is None:
        raise BagDamagedError(f"the bag file {storage.path} is damaged: its records do not "
                              "tile its data section")
    for stamp, at, channel in sorted(h for h in heads if h[2] in channels):
        bio.seek(at)
        _, length = RECORD.unpack(bio.read(RECORD.size))
        bio.seek(at + RECORD.size + MESSAGE_HEAD.size + 8)  # past channel, sequence, 2 times
        data = bio.read(length - MESSAGE_HEAD.size - 8)
        yield channel, stamp, data
