"""The 33-byte attachment of every rmw_zenoh sample.

Models ``attachment_helpers.cpp`` (``AttachmentData::serialize_to_zbytes`` and the
``AttachmentData(const zenoh::Bytes &)`` reader): zenoh-ext serialization of int64 sequence
number, int64 source timestamp (ns) and ``std::array<uint8_t, 16>`` gid, which zenoh-ext writes
as a sequence: a LEB128 length (one byte, 0x10) then the 16 bytes.
"""

from __future__ import annotations

import dataclasses
import struct

GID_SIZE = 16  # RMW_GID_STORAGE_SIZE
SIZE = 8 + 8 + 1 + GID_SIZE


@dataclasses.dataclass(frozen=True)
class Attachment:
    sequence_number: int
    source_timestamp: int
    gid: bytes


def pack(sequence_number: int, source_timestamp: int, gid: bytes) -> bytes:
    """``serialize_to_zbytes``."""
    if len(gid) != GID_SIZE:
        raise ValueError(f"a gid has {GID_SIZE} bytes, not {len(gid)}")
    return struct.pack("<qqB", sequence_number, source_timestamp, GID_SIZE) + gid


def unpack(data: bytes) -> Attachment | None:
    """The reader; None where zenoh-ext's deserializer fails (too short, a length other than
    16). Upstream does not catch that exception in its sample callback; the model drops the
    sample. Bytes after the gid are ignored, as the deserializer does not check for them."""
    if len(data) < SIZE or data[16] != GID_SIZE:
        return None
    sequence_number, source_timestamp = struct.unpack_from("<qq", data)
    return Attachment(sequence_number, source_timestamp, bytes(data[17:SIZE]))
