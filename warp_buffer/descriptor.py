"""The descriptor of an export, in its one form: the ``WarpBufferDescriptor`` message.

The message (``warp_buffer_backend_msgs/msg/WarpBufferDescriptor``, shipped by the backend
package) has fixed-size fields only, so its CDR encoding is one fixed struct, :data:`LAYOUT`
(little endian, the natural alignment needs no padding at an 8-byte boundary): inside a message
the CDR codec packs and unpacks it with one precompiled struct call (the same run at the
alignment phase where the field falls), sized once, and a transport that carries descriptors
outside CDR can :func:`pack` and :func:`unpack` it directly, through the native core
(:mod:`warp_buffer._core`, which checks each field's width). Tests check that the bytes are
those of the generic codec's field-by-field path.
"""

from __future__ import annotations

import hashlib
import operator
import struct
from typing import Any

from rosidl_buffer.messages import get_message_type
from rosidl_buffer.native import load_extension

from .errors import (
    DescriptorError,
    ExportBoundsError,
    ExportError,
    RecycledBufferError,
    StaleBufferError,
)

#: The package's native core (the private extension module ``warp_buffer._core``), loaded here
#: once with its error classes set: the package's modules (arena, attach, ipc, lease, loan)
#: import it from here (``from .descriptor import _core``), never load it themselves.
_core = load_extension("warp_buffer._core")
_core.set_error_classes(DescriptorError, ExportBoundsError, StaleBufferError, ExportError,
                        RecycledBufferError)

__all__ = [
    "DESCRIPTOR_TYPE",
    "VERSION",
    "KIND_HOST",
    "KIND_CUDA_IPC",
    "KIND_CUDA_STAGING",
    "KIND_CUDA_VMM",
    "CUDA_ZERO_COPY",
    "FIELDS",
    "LAYOUT",
    "descriptor_type",
    "fields_of",
    "make",
    "pack",
    "unpack",
    "handle_words",
    "handle_bytes",
    "uuid_word",
]

DESCRIPTOR_TYPE = "warp_buffer_backend_msgs/msg/WarpBufferDescriptor"
VERSION = 2
KIND_HOST = 0
KIND_CUDA_IPC = 1
KIND_CUDA_STAGING = 2
KIND_CUDA_VMM = 3
KINDS = (KIND_HOST, KIND_CUDA_IPC, KIND_CUDA_STAGING, KIND_CUDA_VMM)
#: Kinds whose bytes stay in the publisher's device memory (the arena range is a lock only).
CUDA_ZERO_COPY = (KIND_CUDA_IPC, KIND_CUDA_VMM)
HANDLE_WORDS = 8

FIELDS = ("version", "kind", "peer_slot", "owner_pid", "session", "offset", "capacity", "size",
          "generation", "sequence", "device_uuid",
          *(f"mem_handle_{i}" for i in range(HANDLE_WORDS)),
          *(f"event_handle_{i}" for i in range(HANDLE_WORDS)))
#: CDR layout of the descriptor starting at an 8-byte boundary of the stream.
LAYOUT = struct.Struct("<BBHIQQQQQQQ" + "Q" * 2 * HANDLE_WORDS)

#: The generated descriptor class once :func:`descriptor_type` looked it up, None before: the
#: per-message paths of :mod:`warp_buffer.ipc` compare against it (and call
#: :func:`descriptor_type` only while it is None) without a function call per message.
loaded_type: Any = None


def descriptor_type() -> type:
    """The generated descriptor class (looked up once, and given to the native core, which
    makes descriptors by writing their slots)."""
    global loaded_type
    if loaded_type is None:
        cls = get_message_type(DESCRIPTOR_TYPE)
        if tuple(cls.__slots__) != FIELDS:  # pragma: no cover - the .msg and this disagree
            raise DescriptorError(f"{DESCRIPTOR_TYPE} fields {cls.__slots__} != {FIELDS}")
        _core.set_descriptor_type(cls, FIELDS)
        loaded_type = cls
    return loaded_type


def make(values: tuple[int, ...]) -> Any:
    """A descriptor from its field values, all of :data:`FIELDS` in order (no per-field
    validation: the values come from this process's own bookkeeping, or from :data:`LAYOUT`).
    One C call that writes each slot, as its setter would (no validating ``__setattr__``)."""
    if loaded_type is None:
        descriptor_type()
    return _make(values)


_make = _core.make


#: The field values of a descriptor, in :data:`FIELDS` order (one C call, unchecked).
fields_of = operator.attrgetter(*FIELDS)
_get_fields = fields_of


def values_of(descriptor: Any) -> tuple[int, ...]:
    """The field values of ``descriptor``, checked to be what the wire can carry (a forged or
    hand-made one may hold anything): integers in each field's range, else
    :class:`DescriptorError`. The check is the layout itself (one C call)."""
    try:
        values = _get_fields(descriptor)
    except AttributeError as exc:
        raise DescriptorError(f"not a {DESCRIPTOR_TYPE}: {exc}") from None
    _core.pack(values)  # DescriptorError: a field the wire cannot carry
    return values


#: ``check_names(values)``: :class:`DescriptorError` unless a descriptor's field values name an
#: export (version, kind, pid, session, generation, peer slot; each field's width), one C call.
check_names = _core.check_names


def pack(descriptor: Any) -> bytes:
    """The descriptor's CDR bytes (as at an 8-byte boundary of a CDR stream)."""
    try:
        values = _get_fields(descriptor)
    except AttributeError as exc:
        raise DescriptorError(f"not a {DESCRIPTOR_TYPE}: {exc}") from None
    return _core.pack(values)


def unpack(data: bytes | bytearray | memoryview) -> Any:
    """Inverse of :func:`pack`."""
    return make(_core.unpack(data))


def handle_words(handle: bytes) -> tuple[int, ...]:
    """A 64-byte CUDA IPC handle as eight little-endian words."""
    if len(handle) > 8 * HANDLE_WORDS:
        raise DescriptorError(f"a CUDA IPC handle is {8 * HANDLE_WORDS} bytes, not {len(handle)}")
    return struct.unpack("<8Q", handle.ljust(8 * HANDLE_WORDS, b"\0"))


def handle_bytes(words: tuple[int, ...] | list[int]) -> bytes:
    return struct.pack("<8Q", *words)


def vmm_words(serial: int, nbytes: int) -> tuple[int, ...]:
    """The ``mem_handle`` words of a ``KIND_CUDA_VMM`` block: its allocation serial (unique in
    the session, so an importer re-imports a block whose memory changed) and its bytes."""
    return (serial, nbytes) + (0,) * (HANDLE_WORDS - 2)


def uuid_word(uuid: str | None) -> int:
    """The descriptor's 64-bit word for a CUDA device UUID (``wp.Device.uuid``, one per GPU and
    per MIG instance; PCI bus ids are shared by MIG instances): a BLAKE2b digest, 0 for none."""
    if not uuid:
        return 0
    return int.from_bytes(hashlib.blake2b(uuid.encode(), digest_size=8).digest(), "little") or 1
