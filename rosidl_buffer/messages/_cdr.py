"""ROS 2 CDR (XCDR1, little endian) for generated messages, with the buffer-field extension.

Why not rosbags' own serializer: it has no hook to write a ``uint8[]`` field as a backend
descriptor (the marker form below) and reports malformed input with untyped errors. Its bytes are
the reference: tests check this codec byte for byte against ``Typestore.serialize_cdr``.

Wire form of a buffer field:
- CPU: the ordinary sequence, ``uint32 length`` then the bytes (old readers are unaffected);
- backend (rosidl_typesupport_fastrtps >= 3.9.4, ``buffer_serialization.hpp``): after aligning to
  4, the words ``0xFFFFFFFF`` and ``0x524F5332`` ("ROS2"), the backend name as a CDR string, then
  the descriptor message inline (aligned against the same origin as the rest of the stream), at
  most ``MAX_BUFFER_DESCRIPTOR_SIZE`` bytes. A reader takes the descriptor path only when both
  words match; a first word alone is the length of an ordinary sequence. As upstream's generated
  type support, only top-level ``uint8[]`` fields travel in backend form: a nested message's
  buffers are always CPU bytes.

Serialization runs in two passes, sizing then writing into one preallocated ``bytearray``, so a
payload is copied exactly once. Deserialization returns buffers that alias the input bytes.

A descriptor type made of primitives only (the warp backend's) has a fixed layout: it is sized
once per type, and packed and unpacked with one precompiled ``struct`` call (the run's struct
at the alignment phase where the field falls), its message built by the slots' own setters from
C. The field-by-field path is the reference: it gives the same bytes, and the typed error for a
value the struct refuses.

Per message, :func:`serialize_message` and :func:`deserialize_message` run the C codec
(``rosidl_buffer._cdr_native``): one call per message, interpreting a program made once per type
from the same steps (``_MessageCodec.native``, see :func:`_native_program`). This module stays
the reference and the fallback: the C codec hands any value or input that is not the plain case
to the field objects here (which write it or raise their error), and a type it would not take,
or input that is not a byte buffer of CDR_LE, goes through :func:`_serialize_python` /
:func:`_read_python` entirely.
"""

from __future__ import annotations

import collections
import functools
import itertools
import keyword
import operator
import struct
import sys
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import numpy as np

from ..backend import MAX_BUFFER_DESCRIPTOR_SIZE, BufferBackend
from ..buffer import Buffer, impl_of, set_impl
from ..buffer_impl import BufferImplBase, CpuBufferImpl, exact_array
from ..endpoint import EndpointInfo
from ..errors import (
    DeserializationError,
    DescriptorTooLargeError,
    RosidlBufferError,
    SerializationError,
)
from ..native import load_extension
from ._classes import Message, get_message_type, numpy_dtype
from ._schema import PRIMITIVE_FORMATS, FieldKind, FieldSpec, get_schema

__all__ = [
    "BUFFER_DESCRIPTOR_MARKER",
    "BUFFER_DESCRIPTOR_MARKER_2",
    "CDR_HEADER",
    "BufferRoute",
    "serialize_message",
    "deserialize_message",
    "serialized_size",
]

CDR_HEADER = b"\x00\x01\x00\x00"  # representation CDR_LE, options 0
_ORIGIN = len(CDR_HEADER)  # alignment counts from the end of the header
BUFFER_DESCRIPTOR_MARKER = 0xFFFFFFFF
BUFFER_DESCRIPTOR_MARKER_2 = 0x524F5332  # "ROS2"
_U32 = struct.Struct("<I")
_HEADER = struct.Struct("<III")  # a descriptor form's two markers and its backend name's length
_NUMPY_COPY_THRESHOLD = 1 << 16
_ZEROS = tuple(bytes(n) for n in range(8))  # padding, by length
_LITTLE_ENDIAN = sys.byteorder == "little"

#: Decides, per buffer field, whether it travels as a descriptor: returns ``(backend_name,
#: descriptor)`` or None for the ordinary CPU sequence.
BufferRoute = Callable[[Buffer], "tuple[str, Any] | None"]


def _align(pos: int, alignment: int) -> int:
    return pos + (-(pos - _ORIGIN) % alignment)


def _pad(out: bytearray, pos: int, alignment: int) -> int:
    """``_align`` for the write pass: zero the padding, so a reused output buffer (see
    :func:`serialize_message`'s ``out``) carries no bytes of an earlier message."""
    pad = -(pos - _ORIGIN) % alignment
    if pad:
        out[pos:pos + pad] = _ZEROS[pad]
        return pos + pad
    return pos


class _SizeContext(NamedTuple):
    """Pass one's context (a NamedTuple: made once per message, built by ``_new_context``
    without a Python ``__new__``)."""

    route: BufferRoute | None
    decisions: list[Any]

    def inner(self) -> _SizeContext:
        """The context of a nested message: no route (its buffers are CPU bytes), the same
        decisions (pass two replays them in field order)."""
        if self.route is None:
            return self
        return _SizeContext(None, self.decisions)


class _ReadContext(NamedTuple):
    """A read's context (a NamedTuple, as :class:`_SizeContext`)."""

    data: memoryview
    owner: Any
    backends: Mapping[str, BufferBackend] | None
    endpoint_info: EndpointInfo | None
    top_level: bool = True

    def inner(self) -> _ReadContext:
        """The context of a nested message, where a descriptor is malformed input."""
        if not self.top_level:
            return self
        return _ReadContext(self.data, self.owner, self.backends, self.endpoint_info, False)


# What pass one decided for one buffer field, replayed by pass two: ``(host bytes, None, None)``
# for the CPU form, ``(None, encoded backend name, descriptor, its decisions or None for a fixed
# layout)`` for a descriptor.
_CPU_IMPLS: dict[type, bool] = {}  # impl type -> is it CPU storage (judged once per type)
_IMPLS: dict[type, bool] = {}  # type a backend returned -> is it a BufferImplBase
_NAMES: dict[str, bytes] = {}  # backend name -> its CDR string bytes after the length
_call = getattr(operator, "call", lambda function, *args: function(*args))  # (3.11+)
_repeat = itertools.repeat
_drain = collections.deque(maxlen=0).extend  # runs an iterator at C speed, keeps nothing
_new_buffer = Buffer.__new__
_new_context = tuple.__new__  # a context NamedTuple from its values, no Python frame


