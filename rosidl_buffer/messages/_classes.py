"""Generated Python message classes (our rosidl_generator_py).

Each class has one slot per field, keyword construction with ROS 2 defaults, ``==`` by value and a
readable ``repr``. Every unbounded ``uint8[]`` field holds a :class:`~rosidl_buffer.Buffer`:
assigning bytes, a list or an array wraps it in a CPU buffer; assigning a Buffer keeps its backend.
"""

from __future__ import annotations

import difflib
import threading
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from ..buffer import Buffer
from ..errors import InvalidBufferDataError, UnknownFieldError
from ._schema import FieldKind, FieldSpec, MessageSchema, get_schema, normalize_type_name

__all__ = ["Message", "get_message_type", "iter_buffers", "numpy_dtype", "release_buffers",
           "seal_buffers"]

_NUMPY_DTYPES = {
    "bool": np.bool_, "byte": np.uint8, "char": np.uint8, "int8": np.int8, "uint8": np.uint8,
    "int16": np.int16, "uint16": np.uint16, "int32": np.int32, "uint32": np.uint32,
    "int64": np.int64, "uint64": np.uint64, "float32": np.float32, "float64": np.float64,
}


def numpy_dtype(primitive: str) -> np.dtype:
    """The NumPy dtype of a primitive field type (``"uint8"``, ``"float32"``, ...)."""
    return np.dtype(_NUMPY_DTYPES[primitive])


class Message:
    """Base of every generated message class.

    ``_native`` is not a field: it is a per-message cache that conversions packages own (the
    write handle its views share; native views a loan reuses). It is never serialized, compared
    or printed; its value decides what copy/deepcopy keep of it.
    """

    __slots__ = ("_native",)
    __msgtype__: ClassVar[str]
    _schema: ClassVar[MessageSchema]
    _buffer_fields: ClassVar[frozenset[str]]

    if TYPE_CHECKING:
        # Fields are made per type at run time: a type checker sees them as Any (msg.data,
        # msg.height) instead of refusing every field of a message.
        def __getattr__(self, name: str) -> Any: ...

    def __init__(self, **fields: Any) -> None:
        unknown = set(fields) - set(self.__slots__)
        if unknown:
            raise _unknown_field(self, sorted(unknown)[0])
        for spec in self._schema.fields:
            value = fields[spec.name] if spec.name in fields else _default(spec)
            setattr(self, spec.name, value)

    def __setattr__(self, name: str, value: Any) -> None:
        if name in self._buffer_fields and not isinstance(value, Buffer):
            try:
                value = Buffer(value)
            except InvalidBufferDataError as exc:
                raise InvalidBufferDataError(f"{self.__msgtype__}.{name} (uint8[]): {exc}") from None
        try:
            object.__setattr__(self, name, value)
        except AttributeError:
            raise _unknown_field(self, name) from None

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        return all(_values_equal(getattr(self, name), getattr(other, name))
                   for name in self.__slots__)

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        body = ", ".join(f"{name}={_short_repr(getattr(self, name))}" for name in self.__slots__)
        return f"{self.__msgtype__.replace('/', '.')}({body})"

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickled by type name and field values (generated classes live in no importable
        module): buffers travel as their CPU bytes, as ``Buffer`` pickles; ``_native`` is not
        kept (a copy is not loaned, and holds no handle)."""
        return (_restore, (self.__msgtype__,
                           tuple(getattr(self, spec.name) for spec in self._schema.fields)))

    @classmethod
    def get_fields_and_field_types(cls) -> dict[str, str]:
        """Field name -> ROS type string, as rclpy's generated classes offer."""
        return {spec.name: _type_string(spec) for spec in cls._schema.fields}


def _restore(type_name: str, values: tuple[Any, ...]) -> Message:
    """Unpickle a message (see :meth:`Message.__reduce__`)."""
    from . import get_message_type

    cls = get_message_type(type_name)
    return cls(**{spec.name: value for spec, value in zip(cls._schema.fields, values)})


def _unknown_field(msg: Message, name: str) -> UnknownFieldError:
    fields = list(type(msg).__slots__)
    close = difflib.get_close_matches(name, fields, n=1)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    return UnknownFieldError(f"{msg.__msgtype__} has no field {name!r}{hint} "
                             f"(fields: {', '.join(fields)})", name=name, obj=msg)


