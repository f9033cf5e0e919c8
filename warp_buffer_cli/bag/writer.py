"""rosbags' bag writer, with large messages written to MCAP in one write each, and what it
holds flushed each second.

A killed recorder loses what its storage did not hold yet: rosbags commits a sqlite3 bag once,
when it closes, and keeps an MCAP bag's small messages in memory until their chunk passes 1 MiB.
Here a written message waits at most :data:`COMMIT_S` seconds before it is in the file (the
sqlite3 transaction committed, the MCAP chunk closed and flushed): checked at each write and,
when no message comes, by the recorder's writer thread (:meth:`BagWriter.flush_if_due`).
``bag reindex`` recovers such a bag. While it writes, the writer holds the bag's directory
(:mod:`.lock`): ``bag reindex`` refuses a bag still being recorded.

rosbags' MCAP storage builds every message record in a ``BytesIO``, appends it to the pending
chunk's ``BytesIO``, and copies the chunk twice more when it closes it: for a 16 MiB frame that
is 65 ms of CPU here (six copies into fresh memory), against 3 ms for the one serialization.
A message of at least :data:`DIRECT_BYTES` is written here as a chunk of its own, header and
payload straight to the file (the payload from the caller's buffer, no copy in Python), with the
same records rosbags writes for a chunk (chunk, message index, and the chunk index it keeps for
the summary). Smaller messages, compression and everything else are rosbags' own.
"""

from __future__ import annotations

import os
import struct
import time
from collections import defaultdict
from io import BytesIO
from typing import Any

from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.storage_mcap import (
    Channel,
    McapWriter,
    PendingChunk,
    write_channel,
    write_string,
)
from rosbags.rosbag2.storage_sqlite3 import Sqlite3Writer

from .lock import lock_directory
from .mcap_end import chunk_index

__all__ = ["COMMIT_S", "DIRECT_BYTES", "BagWriter"]

#: Longest time a written message waits before it is in the bag's file.
COMMIT_S = 1.0

#: Messages from this size on get a chunk of their own (rosbags closes a chunk past 1 MiB).
DIRECT_BYTES = 1 << 20

_OP_MESSAGE, _OP_CHUNK, _OP_MESSAGE_INDEX = 0x05, 0x06, 0x07
_MESSAGE_HEADER = struct.Struct("<BQHIQQ")  # op, record length, channel, sequence, log, publish
_CHUNK_HEADER = struct.Struct("<BQQQQIIQ")  # op, length, start, end, size, crc, "", compressed


class _Flushing:
    """A storage writer whose written messages reach its file at most COMMIT_S seconds apart."""

    _flushed = 0.0
    _pending = False

    def flush_if_due(self) -> None:
        """Put what was written into the file if it waited COMMIT_S seconds or more."""
        now = time.monotonic()
        if self._pending and now - self._flushed >= COMMIT_S:
            self._flush()
            self._pending = False
            self._flushed = now

    def _flush(self) -> None:
        raise NotImplementedError


class _DirectMcapWriter(_Flushing, McapWriter):
    """rosbags' MCAP storage writer; large uncompressed messages go to the file directly."""

    def write(self, connection: Any, timestamp: int, data: bytes | memoryview) -> None:
        self._pending = True
        self._write(connection, timestamp, data)
        self.flush_if_due()

    def add_connection(self, connection: Any, offered_qos_profiles: str) -> None:
        """rosbags' channel, whose metadata also carries the type's hash under
        ``topic_type_hash``, as rosbag2's MCAP storage writes and reads it (rosbags keeps it only
        in ``metadata.yaml``, which a killed recorder never writes)."""
        metadata = BytesIO()
        for key, value in (("offered_qos_profiles", offered_qos_profiles),
                           ("topic_type_hash", connection.digest)):
            if value:
                write_string(metadata, key)
                write_string(metadata, value)
        self.channels.append(Channel(connection.id, connection.msgtype, connection.topic,
                                     connection.ext.serialization_format, metadata.getvalue()))
        self.channel_stats[connection.id] = 0
        write_channel(self.chunk.bio, self.channels[-1], self.schemas)

    def _flush(self) -> None:
        if self.chunk.bio.tell():
            self.close_chunk()
        self.bio.flush()  # (out of Python's buffer: a killed process loses nothing of it)

    def _write(self, connection: Any, timestamp: int, data: bytes | memoryview) -> None:
        if len(data) < DIRECT_BYTES or self.compression:
            super().write(connection, timestamp, data)
            return
        if self.chunk.bio.tell():  # what is pending (schemas, channels, small messages) first
            self.close_chunk()
        self.message_start_time = min(timestamp, self.message_start_time)
        self.message_end_time = max(timestamp, self.message_end_time)
        self.channel_stats[connection.id] += 1
        record_length = _MESSAGE_HEADER.size - 9 + len(data)
        content_length = 9 + record_length
        chunk_start = self.bio.tell()
        self.bio.write(_CHUNK_HEADER.pack(
            _OP_CHUNK, 8 + 8 + 8 + 4 + 4 + 8 + content_length, timestamp, timestamp,
            content_length, 0, 0, content_length))
        self.bio.write(_MESSAGE_HEADER.pack(_OP_MESSAGE, record_length, connection.id, 0,
                                            timestamp, timestamp))
        self.bio.write(data)
        chunk_end = self.bio.tell()
        index_start = chunk_end
        self.bio.write(struct.pack("<BQHIQQ", _OP_MESSAGE_INDEX, 2 + 4 + 16, connection.id, 16,
                                   timestamp, 0))  # one message, at offset 0 of the content
        self.chunks.append(chunk_index(timestamp, timestamp, chunk_start,
                                       chunk_end - chunk_start, {connection.id: index_start},
                                       self.bio.tell() - chunk_end, "", content_length,
                                       content_length))
        self.chunk = PendingChunk(2**63 - 1, 0, BytesIO(), defaultdict(list))


class _CommittingSqlite3Writer(_Flushing, Sqlite3Writer):
    """rosbags' sqlite3 storage writer, committed at most COMMIT_S seconds apart."""

    def write(self, connection: Any, timestamp: int, data: bytes | memoryview) -> None:
        super().write(connection, timestamp, data)
        self._pending = True
        self.flush_if_due()

    def _flush(self) -> None:
        self.conn.commit()


class BagWriter(Writer):
    """rosbags' ``Writer`` whose MCAP storage writes large messages in one write each, whose
    storage puts what it was given in the file each second, and which holds the bag's
    directory while it writes."""

    STORAGE_PLUGINS = {**Writer.STORAGE_PLUGINS, StoragePlugin.MCAP: _DirectMcapWriter,
                       StoragePlugin.SQLITE3: _CommittingSqlite3Writer}

    _lock_fd: int | None = None

    def flush_if_due(self) -> None:
        """Put what was written into the file if it waited :data:`COMMIT_S` or more (a writer
        that gets no message for a while calls this: nothing waits on a next write)."""
        if self.storage is not None:
            self.storage.flush_if_due()

    def open(self) -> None:
        super().open()  # (creates the directory)
        try:
            self._lock_fd = lock_directory(self.path)
        except BaseException:
            super().abort()
            raise

    def close(self) -> None:
        try:
            super().close()
        finally:
            self._unlock()

    def abort(self) -> None:
        try:
            super().abort()
        finally:
            self._unlock()

    def _unlock(self) -> None:
        fd, self._lock_fd = self._lock_fd, None
        if fd is not None:
            os.close(fd)