def _judge_cpu(kind: type) -> bool:
    """Is ``kind`` (an impl type) CPU storage? Judged once per type (``_CPU_IMPLS``)."""
    found = _CPU_IMPLS[kind] = issubclass(kind, CpuBufferImpl)
    return found


def _name_bytes(name: Any, field: str) -> bytes:
    """A backend name's CDR string bytes after the length (remembered: ``_NAMES``)."""
    found = _encode_string(name, 0, field) + b"\0"
    if type(name) is str and len(_NAMES) < 64:
        _NAMES[name] = found
    return found


def _host_bytes(buffer: Buffer) -> np.ndarray:
    """``buffer``'s contents as the bytes a ``uint8[]`` carries: its host view, or (a Buffer of
    another dtype, a view of more dimensions) that view's bytes, so the count written is the
    byte count the data fills."""
    host = buffer.host_view()
    if host.dtype != np.uint8 or host.ndim != 1 or not host.flags.c_contiguous:
        host = np.ascontiguousarray(host).reshape(-1).view(np.uint8)
    return host


def _buffer_of(impl: BufferImplBase) -> Buffer:
    """A Buffer over ``impl`` (``Buffer._of``, without its call: once per received field)."""
    buffer = _new_buffer(Buffer)
    set_impl(buffer, impl)
    return buffer


# --------------------------------------------------------------------------- field operations
class _Field:
    """Sizes, writes and reads one field. Subclasses are built once per schema field."""

    def __init__(self, spec: FieldSpec) -> None:
        self.spec = spec
        self.name = spec.name

    def size(self, value: Any, pos: int, ctx: _SizeContext) -> int:
        raise NotImplementedError

    def write(self, value: Any, out: bytearray, pos: int, decisions: list[Any]) -> int:
        raise NotImplementedError

    def read(self, ctx: _ReadContext, pos: int) -> tuple[Any, int]:
        raise NotImplementedError

    def _fail(self, message: str) -> SerializationError:
        return SerializationError(f"field {self.name!r}: {message}")


def _need(ctx: _ReadContext, pos: int, nbytes: int, what: str) -> None:
    if nbytes < 0 or pos + nbytes > len(ctx.data):
        raise DeserializationError(
            f"truncated message: {what} needs {nbytes} bytes at offset {pos}, "
            f"{max(0, len(ctx.data) - pos)} left"
        )


def _read_count(ctx: _ReadContext, pos: int, what: str) -> tuple[int, int]:
    pos = _align(pos, 4)
    _need(ctx, pos, 4, what)
    return _U32.unpack_from(ctx.data, pos)[0], pos + 4


class _Primitive(_Field):
    def __init__(self, spec: FieldSpec) -> None:
        super().__init__(spec)
        self.struct = struct.Struct("<" + PRIMITIVE_FORMATS[spec.element])
        self.width = self.struct.size

    def size(self, value: Any, pos: int, ctx: _SizeContext) -> int:
        return _align(pos, self.width) + self.width

    def write(self, value: Any, out: bytearray, pos: int, decisions: list[Any]) -> int:
        pos = _pad(out, pos, self.width)
        try:
            self.struct.pack_into(out, pos, value)
        except (struct.error, TypeError, OverflowError) as exc:  # OverflowError: 1e39 in float32
            raise self._fail(f"{value!r} is not a valid {self.spec.element}: {exc}") from None
        return pos + self.width

    def read(self, ctx: _ReadContext, pos: int) -> tuple[Any, int]:
        pos = _align(pos, self.width)
        _need(ctx, pos, self.width, self.name)
        return self.struct.unpack_from(ctx.data, pos)[0], pos + self.width


def _encode_string(value: Any, bound: int, name: str) -> bytes:
    if not isinstance(value, str):
        raise SerializationError(f"field {name!r}: expected str, got {type(value).__name__}")
    try:
        encoded = value.encode("utf-8")
    except UnicodeEncodeError as exc:  # a lone surrogate ("\ud800")
        raise SerializationError(f"field {name!r}: not encodable as UTF-8: {exc}") from None
    if bound and len(encoded) > bound:
        raise SerializationError(f"field {name!r}: string longer than its bound {bound}")
    # An embedded NUL is written as it is, before the terminating one: what _read_string accepts
    # (a relay republishes what it received), byte for byte what rosbags writes and reads back,
    # and what rmw's C++ typesupport (std::string, counted by the length) carries.
    return encoded


def _read_string(ctx: _ReadContext, pos: int, name: str) -> tuple[str, int]:
    length, pos = _read_count(ctx, pos, name)
    _need(ctx, pos, length, name)
    if length == 0 or ctx.data[pos + length - 1] != 0:
        raise DeserializationError(f"field {name!r}: string at offset {pos} is not NUL-terminated")
    try:
        text = bytes(ctx.data[pos:pos + length - 1]).decode("utf-8")
    except UnicodeDecodeError as exc:
        raise DeserializationError(f"field {name!r}: invalid UTF-8: {exc}") from None
    return text, pos + length


class _String(_Field):
    def size(self, value: Any, pos: int, ctx: _SizeContext) -> int:
        return _align(pos, 4) + 4 + len(_encode_string(value, self.spec.string_bound, self.name)) + 1

    def write(self, value: Any, out: bytearray, pos: int, decisions: list[Any]) -> int:
        encoded = _encode_string(value, self.spec.string_bound, self.name)
        pos = _pad(out, pos, 4)
        _U32.pack_into(out, pos, len(encoded) + 1)
        pos += 4
        out[pos:pos + len(encoded)] = encoded
        out[pos + len(encoded)] = 0
        return pos + len(encoded) + 1

    def read(self, ctx: _ReadContext, pos: int) -> tuple[Any, int]:
        text, end = _read_string(ctx, pos, self.name)
        bound = self.spec.string_bound
        if bound and end - _align(pos, 4) - 5 > bound:  # bytes before the NUL, as written
            raise DeserializationError(f"field {self.name!r}: string longer than its bound {bound}")
        return text, end