def _type_string(spec: FieldSpec) -> str:
    base = spec.element
    if spec.kind is FieldKind.STRING and spec.string_bound:
        base = f"string<={spec.string_bound}"
    if spec.array_length:
        return f"{base}[{spec.array_length}]"
    if spec.is_sequence:
        return f"{base}[<={spec.sequence_bound}]" if spec.sequence_bound else f"{base}[]"
    return base


def _values_equal(a: Any, b: Any) -> bool:
    if isinstance(a, Buffer) or isinstance(b, Buffer):
        return a == b
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return bool(np.array_equal(np.asarray(a), np.asarray(b)))
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_values_equal(x, y) for x, y in zip(a, b))
    return a == b


def _short_repr(value: Any) -> str:
    if isinstance(value, np.ndarray):
        return np.array2string(value, threshold=8, separator=",")
    return repr(value)


def _element_default(spec: FieldSpec) -> Any:
    if spec.kind is FieldKind.MESSAGE:
        return get_message_type(spec.element)()
    if spec.kind is FieldKind.STRING:
        return ""
    if spec.element == "bool":
        return False
    return 0.0 if spec.element.startswith("float") else 0


def _default(spec: FieldSpec) -> Any:
    if spec.default is not None:  # the .msg file's (a new object each time: lists are mutable)
        if not spec.is_collection:
            return spec.default
        if spec.is_buffer:
            return Buffer(np.array(spec.default, dtype=np.uint8))
        if spec.kind is FieldKind.PRIMITIVE:
            return np.array(spec.default, dtype=numpy_dtype(spec.element))
        return list(spec.default)
    if spec.is_buffer:
        return Buffer()
    numeric = spec.kind is FieldKind.PRIMITIVE
    if spec.array_length:
        if numeric:
            return np.zeros(spec.array_length, dtype=numpy_dtype(spec.element))
        return [_element_default(spec) for _ in range(spec.array_length)]
    if spec.is_sequence:
        return np.empty(0, dtype=numpy_dtype(spec.element)) if numeric else []
    return _element_default(spec)


_classes: dict[str, type[Message]] = {}
_lock = threading.RLock()


def get_message_type(name: str) -> type[Message]:
    """The Python class of message type ``name`` (``pkg/msg/Name`` or ``pkg/Name``).

    Covers the ``.msg`` files shipped with installed packages and every ROS 2 type rosbags knows,
    such as ``sensor_msgs/msg/Image``. Raises :class:`UnknownMessageTypeError` otherwise.
    """
    type_name = normalize_type_name(name)
    with _lock:
        cls = _classes.get(type_name)
        if cls is None:
            schema = get_schema(type_name)
            package, _, class_name = type_name.split("/")
            namespace: dict[str, Any] = {
                "__slots__": tuple(spec.name for spec in schema.fields),
                "__msgtype__": type_name,
                "__module__": f"{package}.msg",
                "__qualname__": class_name,
                "_schema": schema,
                "_buffer_fields": frozenset(s.name for s in schema.fields if s.is_buffer),
            }
            for constant_name, _type, value in schema.constants:
                namespace[constant_name] = value
            cls = type(class_name, (Message,), namespace)
            _classes[type_name] = cls
        return cls


def iter_buffers(msg: Message) -> Iterator[Buffer]:
    """Every :class:`Buffer` of ``msg``, nested messages and sequences of messages included."""
    cls = type(msg)
    for name in cls._buffer_fields:
        yield getattr(msg, name)
    for spec in cls._schema.fields:
        if spec.kind is FieldKind.MESSAGE:
            value = getattr(msg, spec.name)
            for item in (value if isinstance(value, list) else (value,)):
                if isinstance(item, Message):
                    yield from iter_buffers(item)


def seal_buffers(msg: Message) -> None:
    """Seal every buffer of ``msg`` (the transport calls it once per publish, on every route)."""
    for buffer in iter_buffers(msg):
        buffer.seal()


def release_buffers(msg: Message) -> None:
    """Release every buffer of ``msg`` now (a message dropped before delivery, or done with)."""
    for buffer in iter_buffers(msg):
        buffer.release()
