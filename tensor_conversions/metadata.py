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
from .errors import InvalidTensorMetadataError

__all__ = [
    "TENSOR_MSG_TYPE",
    "TensorLayout",
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
        dims = tuple(int(d) for d in shape)
    except (TypeError, ValueError):
        raise InvalidTensorMetadataError(
            f"shape must be a sequence of ints, got {shape!r}") from None
    if any(d < 0 for d in dims):
        raise InvalidTensorMetadataError(f"shape {dims} has a negative dimension")
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

    @property
    def ndim(self) -> int:
        return len(self.shape)

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

    @classmethod
    def contiguous(cls, dtype: DType, shape: Sequence[int]) -> TensorLayout:
        dims = normalize_shape(shape)
        return cls(dtype, dims, contiguous_strides(dims), 0)

    def check_fits(self, nbytes: int) -> None:
        if self.required_nbytes > nbytes:
            raise InvalidTensorMetadataError(
                f"tensor {self.dtype.name}{list(self.shape)} with strides {list(self.strides)} and "
                f"byte_offset {self.byte_offset} needs {self.required_nbytes} bytes of data, "
                f"the message has {nbytes}"
            )


def _int_list(value: Any, field: str) -> list[int]:
    # perf: the fields are 1-D int64 arrays in practice; tolist() is one C call instead of a
    # Python loop of int() (same values; anything else takes the generic path below).
    if type(value) is np.ndarray and value.dtype.kind in "iu":
        return value.reshape(-1).tolist()
    try:
        return [int(v) for v in np.asarray(value).reshape(-1)]
    except (TypeError, ValueError):
        raise InvalidTensorMetadataError(
            f"{field} must be a sequence of ints, got {value!r}") from None


def layout_of(msg: Any, nbytes: int | None = None) -> TensorLayout:
    """Validate the metadata of ``msg`` against its ``data`` size and return its layout.

    Raises :class:`UnsupportedDTypeError` for a dtype this package cannot handle and
    :class:`InvalidTensorMetadataError` for inconsistent shape/strides/byte_offset.
    """
    dtype = dtype_from_metadata(msg.dtype_code, msg.dtype_bits, msg.dtype_lanes)
    shape = _int_list(msg.shape, "shape")
    if any(d < 0 for d in shape):
        raise InvalidTensorMetadataError(f"shape {shape} has a negative dimension")
    strides = _int_list(msg.strides, "strides")
    if not strides:
        strides = list(contiguous_strides(shape))
    elif len(strides) != len(shape):
        raise InvalidTensorMetadataError(
            f"strides {strides} must be empty or have one entry per dimension of shape {shape}")
    if any(s < 0 for s in strides):
        raise InvalidTensorMetadataError(f"negative strides {strides} are not supported")
    byte_offset = int(msg.byte_offset)
    if byte_offset < 0:
        raise InvalidTensorMetadataError(f"byte_offset {byte_offset} is negative")
    layout = TensorLayout(dtype, tuple(shape), tuple(strides), byte_offset)
    layout.check_fits(len(msg.data) if nbytes is None else nbytes)
    return layout


def write_metadata(msg: Any, layout: TensorLayout, *, explicit_strides: bool = False) -> None:
    """Store ``layout`` in the metadata fields of ``msg`` (``data`` is left alone).

    Contiguous layouts are written with empty ``strides`` (DLPack's convention) unless
    ``explicit_strides`` is set.
    """
    msg.dtype_code = layout.dtype.code
    msg.dtype_bits = layout.dtype.bits
    msg.dtype_lanes = layout.dtype.lanes
    msg.shape = np.asarray(layout.shape, dtype=np.int64).reshape(-1)
    keep = explicit_strides or not layout.is_contiguous
    msg.strides = np.asarray(layout.strides if keep else (), dtype=np.int64).reshape(-1)
    msg.byte_offset = layout.byte_offset