class _Nested(_Field):
    def size(self, value: Any, pos: int, ctx: _SizeContext) -> int:
        return _codec(self.spec.element).size(value, pos, ctx.inner())

    def write(self, value: Any, out: bytearray, pos: int, decisions: list[Any]) -> int:
        return _codec(self.spec.element).write(value, out, pos, decisions)

    def read(self, ctx: _ReadContext, pos: int) -> tuple[Any, int]:
        return _codec(self.spec.element).read(ctx.inner(), pos)


class _NumericArray(_Field):
    """``T[N]``, ``T[]`` and ``T[<=N]`` of primitives, held as NumPy arrays."""

    def __init__(self, spec: FieldSpec) -> None:
        super().__init__(spec)
        self.dtype = numpy_dtype(spec.element).newbyteorder("<")
        self.width = self.dtype.itemsize
        # Arrays are read in this dtype; on a little-endian host it is the builtin one, so a
        # received array that is published again passes the ``is`` check of :meth:`write`.
        self.native = numpy_dtype(spec.element) if _LITTLE_ENDIAN else self.dtype
        self.unchecked = _LITTLE_ENDIAN and not (spec.array_length or spec.sequence_bound)

    def _array(self, value: Any) -> np.ndarray:
        # The shape is checked before the array is made contiguous: ascontiguousarray turns a
        # scalar (None, 5) into a 1-element array. Values must fit exactly (see exact_array).
        try:
            array = exact_array(value, self.dtype)
        except (TypeError, ValueError, OverflowError) as exc:
            raise self._fail(f"cannot convert to {self.spec.element}[]: {exc}") from None
        if array.ndim != 1:
            raise self._fail(f"expected a 1-D sequence, got shape {array.shape}")
        array = np.ascontiguousarray(array)
        n = array.shape[0]
        if self.spec.array_length and n != self.spec.array_length:
            raise self._fail(f"expected exactly {self.spec.array_length} elements, got {n}")
        if self.spec.sequence_bound and n > self.spec.sequence_bound:
            raise self._fail(f"{n} elements exceed the bound {self.spec.sequence_bound}")
        return array

    def size(self, value: Any, pos: int, ctx: _SizeContext) -> int:
        if (value.__class__ is np.ndarray and value.ndim == 1) or value.__class__ is list:
            n = len(value)  # write checks the values
        else:  # anything else (None, a scalar, a 0-d array, a tuple) is checked here
            n = self._array(value).shape[0]
        if self.spec.is_sequence:
            pos += 4 + (-(pos - _ORIGIN) % 4)
        return pos + (-(pos - _ORIGIN) % self.width) + n * self.width if n else pos

    def write(self, value: Any, out: bytearray, pos: int, decisions: list[Any]) -> int:
        # An array already in the wire form is written as it is (the common case: metadata a
        # conversions package built, or one received); anything else is converted and checked.
        if (value.__class__ is np.ndarray and value.dtype is self.native and self.unchecked
                and value.ndim == 1 and value.flags.c_contiguous):
            array = value
        else:
            array = self._array(value)
        return _write_array(array, out, pos, self.spec.is_sequence, self.width)

    def read(self, ctx: _ReadContext, pos: int) -> tuple[Any, int]:
        data = ctx.data
        if self.spec.is_sequence:
            pos += -(pos - _ORIGIN) % 4
            if pos + 4 > len(data):
                _need(ctx, pos, 4, self.name)
            n = _U32.unpack_from(data, pos)[0]
            pos += 4
            if self.spec.sequence_bound and n > self.spec.sequence_bound:
                raise DeserializationError(
                    f"field {self.name!r}: {n} elements exceed the bound {self.spec.sequence_bound}"
                )
        else:
            n = self.spec.array_length
        if n:
            pos += -(pos - _ORIGIN) % self.width
        nbytes = n * self.width
        if pos + nbytes > len(data):
            _need(ctx, pos, nbytes, self.name)
        array = np.frombuffer(data, dtype=self.dtype, count=n, offset=pos).astype(self.native)
        return array, pos + nbytes


def _write_array(array: np.ndarray, out: bytearray, pos: int, counted: bool, width: int) -> int:
    n = array.shape[0]
    if counted:
        pad = -(pos - _ORIGIN) % 4  # (the padding of _pad, inline: once per array per message)
        if pad:
            out[pos:pos + pad] = _ZEROS[pad]
            pos += pad
        _U32.pack_into(out, pos, n)
        pos += 4
    if n:
        pad = -(pos - _ORIGIN) % width
        if pad:
            out[pos:pos + pad] = _ZEROS[pad]
            pos += pad
        nbytes = n * width
        if nbytes >= _NUMPY_COPY_THRESHOLD:
            # NumPy's copy runs at memcpy speed; bytearray slice assignment is several times slower.
            np.frombuffer(out, np.uint8, nbytes, pos)[:] = array.view(np.uint8)
        elif nbytes <= 1024:  # a few metadata integers: tobytes is the cheapest small copy
            out[pos:pos + nbytes] = array.tobytes()
        else:
            out[pos:pos + nbytes] = memoryview(array).cast("B")
        pos += nbytes
    return pos


