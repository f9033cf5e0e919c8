"""Typed errors of tensor_conversions (all subclasses of ``RosidlBufferError``)."""

from __future__ import annotations

from rosidl_buffer.errors import RosidlBufferError

__all__ = [
    "TensorConversionError",
    "UnsupportedDTypeError",
    "InvalidTensorMetadataError",
    "UnsupportedBackendError",
    "TensorSizeError",
    "UnsupportedValueError",
    "WrongMessageTypeError",
    "UnsupportedEncodingError",
    "StorageNotWritableError",
]


class TensorConversionError(RosidlBufferError):
    """Base class of every error raised by tensor_conversions."""


class UnsupportedDTypeError(TensorConversionError, TypeError):
    """A dtype (DLPack code/bits/lanes or a framework dtype) that cannot be represented."""


class InvalidTensorMetadataError(TensorConversionError, ValueError):
    """Message metadata (shape, strides, byte_offset) is inconsistent or does not fit ``data``."""


class UnsupportedBackendError(TensorConversionError, ValueError):
    """A storage backend or device that cannot be served (never silently replaced by another)."""


class TensorSizeError(TensorConversionError, ValueError):
    """A value does not fit the preallocated ``data`` of a message."""


class UnsupportedValueError(TensorConversionError, TypeError):
    """A value the framework module cannot send (``to_tensor_msg`` of a list, another
    framework's tensor, ...)."""


class WrongMessageTypeError(TensorConversionError, TypeError):
    """A message of another type (an ``Image`` given to a tensor function, or the reverse)."""


class UnsupportedEncodingError(TensorConversionError, ValueError):
    """An image encoding this package cannot view (compressed, YUV, 16-bit Bayer, ...)."""


class StorageNotWritableError(TensorConversionError, RuntimeError):
    """A writable view of storage whose write is over: a warp buffer takes one write in its life
    (it was written, read or published), and a loaned message's loan ended at publish."""
