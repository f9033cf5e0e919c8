"""CDR of buffer-era messages: the framing of a top-level ``uint8[]`` field.

Models ``rosidl_typesupport_fastrtps_cpp/buffer_serialization.hpp`` (3.9.5) as the generated
type support (``msg__type_support.cpp.em``) applies it to each top-level ``uint8[]`` member:

- CPU form: the ordinary CDR sequence (align 4, uint32 length, the bytes).
- Backend form (``serialize_buffer_with_endpoint`` when the backend made a descriptor):
  align 4, uint32 ``0xFFFFFFFF``, uint32 ``0x524F5332`` ("ROS2"), the backend name as a CDR
  string, then the descriptor message inline in the same stream.
- Reading: endpoint-aware (``deserialize_buffer_with_endpoint``, used on a subscription's
  ``_buf/<gid>`` route) takes the descriptor path only when both words match, and fails when
  the backend is not installed; plain (``operator>>``, used on the base key and ``_buf_cpu``)
  throws on the descriptor form.

Everything else is ordinary XCDR1 little endian, written and read by rosbags. Positions, and so
alignment, count from the start of the stream after the 4-byte encapsulation header, as FastCDR
counts them. The model reads little-endian payloads only.
"""

from __future__ import annotations

import dataclasses
import struct
from collections.abc import Mapping
from typing import Any

import numpy as np
from rosbags.serde.utils import align as rosbags_align
from rosbags.typesys.store import Typestore

from tests.upstream_model.messages import buffer_fields

MARKER1 = 0xFFFFFFFF
MARKER2 = 0x524F5332  # "ROS2"
HEADER = b"\x00\x01\x00\x00"  # CDR, little endian
_SEGMENT_PKG = "upstream_model_segments/msg/"


class CdrError(ValueError):
    """Upstream's deserialization fails (returns false or throws) on this payload."""


@dataclasses.dataclass(frozen=True)
class BackendForm:
    """A buffer field written by a backend: its name and its descriptor message."""

    backend: str
    descriptor: Any
    descriptor_type: str


@dataclasses.dataclass(frozen=True)
class FieldFrame:
    """How one buffer field was framed on the wire."""

    form: str                     # "cpu" or "backend"
    data: bytes | None = None     # the CPU bytes
    backend: str | None = None
    descriptor: Any = None
    descriptor_type: str | None = None


@dataclasses.dataclass(frozen=True)
class Decoded:
    message: Any                  # backend-form fields hold an empty array
    frames: dict[str, FieldFrame]


# ---------------------------------------------------------------------------- layout
def _layout(store: Typestore, ros_type: str) -> list[tuple[str, str]]:
    """The message as ("segment", <registered type of consecutive ordinary fields>) and
    ("buffer", <field name>) items, in field order."""
    fields = store.fielddefs[ros_type][1]
    buffers = set(buffer_fields(store, ros_type))
    items: list[tuple[str, str]] = []
    run: list[tuple[str, Any]] = []
    for name, desc in [*fields, (None, None)]:
        if name is None or name in buffers:
            if run:
                seg = f"{_SEGMENT_PKG}{ros_type.replace('/', '__')}__{len(items)}"
                if seg not in store.fielddefs:
                    store.register({seg: ([], run)})
                items.append(("segment", seg))
                run = []
            if name is not None:
                items.append(("buffer", name))
        else:
            run.append((name, desc))
    return items


def _align(pos: int, size: int) -> int:
    return (pos + size - 1) & -size


def _first_alignment(store: Typestore, ros_type: str) -> int:
    return rosbags_align(store.fielddefs[ros_type][1][0][1], store)


# ---------------------------------------------------------------------------- writing
class _Writer:
    def __init__(self, store: Typestore) -> None:
        self.store = store
        self.buf = bytearray(HEADER)

    @property
    def pos(self) -> int:
        return len(self.buf) - len(HEADER)

    def pad(self, size: int) -> None:
        self.buf += bytes(_align(self.pos, size) - self.pos)

    def u32(self, value: int) -> None:
        self.pad(4)
        self.buf += struct.pack("<I", value)

    def string(self, text: str) -> None:
        raw = text.encode()
        self.u32(len(raw) + 1)
        self.buf += raw + b"\x00"

    def message(self, ros_type: str, message: Any) -> None:
        """A message (or segment) inline, through rosbags, at the current position."""
        self.pad(_first_alignment(self.store, ros_type))
        msgdef = self.store.get_msgdef(ros_type)
        end = msgdef.getsize_cdr(self.pos, message, self.store)
        start = self.pos
        self.buf += bytes(end - start)
        written = msgdef.serialize_cdr_le(memoryview(self.buf)[len(HEADER):], start, message,
                                          self.store)
        assert written == end