class _ObjectArray(_Field):
    """``T[N]`` / ``T[]`` of strings or messages, held as lists."""

    def __init__(self, spec: FieldSpec) -> None:
        super().__init__(spec)
        element = FieldSpec(spec.name, spec.kind, spec.element, string_bound=spec.string_bound)
        self.element = _String(element) if spec.kind is FieldKind.STRING else _Nested(element)

    def _check(self, value: Any) -> None:
        if not isinstance(value, (list, tuple)):
            raise self._fail(f"expected a list, got {type(value).__name__}")
        n = len(value)
        if self.spec.array_length and n != self.spec.array_length:
            raise self._fail(f"expected exactly {self.spec.array_length} elements, got {n}")
        if self.spec.sequence_bound and n > self.spec.sequence_bound:
            raise self._fail(f"{n} elements exceed the bound {self.spec.sequence_bound}")

    def size(self, value: Any, pos: int, ctx: _SizeContext) -> int:
        self._check(value)
        if self.spec.is_sequence:
            pos = _align(pos, 4) + 4
        for item in value:
            pos = self.element.size(item, pos, ctx)
        return pos

    def write(self, value: Any, out: bytearray, pos: int, decisions: list[Any]) -> int:
        if self.spec.is_sequence:
            pos = _pad(out, pos, 4)
            _U32.pack_into(out, pos, len(value))
            pos += 4
        for item in value:
            pos = self.element.write(item, out, pos, decisions)
        return pos

    def read(self, ctx: _ReadContext, pos: int) -> tuple[Any, int]:
        if self.spec.is_sequence:
            n, pos = _read_count(ctx, pos, self.name)
            if self.spec.sequence_bound and n > self.spec.sequence_bound:
                raise DeserializationError(
                    f"field {self.name!r}: {n} elements exceed the bound {self.spec.sequence_bound}"
                )
            # Every element takes at least one byte: reject absurd counts before looping.
            _need(ctx, pos, n, self.name)
        else:
            n = self.spec.array_length
        items = []
        for _ in range(n):
            item, pos = self.element.read(ctx, pos)
            items.append(item)
        return items, pos


def _descriptor_size(codec: _MessageCodec, descriptor: Any) -> int:
    """The descriptor's own CDR size (as serialized alone), which the limit applies to.

    Inline, padding before and inside it depends on where the field falls in the message, so the
    limit would otherwise shift by a few bytes with the position of the field.
    """
    return codec.size(descriptor, _ORIGIN, _SizeContext(None, [])) - _ORIGIN


class _BufferField(_Field):
    """An unbounded ``uint8[]``: CPU sequence, or markers + backend name + descriptor (a
    fixed-layout descriptor in one struct call, see the module docstring)."""

    def __init__(self, spec: FieldSpec) -> None:
        super().__init__(spec)
        self.backend_name = _String(spec)  # the name written before a descriptor
        self._descriptor_types: dict[Any, Any] = {}  # backend -> its descriptor's codec

    def size(self, value: Buffer, pos: int, ctx: _SizeContext) -> int:
        if value.__class__ is not Buffer and not isinstance(value, Buffer):
            value = Buffer(value)
        route = ctx.route
        if route is not None:
            kind = type(impl_of(value))
            cpu = _CPU_IMPLS.get(kind)
            route = None if (_judge_cpu(kind) if cpu is None else cpu) else route(value)
        if route is None:
            host = _host_bytes(value)
            ctx.decisions.append((host, None, None))
            return _align(pos, 4) + 4 + host.nbytes
        backend_name, descriptor = route
        name = _NAMES.get(backend_name) if type(backend_name) is str else None
        if name is None:
            name = _name_bytes(backend_name, self.name)
        pos += 12 + (-(pos - _ORIGIN) % 4) + len(name)  # two markers, the name's length, name
        codec = _codec(descriptor.__msgtype__)
        if codec.fixed is not None:  # sized once per type
            nbytes = codec.fixed_size
            end = pos + codec.fixed[(pos - _ORIGIN) & 7][1]
            descriptor_decisions = None
        else:
            nbytes = _descriptor_size(codec, descriptor)
            # The descriptor's own fields (a uint8[] included) are always written as plain CDR.
            descriptor_ctx = _SizeContext(None, [])
            end = codec.size(descriptor, pos, descriptor_ctx)
            descriptor_decisions = descriptor_ctx.decisions[::-1]
        if nbytes > MAX_BUFFER_DESCRIPTOR_SIZE:
            raise DescriptorTooLargeError(
                f"field {self.name!r}: descriptor of backend {backend_name!r} serializes to "
                f"{nbytes} bytes, over the {MAX_BUFFER_DESCRIPTOR_SIZE}-byte limit"
            )
        ctx.decisions.append((None, name, descriptor, descriptor_decisions))
        return end

    def write(self, value: Any, out: bytearray, pos: int, decisions: list[Any]) -> int:
        decision = decisions.pop()
        host = decision[0]
        if host is not None:
            return _write_array(host, out, pos, True, 1)
        _, name, descriptor, descriptor_decisions = decision
        pad = -(pos - _ORIGIN) % 4
        if pad:
            out[pos:pos + pad] = _ZEROS[pad]
            pos += pad
        end = pos + 12 + len(name)
        _HEADER.pack_into(out, pos, BUFFER_DESCRIPTOR_MARKER, BUFFER_DESCRIPTOR_MARKER_2,
                          len(name))
        out[pos + 12:end] = name
        codec = _codec(descriptor.__msgtype__)
        if descriptor_decisions is None:  # fixed layout: one struct call
            packer, length = codec.fixed[(end - _ORIGIN) & 7]
            try:
                packer.pack_into(out, end, *codec.values(descriptor))
            except (struct.error, TypeError, OverflowError):
                return codec.write(descriptor, out, end, [])  # the field's own typed error
            return end + length
        return codec.write(descriptor, out, end, descriptor_decisions)

    def _native_descriptor_program(self, backend: BufferBackend) -> Any:
        """The native Program of ``backend``'s descriptor type (the C codec's lookup, cached
        there per backend as ``_descriptor_types`` is here)."""
        codec = self._descriptor_types.get(backend)
        if codec is None:
            codec = self._descriptor_types[backend] = _codec(
                backend.get_descriptor_type().__msgtype__)
        return codec.native

    @staticmethod
    def _second_marker(ctx: _ReadContext, pos: int) -> bool:
        """Is the word after a first marker the second one? (Upstream reads it only then: an
        empty stream end after 0xFFFFFFFF is a too-long sequence, not a short read.)"""
        data = ctx.data
        return pos + 4 <= len(data) and _U32.unpack_from(data, pos)[0] == BUFFER_DESCRIPTOR_MARKER_2

    def read(self, ctx: _ReadContext, pos: int) -> tuple[Any, int]:
        data = ctx.data
        pos += -(pos - _ORIGIN) % 4
        end = len(data)
        if pos + 4 <= end:  # the common forms in one pass; anything else: _read_checked
            n = _U32.unpack_from(data, pos)[0]
            if n != BUFFER_DESCRIPTOR_MARKER:
                if pos + 4 + n <= end:
                    view = np.frombuffer(ctx.owner, dtype=np.uint8, count=n, offset=pos + 4)
                    return _buffer_of(CpuBufferImpl.wrap(view)), pos + 4 + n
            elif pos + 12 <= end and ctx.top_level:
                _, second, length = _HEADER.unpack_from(data, pos)
                if second == BUFFER_DESCRIPTOR_MARKER_2 and length and pos + 12 + length <= end:
                    return self._read_descriptor(ctx, pos + 12, length)
        return self._read_checked(ctx, pos)

    def _read_checked(self, ctx: _ReadContext, pos: int) -> tuple[Any, int]:
        """The field read step by step: every malformed form's typed error."""
        n, pos = _read_count(ctx, pos, self.name)
        if n != BUFFER_DESCRIPTOR_MARKER or not self._second_marker(ctx, pos):
            _need(ctx, pos, n, self.name)
            view = np.frombuffer(ctx.owner, dtype=np.uint8, count=n, offset=pos)
            return _buffer_of(CpuBufferImpl.wrap(view)), pos + n
        if not ctx.top_level:
            raise DeserializationError(
                f"field {self.name!r}: a backend descriptor in a nested message (only top-level "
                "uint8[] fields travel in backend form)")
        return self._read_descriptor(ctx, pos + 4, None)

    def _read_descriptor(self, ctx: _ReadContext, pos: int, length: int | None
                         ) -> tuple[Any, int]:
        """A descriptor form: the backend name at ``pos`` (after its ``length``, read already;
        None: at ``pos`` with its length), then the descriptor, rebuilt by the backend."""
        data = ctx.data
        if length is not None and data[pos + length - 1] == 0:
            try:
                backend_name = bytes(data[pos:pos + length - 1]).decode("utf-8")
            except UnicodeDecodeError as exc:
                raise DeserializationError(f"field {self.name!r}: invalid UTF-8: {exc}") from None
            pos += length
        else:
            backend_name, pos = _read_string(ctx, pos - (0 if length is None else 4), self.name)
        backend = (ctx.backends or {}).get(backend_name)
        if backend is None:
            raise DeserializationError(
                f"field {self.name!r}: buffer from backend {backend_name!r}, which this reader "
                f"does not have (available: {sorted(ctx.backends or {})})"
            )
        descriptor_codec = self._descriptor_types.get(backend)
        if descriptor_codec is None:
            descriptor_codec = self._descriptor_types[backend] = _codec(
                backend.get_descriptor_type().__msgtype__)
        fixed = descriptor_codec.fixed
        unpacker, size = fixed[(pos - _ORIGIN) & 7] if fixed is not None else (None, 0)
        if unpacker is not None and pos + size <= len(data):  # one struct call
            nbytes = descriptor_codec.fixed_size
            descriptor = descriptor_codec.new(descriptor_codec.cls)
            _drain(map(_call, descriptor_codec.setters, _repeat(descriptor),
                       unpacker.unpack_from(data, pos)))
            pos += size
        else:
            descriptor, pos = descriptor_codec.read(ctx, pos)
            nbytes = _descriptor_size(descriptor_codec, descriptor)
        if nbytes > MAX_BUFFER_DESCRIPTOR_SIZE:
            raise DeserializationError(
                f"field {self.name!r}: descriptor is {nbytes} bytes, over the "
                f"{MAX_BUFFER_DESCRIPTOR_SIZE}-byte limit"
            )
        if ctx.endpoint_info is None:
            raise DeserializationError(
                f"field {self.name!r}: a backend descriptor needs the publisher's endpoint info"
            )
        impl = backend.from_descriptor_with_endpoint(descriptor, ctx.endpoint_info)
        kind = type(impl)
        valid = _IMPLS.get(kind)  # (isinstance against the ABC costs a call: once per type)
        if valid is None:
            valid = _IMPLS[kind] = issubclass(kind, BufferImplBase)
        if not valid:
            raise DeserializationError(
                f"field {self.name!r}: backend {backend_name!r} returned "
                f"{type(impl).__name__}, not a BufferImplBase")
        buffer = _new_buffer(Buffer)  # (_buffer_of, inline: once per received descriptor)
        set_impl(buffer, impl)
        return buffer, pos


