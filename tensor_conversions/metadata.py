"""Tensor layout of an ExperimentalTensor message: read, validate and write its metadata.

Conventions (DLPack's): strides are in elements and an empty ``strides`` means contiguous
row-major; ``byte_offset`` is the offset of element ``[0, ..., 0]`` inside ``data``. Negative
strides are rejected (PyTorch and Warp cannot view them); zero strides (broadcast) are allowed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from rosidl_buffer.messages import get_message_type

from .dtypes import DType, dtype_from_metadata
from .errors import InvalidTensorMetadataError, UnsupportedDTypeError, WrongMessageTypeError

__all__ = [
    "TENSOR_MSG_TYPE",
    "TensorLayout",
    "check_tensor_msg",
    "contiguous_strides",
    "layout_of",
    "normalize_shape",
    "tensor_msg_type",
    "write_metadata",
]

TENSOR_MSG_TYPE = "tensor_msgs/msg/ExperimentalTensor"


def tensor_msg_type() -> type:
    """The generated ``tensor_msgs/msg/ExperimentalTensor`` class."""
    return get_message_type(TENSOR_MSG_TYPE)


INT64_MAX = 2**63 - 1  # a dimension, a stride: the message's fields are int64[]


def contiguous_strides(shape: Sequence[int]) -> tuple[int, ...]:
    """Row-major strides in elements for ``shape``."""
    strides = []
    step = 1
    for dim in reversed(shape):
        strides.append(step)
        step *= max(int(dim), 1)
    return tuple(reversed(strides))


def normalize_shape(shape: Sequence[int] | int) -> tuple[int, ...]:
    """``shape`` as a tuple of non-negative ints (an int means a 1-D shape)."""
    if isinstance(shape, (int, np.integer)):
        shape = (int(shape),)
    try:
        items = list(shape)
    except TypeError:
        items = None
    dims = None if items is None else _exact_ints(items)
    if dims is None or any(isinstance(d, (bool, str, bytes)) for d in items):
        raise InvalidTensorMetadataError(f"shape must be a sequence of ints, got {shape!r}")
    if any(d < 0 for d in dims):
        raise InvalidTensorMetadataError(f"shape {dims} has a negative dimension")
    if any(d > INT64_MAX for d in dims):  # the message's shape is int64[]
        raise InvalidTensorMetadataError(f"shape {dims} has a dimension past int64")
    return dims


class _cached:
    """perf: a lock-free ``functools.cached_property`` (3.11's takes a lock on every miss).

    A non-data descriptor: the first access stores the value in the instance ``__dict__``
    (bypassing the frozen ``__setattr__``), later accesses never reach the descriptor.
    """

    def __init__(self, func: Any) -> None:
        self.func = func
        self.name = func.__name__
        self.__doc__ = func.__doc__

    def __get__(self, instance: Any, owner: Any = None) -> Any:
        if instance is None:
            return self
        value = self.func(instance)
        instance.__dict__[self.name] = value
        return value


@dataclass(frozen=True)
class TensorLayout:
    """A validated layout: dtype, shape, element strides (always explicit) and byte offset."""

    dtype: DType
    shape: tuple[int, ...]
    strides: tuple[int, ...]
    byte_offset: int = 0

    @_cached  # perf: layouts are immutable; computed once, not per access
    def numel(self) -> int:
        return math.prod(self.shape)

    @_cached  # perf: layouts are immutable; computed once, not per access
    def byte_strides(self) -> tuple[int, ...]:
        return tuple(s * self.dtype.itemsize for s in self.strides)

    @_cached  # perf: layouts are immutable; computed once, not per access
    def is_contiguous(self) -> bool:
        """Row-major contiguous (strides of size-1 dimensions do not matter)."""
        expected = contiguous_strides(self.shape)
        return self.numel == 0 or all(
            d == 1 or s == e for d, s, e in zip(self.shape, self.strides, expected))

    @_cached  # perf: layouts are immutable; computed once, not per access
    def span_bytes(self) -> int:
        """Bytes from the first element to the end of the last one (0 for an empty tensor)."""
        if self.numel == 0:
            return 0
        last = sum((d - 1) * s for d, s in zip(self.shape, self.strides))
        return (last + 1) * self.dtype.itemsize

    @_cached  # perf: layouts are immutable; computed once, not per access
    def required_nbytes(self) -> int:
        """Smallest ``len(data)`` that holds this layout."""
        return self.byte_offset + self.span_bytes

    @_cached  # perf: layouts are immutable; computed once, not per access
    def numpy_args(self) -> tuple[Any, ...] | None:
        """``(shape, np.dtype, byte_offset, byte_strides)`` for ``np.ndarray`` over the bytes,
        or None where NumPy cannot carry it (bfloat16, an empty tensor)."""
        if self.numel == 0:
            return None
        try:
            dtype = self.dtype.numpy_dtype()
        except UnsupportedDTypeError:
            return None
        return self.shape, dtype, self.byte_offset, self.byte_strides

    def ndarray_over(self, storage: np.ndarray) -> np.ndarray:
        """This layout as an ``np.ndarray`` over host ``storage`` (1-D uint8, no copy); an empty
        tensor is a new empty array, a dtype NumPy lacks raises :class:`UnsupportedDTypeError`."""
        args = self.numpy_args
        if args is None:
            return np.empty(self.shape, dtype=self.dtype.numpy_dtype())
        shape, dtype, offset, strides = args
        return np.ndarray(shape, dtype, buffer=storage, offset=offset, strides=strides)

    @classmethod
    def contiguous(cls, dtype: DType, shape: Sequence[int]) -> TensorLayout:
        """A new row-major layout of ``shape``, refused where a reader would refuse it."""
        dims = normalize_shape(shape)
        check_extent(dtype, dims)
        return cls(dtype, dims, contiguous_strides(dims), 0)

    def check_fits(self, nbytes: int) -> None:
        """Raise :class:`InvalidTensorMetadataError` unless ``nbytes`` bytes of data hold this
        layout (:attr:`required_nbytes`: offset, shape and strides together)."""
        if self.required_nbytes > nbytes:
            raise InvalidTensorMetadataError(
                f"tensor {self.dtype.name}{list(self.shape)} with strides {list(self.strides)} and "
                f"byte_offset {self.byte_offset} needs {self.required_nbytes} bytes of data, "
                f"the message has {nbytes}"
            )


def _exact_ints(items: Sequence[Any]) -> tuple[int, ...] | None:
    """``items`` as ints, or None if one is not an integer value: int() would truncate 2.5 to
    2, and a fractional dimension is an error, not a smaller tensor (4.0 or a NumPy int is)."""
    try:
        ints = tuple(int(v) for v in items)
    except (TypeError, ValueError, OverflowError):
        return None
    return ints if all(i == v for i, v in zip(ints, items)) else None


def _ints(value: Any, field: str) -> tuple[int, ...]:
    if type(value) is np.ndarray and value.dtype.kind in "iu":
        return tuple(value.reshape(-1).tolist())  # one C call for the usual int64 field
    try:
        ints = _exact_ints(np.asarray(value).reshape(-1).tolist())
    except (TypeError, ValueError):
        ints = None
    if ints is None:
        raise InvalidTensorMetadataError(f"{field} must be a sequence of ints, got {value!r}")
    return ints


_TENSOR_CLASS: list[type] = []


def check_tensor_msg(msg: Any) -> None:
    """Raise :class:`WrongMessageTypeError` unless ``msg`` is an ExperimentalTensor."""
    if not _TENSOR_CLASS:
        _TENSOR_CLASS.append(tensor_msg_type())
    if type(msg) is not _TENSOR_CLASS[0]:
        name = getattr(msg, "__msgtype__", type(msg).__name__)
        hint = " (use the *_image_msg functions)" if name == "sensor_msgs/msg/Image" else ""
        raise WrongMessageTypeError(f"expected a {TENSOR_MSG_TYPE}, got {name}{hint}")


# A layout is validated once per distinct metadata, not once per frame: the memo is keyed by the
# metadata values and the data size (never by object identity) and bounded.
_LAYOUTS: dict[tuple[Any, ...], TensorLayout] = {}
_INT64 = np.dtype(np.int64)
_MAX_LAYOUTS = 256


#: The largest logical size (elements x item size) a tensor may have: what NumPy indexes.
MAX_LOGICAL_BYTES = 2**62


def layout_of(msg: Any) -> TensorLayout:
    """The validated layout of an ExperimentalTensor ``msg``, checked against its ``data`` size.

    Raises :class:`WrongMessageTypeError` for another message type,
    :class:`UnsupportedDTypeError` for a dtype this package cannot handle and
    :class:`InvalidTensorMetadataError` for inconsistent shape/strides/byte_offset.
    """
    if not _TENSOR_CLASS or type(msg) is not _TENSOR_CLASS[0]:  # (the check's common case,
        check_tensor_msg(msg)  # inline: once per message)
    shape, strides = msg.shape, msg.strides
    if (type(shape) is np.ndarray and type(strides) is np.ndarray and shape.dtype is _INT64
            and strides.dtype is _INT64 and shape.ndim == 1 and strides.ndim == 1):
        dims, steps = tuple(shape.tolist()), tuple(strides.tolist())  # perf: the decoded form
    else:
        dims, steps = _ints(shape, "shape"), _ints(strides, "strides")
    key = (msg.dtype_code, msg.dtype_bits, msg.dtype_lanes, dims, steps, msg.byte_offset,
           len(msg.data))
    found = _LAYOUTS.get(key)
    if found is None:
        found = _validate(*key)
        if len(_LAYOUTS) >= _MAX_LAYOUTS:
            _LAYOUTS.clear()
        _LAYOUTS[key] = found
    return found


def _validate(code: Any, bits: Any, lanes: Any, shape: tuple[int, ...], strides: tuple[int, ...],
              byte_offset: Any, nbytes: int) -> TensorLayout:
    dtype = dtype_from_metadata(code, bits, lanes)
    if any(d < 0 for d in shape):
        raise InvalidTensorMetadataError(f"shape {list(shape)} has a negative dimension")
    if not strides:
        strides = contiguous_strides(shape)
    elif len(strides) != len(shape):
        raise InvalidTensorMetadataError(
            f"strides {list(strides)} must be empty or have one entry per dimension of shape "
            f"{list(shape)}")
    if any(s < 0 for s in strides):
        raise InvalidTensorMetadataError(f"negative strides {list(strides)} are not supported")
    # A dimension of size 0 or 1 never steps: its stride is meaningless, and a huge one (2**62)
    # would overflow the frameworks' byte strides.
    strides = tuple(0 if d <= 1 else s for d, s in zip(shape, strides))
    byte_offset = int(byte_offset)
    if byte_offset < 0:
        raise InvalidTensorMetadataError(f"byte_offset {byte_offset} is negative")
    check_extent(dtype, shape)
    layout = TensorLayout(dtype, shape, strides, byte_offset)
    layout.check_fits(nbytes)
    return layout


def check_extent(dtype: DType, shape: Sequence[int]) -> None:
    """Refuse a shape the frameworks cannot index: NumPy refuses an array whose dimensions
    (the non-zero ones, even when another is 0) multiply past its index type, with a raw
    ValueError."""
    extent = dtype.itemsize
    for d in shape:
        extent *= max(d, 1)
    if extent > MAX_LOGICAL_BYTES:
        raise InvalidTensorMetadataError(
            f"shape {list(shape)} of {dtype.name} spans {extent} bytes, more than any tensor "
            f"can ({MAX_LOGICAL_BYTES})")


def write_metadata(msg: Any, layout: TensorLayout) -> None:
    """Store ``layout`` in the metadata fields of ``msg`` (``data`` is left alone).

    Contiguous layouts are written with empty ``strides`` (DLPack's convention).
    """
    msg.dtype_code = layout.dtype.code
    msg.dtype_bits = layout.dtype.bits
    msg.dtype_lanes = layout.dtype.lanes
    msg.shape = np.asarray(layout.shape, dtype=np.int64).reshape(-1)
    strides = () if layout.is_contiguous else layout.strides
    msg.strides = np.asarray(strides, dtype=np.int64).reshape(-1)
    msg.byte_offset = layout.byte_offset