def serialize(store: Typestore, message: Any, ros_type: str,
              backend_forms: Mapping[str, BackendForm] | None = None) -> bytes:
    """The payload (with encapsulation header) of ``message``; the buffer fields named in
    ``backend_forms`` in backend form, every other field ordinary CDR."""
    backend_forms = backend_forms or {}
    unknown = set(backend_forms) - set(buffer_fields(store, ros_type))
    if unknown:
        raise ValueError(f"not top-level uint8[] fields of {ros_type}: {sorted(unknown)}")
    out = _Writer(store)
    for kind, name in _layout(store, ros_type):
        if kind == "segment":
            seg_fields = [f for f, _ in store.fielddefs[name][1]]
            out.message(name, store.types[name](**{f: getattr(message, f) for f in seg_fields}))
        elif name in backend_forms:
            form = backend_forms[name]
            out.u32(MARKER1)
            out.u32(MARKER2)
            out.string(form.backend)
            out.message(form.descriptor_type, form.descriptor)
        else:
            data = bytes(np.asarray(getattr(message, name), dtype=np.uint8))
            out.u32(len(data))
            out.buf += data
    return bytes(out.buf)


# ---------------------------------------------------------------------------- reading
def deserialize(store: Typestore, payload: bytes, ros_type: str, *, endpoint_aware: bool,
                descriptor_types: Mapping[str, str] | None = None) -> Decoded:
    """Read ``payload`` as upstream's subscription does on a route.

    ``endpoint_aware``: the ``_buf/<gid>`` route (``deserialize_ros_message_with_endpoint``);
    otherwise plain deserialization (base key, ``_buf_cpu``). ``descriptor_types``: backend
    name -> descriptor type of the backends installed in the reader. Raises CdrError where
    upstream's deserialization fails. Bytes after the last field are ignored, as FastCDR does."""
    if bytes(payload[:2]) != HEADER[:2]:
        raise CdrError(f"not a little-endian CDR payload (header {bytes(payload[:4]).hex()})")
    body = memoryview(payload)[len(HEADER):]
    descriptor_types = descriptor_types or {}
    values: dict[str, Any] = {}
    frames: dict[str, FieldFrame] = {}
    pos = 0

    def need(count: int, what: str) -> None:
        if pos + count > len(body):
            raise CdrError(f"payload ends inside {what} (offset {pos}, {count} bytes needed)")

    def u32(what: str) -> int:
        nonlocal pos
        pos = _align(pos, 4)
        need(4, what)
        (value,) = struct.unpack_from("<I", body, pos)
        pos += 4
        return value

    def message(name: str, what: str) -> Any:
        nonlocal pos
        pos = _align(pos, _first_alignment(store, name))
        msgdef = store.get_msgdef(name)
        try:
            value, pos = msgdef.deserialize_cdr_le(body, pos, msgdef.cls, store)
        except (struct.error, UnicodeDecodeError, ValueError, IndexError) as exc:
            raise CdrError(f"cannot read {what}: {exc}") from exc
        return value

    for kind, name in _layout(store, ros_type):
        if kind == "segment":
            seg = message(name, f"fields of {ros_type}")
            values.update({f: getattr(seg, f) for f, _ in store.fielddefs[name][1]})
            continue
        start = _align(pos, 4)
        first = u32(f"field {name}")
        is_descriptor = first == MARKER1 and u32(f"field {name}") == MARKER2
        if not is_descriptor:
            pos = start + 4
            need(first, f"field {name}")
            data = bytes(body[pos:pos + first])
            pos += first
            values[name] = np.frombuffer(data, dtype=np.uint8)
            frames[name] = FieldFrame(form="cpu", data=data)
            continue
        if not endpoint_aware:
            raise CdrError(f"field {name} is in backend form on a plain route "
                           "(operator>> only supports CPU vector bytes)")
        length = u32("backend name")
        need(length, "backend name")
        backend = bytes(body[pos:pos + max(length - 1, 0)]).decode("utf-8", "replace")
        pos += length
        descriptor_type = descriptor_types.get(backend)
        if descriptor_type is None:
            raise CdrError(f"field {name}: backend {backend!r} is not available here")
        descriptor = message(descriptor_type, f"the {backend} descriptor")
        values[name] = np.zeros(0, dtype=np.uint8)
        frames[name] = FieldFrame(form="backend", backend=backend, descriptor=descriptor,
                                  descriptor_type=descriptor_type)
    return Decoded(message=store.types[ros_type](**values), frames=frames)