# --------------------------------------------------------------------------- message codec
def _make_field(spec: FieldSpec) -> _Field:
    if spec.is_buffer:
        return _BufferField(spec)
    if spec.is_collection:
        if spec.kind is FieldKind.PRIMITIVE:
            return _NumericArray(spec)
        return _ObjectArray(spec)
    if spec.kind is FieldKind.PRIMITIVE:
        return _Primitive(spec)
    if spec.kind is FieldKind.STRING:
        return _String(spec)
    return _Nested(spec)


class _PrimitiveRun:
    """Consecutive primitive fields (one or more) handled as one ``struct``.

    The padding between primitives depends only on the run's start offset modulo 8 (CDR aligns
    each primitive to its own width, at most 8, counted from ``_ORIGIN``), so one ``Struct`` with
    explicit pad bytes per start phase reads, writes and sizes the whole run in one call instead
    of one Python call per field (a backend descriptor is a dozen integers, handled for every
    message). ``layouts[phase]`` is ``(Struct, length)``; the compiled codec indexes it inline.
    Byte layout, values and errors are exactly those of the per-field path: on a short buffer or
    a value ``struct`` rejects, :meth:`write` and :meth:`read` fall back to the fields
    themselves, which raise the usual field-specific error.
    """

    def __init__(self, fields: list[_Primitive]) -> None:
        self.fields = fields
        self.names = tuple(f.name for f in fields)
        self.layouts = tuple(self._layout(phase) for phase in range(8))

    def _layout(self, phase: int) -> tuple[struct.Struct, int]:
        fmt, at = "<", phase
        for field in self.fields:
            pad = -at % field.width
            fmt += "x" * pad + field.struct.format[1:]
            at += pad + field.width
        return struct.Struct(fmt), at - phase

    def write(self, message: Any, out: bytearray, pos: int, decisions: list[Any]) -> int:
        """The per-field write (called when the one-call pack failed): raises the field's own
        error for the value ``struct`` rejected."""
        for field in self.fields:
            pos = field.write(getattr(message, field.name), out, pos, decisions)
        return pos

    def read(self, ctx: _ReadContext, message: Any, pos: int) -> int:
        """The per-field read (called when the run does not fit): raises the truncation error
        of the first field that does not."""
        for field in self.fields:
            value, pos = field.read(ctx, pos)
            object.__setattr__(message, field.name, value)
        return pos


