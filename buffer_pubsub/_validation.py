"""Field values checked once per publish, whoever listens (intra-process subscribers included).

Serialization catches a bad value only when some remote subscriber makes the publisher serialize;
an intra-process subscriber would get a ``str`` in a ``uint32`` field. :func:`validate_message`
runs one check per field, chosen by field kind when the message class is first seen: a type and
range check for scalars, a dtype-kind and length check for numeric arrays (not per element), a
class check for nested messages. Errors are :class:`rosidl_buffer.errors.SerializationError`, the
same type the CPU serializer raises, so a bad value fails the same way on every route.
"""

from __future__ import annotations

import keyword
import numbers
import struct
from collections.abc import Callable
from typing import Any

import numpy as np

from rosidl_buffer.buffer_impl import exact_array
from rosidl_buffer.errors import SerializationError
from rosidl_buffer.messages import (
    FieldKind,
    FieldSpec,
    Message,
    get_message_type,
    get_schema,
    numpy_dtype,
)

__all__ = ["validate_message"]

_Check = Callable[[Any], None]
_validators: dict[type, Callable[[Message], None]] = {}

_INT_RANGES = {
    "byte": (0, 255), "char": (0, 255), "int8": (-2**7, 2**7 - 1), "uint8": (0, 2**8 - 1),
    "int16": (-2**15, 2**15 - 1), "uint16": (0, 2**16 - 1), "int32": (-2**31, 2**31 - 1),
    "uint32": (0, 2**32 - 1), "int64": (-2**63, 2**63 - 1), "uint64": (0, 2**64 - 1),
}
_FLOAT32_MAX = float(np.finfo(np.float32).max)
# Array dtype kinds a numeric field accepts: b bool, i/u integers, f floats.
_ARRAY_KINDS = {"bool": "b", "float32": "biuf", "float64": "biuf"}


def validate_message(msg: Message) -> None:
    """Raise SerializationError if a field of ``msg`` (nested ones included) holds a value its
    type cannot carry."""
    validator(type(msg))(msg)


def validator(cls: type) -> Callable[[Message], None]:
    """The compiled :func:`validate_message` of messages of exactly ``cls`` (a publisher keeps
    its type's: one call per publish instead of two)."""
    function = _validators.get(cls)
    if function is None:
        function = _validators[cls] = _compile(cls)
    return function


def _compile(cls: type) -> Callable[[Message], None]:
    """The validator of ``cls``: one function with a line per field, so a publish pays a few
    compares per field and no call. Each line's quick test accepts only the common exact
    types (an ``int`` in range, a ``float``, a 1-D ``ndarray`` of a fitting kind...); any other
    value goes to that field's full check, which accepts or raises as it always did."""
    lines, scope = [], {"ndarray": np.ndarray, "full": _full_check}
    for i, spec in enumerate(get_schema(cls.__msgtype__).fields):
        if spec.is_buffer:
            continue
        name = spec.name
        read = f"msg.{name}" if name.isidentifier() and not keyword.iskeyword(name) \
            else f"getattr(msg, {name!r})"
        scope[f"c{i}"] = _field_check(spec)
        quick = _quick_test(spec, scope, i)
        lines.append(f"    v = {read}\n    if not ({quick}):\n"
                     f"        full(cls, {name!r}, c{i}, v)\n")
    scope["cls"] = cls
    source = "def validate(msg):\n" + ("".join(lines) or "    pass\n")
    exec(source, scope)  # noqa: S102 - built above from the schema's field names only
    return scope["validate"]  # type: ignore[no-any-return]


def _quick_test(spec: FieldSpec, scope: dict[str, Any], i: int) -> str:
    """A Python expression over ``v`` that is True only for values the field's full check
    accepts ("False": always run the full check)."""
    element = spec.element
    if spec.is_collection:
        if spec.kind is not FieldKind.PRIMITIVE:
            return "False"
        if element in _INT_RANGES:  # only the field's own dtype is in range without a look
            scope[f"d{i}"] = numpy_dtype(element)
            test = f"type(v) is ndarray and v.ndim == 1 and v.dtype is d{i}"
        elif element == "float32":  # float64 values may not fit: those get a look
            scope[f"d{i}"] = numpy_dtype(element)
            test = (f"type(v) is ndarray and v.ndim == 1 and "
                    f"(v.dtype is d{i} or v.dtype.kind in 'biu')")
        else:
            scope[f"k{i}"] = _ARRAY_KINDS.get(element, "biu")
            test = f"type(v) is ndarray and v.ndim == 1 and v.dtype.kind in k{i}"
        if spec.array_length:
            test += f" and v.shape[0] == {spec.array_length}"
        if spec.sequence_bound:
            test += f" and v.shape[0] <= {spec.sequence_bound}"
        return test
    if spec.kind is FieldKind.STRING:  # ASCII (an O(1) flag) encodes; others are checked
        bound = spec.string_bound
        return "type(v) is str and v.isascii()" + (f" and len(v) <= {bound}" if bound else "")
    if spec.kind is not FieldKind.PRIMITIVE:
        return "False"
    if element == "bool":
        return "v is True or v is False"
    if element == "float32":  # beyond it (and NaN, which the full check accepts): a look
        return f"type(v) is float and {-_FLOAT32_MAX!r} <= v <= {_FLOAT32_MAX!r}"
    if element.startswith("float"):
        return "type(v) is float"
    low, high = _INT_RANGES[element]
    return f"type(v) is int and {low} <= v <= {high}"