class _MessageCodec:
    """CDR of one message type: ``size``, ``write`` and ``read`` are functions compiled for it.

    The generic form (a loop over field objects, a dispatch and a ``getattr`` per field per pass)
    cost 15-30 us for an ExperimentalTensor, paid on every publish and every delivery. The
    compiled form is straight-line Python generated once per type from its schema (as rosbags
    and genpy generate theirs): runs of primitives are one inline ``struct`` call, nested
    messages call their own compiled functions, and other fields delegate to their field object
    (one call). The bytes and errors are the field objects'; ``source`` holds the code.
    """

    def __init__(self, type_name: str) -> None:
        self.cls = get_message_type(type_name)
        fields = [_make_field(spec) for spec in get_schema(type_name).fields]
        # The fields with every run of consecutive primitives grouped (see _PrimitiveRun).
        self.steps: list[Any] = []
        run: list[_Primitive] = []
        for field in [*fields, None]:
            if type(field) is _Primitive:
                run.append(field)
                continue
            if run:
                self.steps.append(_PrimitiveRun(run))
            run = []
            if field is not None:
                self.steps.append(field)
        self.source = _codec_source(self.steps)
        namespace = _codec_namespace(self)
        exec(compile(self.source, f"<cdr {type_name}>", "exec"), namespace)
        self.size: Callable[[Any, int, _SizeContext], int] = namespace["size"]
        self.write: Callable[[Any, bytearray, int, list[Any]], int] = namespace["write"]
        self.read: Callable[[_ReadContext, int], tuple[Any, int]] = namespace["read"]
        # A type of primitives only has a fixed layout: (struct, length) by alignment phase, its
        # size alone, its values in field order (one C call) and its slots' setters.
        run = self.steps[0] if len(self.steps) == 1 else None
        self.fixed: tuple[tuple[struct.Struct, int], ...] | None = None
        if type(run) is _PrimitiveRun:
            self.fixed = run.layouts
            self.fixed_size = run.layouts[0][1]  # as serialized alone (from the origin)
            self.values = operator.attrgetter(*run.names) if len(run.names) > 1 else (
                lambda m, get=operator.attrgetter(run.names[0]): (get(m),))
            self.setters = tuple(self.cls.__dict__[name].__set__ for name in run.names)
            self.new = self.cls.__new__
        # The same steps as a program of the C codec (None: a step it does not take, or a
        # big-endian host; the type then keeps this codec entirely).
        self.native: Any = _native_program(self)


def _wrong_type(cls: type, message: Any) -> SerializationError:
    return SerializationError(f"expected a {cls.__msgtype__} message, got {type(message).__name__}")


def _codec_namespace(codec: _MessageCodec) -> dict[str, Any]:
    """The names the compiled functions of ``codec`` use (see :func:`_codec_source`)."""
    namespace: dict[str, Any] = {
        "cls": codec.cls, "new": codec.cls.__new__, "wrong_type": _wrong_type,
        "struct_error": struct.error, "ndarray": np.ndarray, "frombuffer": np.frombuffer,
        "u32": _U32.unpack_from, "write_array": _write_array,
    }
    for i, step in enumerate(codec.steps):
        namespace[f"S{i}"] = step
        if type(step) is _PrimitiveRun:
            namespace[f"L{i}"] = step.layouts
            namespace[f"N{i}"] = tuple(length for _, length in step.layouts)
            names = step.names
        elif type(step) is _NumericArray and step.unchecked and step.spec.is_sequence:
            # the inline form's names (see _codec_source)
            namespace[f"W{i}"], namespace[f"D{i}"] = step.width, step.dtype
            namespace[f"NAT{i}"] = step.native
            names = (step.name,)
        elif type(step) is _Nested:
            nested = _codec(step.spec.element)
            namespace[f"CS{i}"], namespace[f"CW{i}"] = nested.size, nested.write
            namespace[f"CR{i}"] = nested.read
            names = (step.name,)
        else:
            names = (step.name,)
        for name in names:  # the slot's own setter: no Message.__setattr__ per field
            namespace[f"set_{name}"] = codec.cls.__dict__[name].__set__
            if keyword.iskeyword(name):  # see _get
                namespace[f"get_{name}"] = operator.attrgetter(name)
    return namespace


def _get(name: str) -> str:
    """The expression reading field ``name`` of message ``m``: an attribute access, or for a
    field named like a Python keyword (valid in a .msg file) its getter."""
    return f"get_{name}(m)" if keyword.iskeyword(name) else f"m.{name}"


def _codec_source(steps: list[Any]) -> str:
    """Python source of ``size``, ``write`` and ``read`` for a message made of ``steps``.

    Phases are ``(pos - _ORIGIN) & 7`` with ``_ORIGIN`` = 4 (alignment counts from the end of
    the CDR header); runs fall back to their per-field code for the exact error.
    """
    assert _ORIGIN == 4
    size = ["def size(m, pos, ctx):",
            "    if m.__class__ is not cls and not isinstance(m, cls):",
            "        raise wrong_type(cls, m)"]
    write = ["def write(m, out, pos, decisions):"]
    read = ["def read(ctx, pos):", "    m = new(cls)", "    data = ctx.data"]
    for i, step in enumerate(steps):
        kind = type(step)
        if kind is _PrimitiveRun:
            values = ", ".join(_get(name) for name in step.names)
            targets = ", ".join(f"v_{name}" for name in step.names)
            size.append(f"    pos += N{i}[(pos - 4) & 7]")
            write += [f"    packer, length = L{i}[(pos - 4) & 7]",
                      "    try:",
                      f"        packer.pack_into(out, pos, {values})",
                      "    except (struct_error, TypeError, OverflowError):",
                      f"        pos = S{i}.write(m, out, pos, decisions)",
                      "    else:",
                      "        pos += length"]
            read += [f"    unpacker, length = L{i}[(pos - 4) & 7]",
                     "    if pos + length > len(data):",
                     f"        pos = S{i}.read(ctx, m, pos)",
                     "    else:",
                     f"        ({targets},) = unpacker.unpack_from(data, pos)",
                     *(f"        set_{name}(m, v_{name})" for name in step.names),
                     "        pos += length"]
        elif kind is _NumericArray and step.unchecked and step.spec.is_sequence:
            # An unbounded sequence of numbers (a tensor's shape and strides): inline when it
            # is a 1-D array (sized, then written as it is when already in the wire dtype) and
            # when it fits the data (read); anything else goes to the field, which converts,
            # checks and raises as ever.
            get = _get(step.name)
            size += [f"    v = {get}",
                     "    if v.__class__ is ndarray and v.ndim == 1:",
                     "        pos += 4 + (4 - pos) % 4",
                     f"        if v.shape[0]: pos += (4 - pos) % W{i} + v.shape[0] * W{i}",
                     "    else:",
                     f"        pos = S{i}.size(v, pos, ctx)"]
            write += [f"    v = {get}",
                      f"    if (v.__class__ is ndarray and v.dtype is NAT{i} and v.ndim == 1",
                      "            and v.flags.c_contiguous):",
                      f"        pos = write_array(v, out, pos, True, W{i})",
                      "    else:",
                      f"        pos = S{i}.write(v, out, pos, decisions)"]
            read += ["    p = pos + (4 - pos) % 4",
                     "    n = u32(data, p)[0] if p + 4 <= len(data) else -1",
                     "    p += 4",
                     "    if n > 0:",
                     f"        p += (4 - p) % W{i}",
                     f"    if n >= 0 and p + n * W{i} <= len(data):",
                     f"        set_{step.name}(m, frombuffer(data, D{i}, n, p).astype(NAT{i}))",
                     f"        pos = p + n * W{i}",
                     "    else:",
                     f"        value, pos = S{i}.read(ctx, pos)",
                     f"        set_{step.name}(m, value)"]
        elif kind is _Nested:
            # a nested message's buffers never travel as descriptors (see the module doc)
            size.append(f"    pos = CS{i}({_get(step.name)}, pos, ctx.inner())")
            write.append(f"    pos = CW{i}({_get(step.name)}, out, pos, decisions)")
            read += [f"    value, pos = CR{i}(ctx.inner(), pos)", f"    set_{step.name}(m, value)"]
        else:
            size.append(f"    pos = S{i}.size({_get(step.name)}, pos, ctx)")
            write.append(f"    pos = S{i}.write({_get(step.name)}, out, pos, decisions)")
            read += [f"    value, pos = S{i}.read(ctx, pos)", f"    set_{step.name}(m, value)"]
    size.append("    return pos")
    write.append("    return pos")
    read.append("    return m, pos")
    return "\n".join([*size, "", *write, "", *read, ""])


def _load_native() -> Any:
    """The C codec (``rosidl_buffer._cdr_native``), configured. Missing, it raises
    :class:`~rosidl_buffer.errors.NativeExtensionMissingError` (see docs/native.md)."""
    native = load_extension("rosidl_buffer._cdr_native")
    native.configure(
        ndarray=np.ndarray, buffer=Buffer, cpu_impl=CpuBufferImpl, frombuffer=np.frombuffer,
        uint8=np.dtype(np.uint8), cpu_impls=_CPU_IMPLS, judge_cpu=_judge_cpu, impls=_IMPLS,
        impl_base=BufferImplBase, read_context=_ReadContext, wrong_type=_wrong_type,
        name_bytes=_name_bytes, write_array=_write_array, pair=_pair, host_bytes=_host_bytes,
        resolve_descriptor=_descriptor_program, DeserializationError=DeserializationError,
        SerializationError=SerializationError, DescriptorTooLargeError=DescriptorTooLargeError,
        settings=globals())
    return native


def _pair(route: Any) -> tuple[Any, Any]:
    """A route's answer as ``(backend_name, descriptor)`` (what pass one unpacks)."""
    backend_name, descriptor = route
    return backend_name, descriptor


def _descriptor_program(descriptor: Any) -> Any:
    """The C codec's Program for a descriptor a route returned (cached there per type)."""
    program = _codec(descriptor.__msgtype__).native
    if program is None:
        raise SerializationError(f"no native codec for {descriptor.__msgtype__}")
    return program


def _native_program(codec: _MessageCodec) -> Any:
    """The C codec's Program for ``codec``'s steps, or None (see ``_MessageCodec.native``)."""
    if not _LITTLE_ENDIAN:
        return None
    slots = codec.cls.__dict__
    kinds = {**_native.KINDS, "byte": _native.KINDS["uint8"], "char": _native.KINDS["uint8"]}
    ops: list[tuple[Any, ...]] = []
    for step in codec.steps:
        kind = type(step)
        if kind is _PrimitiveRun:
            ops.append((_native.OP_RUN, step, tuple(
                (slots[f.name], f.name, kinds[f.spec.element]) for f in step.fields)))
            continue
        spec = step.spec
        head = (step, slots[spec.name], spec.name)
        if kind is _String:
            ops.append((_native.OP_STRING, *head, spec.string_bound))
        elif kind is _Nested:
            sub = _codec(spec.element).native
            if sub is None:
                return None
            ops.append((_native.OP_NESTED, *head, sub))
        elif kind is _NumericArray:
            ops.append((_native.OP_NUMARRAY, *head, kinds[spec.element], spec.array_length,
                        spec.is_sequence, spec.sequence_bound, step.dtype, step.native))
        elif kind is _ObjectArray and spec.kind is FieldKind.STRING:
            ops.append((_native.OP_STRARRAY, *head, spec.array_length, spec.is_sequence,
                        spec.sequence_bound, spec.string_bound, step.element))
        elif kind is _ObjectArray and spec.kind is FieldKind.MESSAGE:
            sub = _codec(spec.element).native
            if sub is None:
                return None
            ops.append((_native.OP_MSGARRAY, *head, spec.array_length, spec.is_sequence,
                        spec.sequence_bound, sub))
        elif kind is _BufferField:
            ops.append((_native.OP_BUFFER, *head))
        else:
            return None
    return _native.Program(codec.cls, tuple(ops))