def _full_check(cls: type, name: str, check: _Check, value: Any) -> None:
    try:
        check(value)
    except SerializationError as exc:
        raise SerializationError(f"{cls.__msgtype__}.{name}: {exc}") from None


def _fail(message: str) -> SerializationError:
    return SerializationError(message)


def _field_check(spec: FieldSpec) -> _Check:
    if spec.is_collection:
        if spec.kind is FieldKind.PRIMITIVE:
            return _numeric_array_check(spec)
        return _object_array_check(spec, _scalar_check(spec))
    return _scalar_check(spec)


def _scalar_check(spec: FieldSpec) -> _Check:
    element = spec.element
    if spec.kind is FieldKind.MESSAGE:
        cls = get_message_type(element)

        def check_message(value: Any) -> None:
            if type(value) is not cls:
                raise _fail(f"expected a {element} message, got {type(value).__name__}")
            validate_message(value)
        return check_message
    if spec.kind is FieldKind.STRING:
        bound = spec.string_bound

        def check_string(value: Any) -> None:
            if type(value) is not str:
                raise _fail(f"expected str, got {type(value).__name__}")
            try:
                encoded = value.encode("utf-8")
            except UnicodeEncodeError as exc:  # a lone surrogate: no UTF-8 for it
                raise _fail(f"string is not valid Unicode: {exc.reason} at {exc.start}") from None
            if bound and len(encoded) > bound:
                raise _fail(f"string longer than its bound {bound}")
        return check_string
    if element == "bool":
        def check_bool(value: Any) -> None:
            if not isinstance(value, (bool, np.bool_, int, np.integer)) or value not in (0, 1):
                raise _fail(f"expected bool, got {value!r}")
        return check_bool
    if element.startswith("float"):
        packer = struct.Struct("<f" if element == "float32" else "<d")

        def check_float(value: Any) -> None:
            if not isinstance(value, numbers.Real) or isinstance(value, str):
                raise _fail(f"expected a number for {element}, got {type(value).__name__}")
            try:
                packer.pack(value)  # exactly what the serializer will do with it
            except (OverflowError, struct.error):
                raise _fail(f"{value!r} is out of range for {element}") from None
        return check_float
    low, high = _INT_RANGES[element]

    def check_int(value: Any) -> None:
        if not isinstance(value, (int, np.integer)):
            raise _fail(f"expected an int for {element}, got {type(value).__name__} {value!r}")
        if not low <= value <= high:
            raise _fail(f"{value} out of range for {element}")
    return check_int


def _check_length(n: int, spec: FieldSpec) -> None:
    if spec.array_length and n != spec.array_length:
        raise _fail(f"expected exactly {spec.array_length} elements, got {n}")
    if spec.sequence_bound and n > spec.sequence_bound:
        raise _fail(f"{n} elements exceed the bound {spec.sequence_bound}")


def _numeric_array_check(spec: FieldSpec) -> _Check:
    kinds = _ARRAY_KINDS.get(spec.element, "biu")  # integers also take bools (0/1)

    def check_array(value: Any) -> None:
        array = value if isinstance(value, np.ndarray) else np.asarray(value)
        if array.size == 0 and array.ndim == 1 and not isinstance(value, np.ndarray):
            _check_length(0, spec)  # [] / (): NumPy calls it float64, but it holds no value
            return
        if array.dtype.kind not in kinds:
            raise _fail(f"expected {spec.element} values, got an array of {array.dtype}")
        if array.ndim != 1:
            raise _fail(f"expected a 1-D sequence, got shape {array.shape}")
        _check_length(array.shape[0], spec)
        if array.dtype != dtype and array.dtype.kind in "iuf":
            try:  # the serializer's own rule: values must fit, never wrapped (300 -> 44)
                exact_array(array, dtype)
            except (ValueError, OverflowError, TypeError) as exc:
                raise _fail(f"{exc} (for {spec.element})") from None
    dtype = numpy_dtype(spec.element)
    return check_array


def _object_array_check(spec: FieldSpec, element: _Check) -> _Check:
    def check_list(value: Any) -> None:
        if not isinstance(value, (list, tuple)):
            raise _fail(f"expected a list, got {type(value).__name__}")
        _check_length(len(value), spec)
        for item in value:
            element(item)
    return check_list