@functools.lru_cache(maxsize=None)
def _codec(type_name: str) -> _MessageCodec:
    return _MessageCodec(type_name)


#: deserialize_message's codec per ``msg_type`` argument (a class or a type name as given).
_decoders: dict[Any, _MessageCodec] = {}


def _plan(message: Message, route: BufferRoute | None) -> tuple[_MessageCodec, int, list[Any]]:
    if not isinstance(message, Message):
        raise SerializationError(f"not a generated message: {type(message).__name__}")
    codec = _codec(message.__msgtype__)
    ctx = _new_context(_SizeContext, (route, []))
    end = codec.size(message, _ORIGIN, ctx)
    return codec, end, ctx.decisions


def serialized_size(message: Message) -> int:
    """Bytes that :func:`serialize_message` would produce on the CPU path."""
    return _plan(message, None)[1]


def serialize_message(message: Message, *, route: BufferRoute | None = None,
                      out: bytearray | None = None) -> bytearray:
    """Serialize ``message`` as ROS 2 CDR, with the 4-byte encapsulation header.

    Without ``route`` every buffer is written as CPU bytes (backend buffers through ``to_cpu``).
    A transport passes ``route`` to write non-CPU buffers as backend descriptors for one peer.
    Returns a ``bytearray`` (a bytes-like; turning it into ``bytes`` would copy the payload again):
    ``out`` itself when it has exactly the serialized size (a transport that copies the bytes
    away at once reuses one buffer and saves a fresh allocation and its page faults per message),
    else a new one.
    """
    program = _programs.get(message.__class__, _UNKNOWN)
    if program is _UNKNOWN:
        program = _program_of(message)
    if program is not None:
        return _native.serialize(program, message, route, out)
    return _serialize_python(message, route, out)


_UNKNOWN = object()
#: serialize_message's C program per message class (None: the Python codec serves it).
_programs: dict[type, Any] = {}


def _program_of(message: Any) -> Any:
    """The C program for ``message``'s class, decided once per class: None for what is not a
    generated message (the Python path raises its error) or a class the codec of its type
    name does not take (as its wrong-type check)."""
    program = None
    if isinstance(message, Message):
        codec = _codec(message.__msgtype__)
        if issubclass(message.__class__, codec.cls):
            program = codec.native
        _programs[message.__class__] = program
    return program


def _serialize_python(message: Message, route: BufferRoute | None = None,
                      out: bytearray | None = None) -> bytearray:
    """:func:`serialize_message` by the Python codec (the reference, and the fallback)."""
    codec, end, decisions = _plan(message, route)
    if out is None or len(out) != end:
        out = bytearray(end)
    out[:_ORIGIN] = CDR_HEADER
    decisions.reverse()  # pass two pops them in field order
    codec.write(message, out, _ORIGIN, decisions)
    return out


def deserialize_message(
    data: bytes | bytearray | memoryview,
    msg_type: type[Message] | str,
    *,
    backends: Mapping[str, BufferBackend] | None = None,
    endpoint_info: EndpointInfo | None = None,
) -> Message:
    """Decode CDR ``data`` into a ``msg_type`` message.

    CPU buffer fields alias ``data`` (zero copy; a write to them copies first when ``data`` is
    immutable). A backend-form buffer field is rebuilt by ``backends[name]`` from the descriptor,
    with ``endpoint_info`` describing the publisher. Malformed input raises
    :class:`DeserializationError`; a backend's own typed errors propagate unchanged.
    """
    codec = _decoders.get(msg_type)
    if codec is None:
        type_name = msg_type if isinstance(msg_type, str) else msg_type.__msgtype__
        codec = _decoders[msg_type] = _codec(get_message_type(type_name).__msgtype__)
    program = codec.native
    if program is not None:
        try:
            message = _native.deserialize(program, data, backends, endpoint_info)
        except RosidlBufferError:
            raise
        except (ValueError, TypeError, struct.error, IndexError, OverflowError) as exc:
            raise DeserializationError(f"malformed {codec.cls.__msgtype__}: {exc}") from exc
        if message is not _native.FALLBACK:
            return message
    return _read_python(codec, data, backends, endpoint_info)


def _deserialize_python(data: bytes | bytearray | memoryview, msg_type: type[Message] | str, *,
                        backends: Mapping[str, BufferBackend] | None = None,
                        endpoint_info: EndpointInfo | None = None) -> Message:
    """:func:`deserialize_message` by the Python codec (the reference, and the fallback)."""
    type_name = msg_type if isinstance(msg_type, str) else msg_type.__msgtype__
    return _read_python(_codec(get_message_type(type_name).__msgtype__), data, backends,
                        endpoint_info)


def _read_python(codec: _MessageCodec, data: bytes | bytearray | memoryview,
                 backends: Mapping[str, BufferBackend] | None,
                 endpoint_info: EndpointInfo | None) -> Message:
    type_name = codec.cls.__msgtype__
    try:
        view = memoryview(data).cast("B") if not isinstance(data, bytes) else memoryview(data)
    except TypeError:
        raise DeserializationError(f"CDR data of a {type_name} is bytes-like, not "
                                   f"{type(data).__name__}") from None
    if len(view) < _ORIGIN:
        raise DeserializationError(f"{len(view)} bytes is shorter than the CDR header")
    header = bytes(view[:2])
    if header != CDR_HEADER[:2]:
        kind = "big-endian CDR is not supported" if header == b"\x00\x00" else "unknown encoding"
        raise DeserializationError(f"CDR header {header.hex()}: {kind}")
    ctx = _new_context(_ReadContext, (view, data, backends, endpoint_info, True))
    try:
        message, _ = codec.read(ctx, _ORIGIN)
    except RosidlBufferError:
        raise
    except (ValueError, TypeError, struct.error, IndexError, OverflowError) as exc:
        raise DeserializationError(f"malformed {type_name}: {exc}") from exc
    return message


_native = _load_native()
