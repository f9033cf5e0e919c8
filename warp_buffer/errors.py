"""Typed errors of warp_buffer and the warp backend.

Every error derives from :class:`WarpBufferError`, itself a
:class:`rosidl_buffer.RosidlBufferError`, so a transport can catch one family, count the failure
and keep running. Errors that also describe a standard condition inherit the matching built-in
(``ValueError``, ``PermissionError``, ...) so generic handlers work too.

::

    WarpBufferError
    ├── DeviceUnavailableError      the requested Warp device does not exist here
    ├── DeviceMemoryError           a CUDA allocation failed (out of device memory); also a
    │                               MemoryError
    ├── InvalidSizeError            a buffer size that cannot be allocated
    │   ├── SizeTypeError           a size that is not an int; also a TypeError
    │   └── EmptyBufferError        zero-byte buffers are rejected (as the backend guide says)
    ├── SizeMismatchError           to_buffer source and destination sizes differ
    ├── UnsupportedSourceError      to_buffer got something that is not array data (a list, a
    │                               str, a handle); also a TypeError
    ├── HandleError                 misuse of a read or write handle
    │   ├── WriteHandleError        a second write handle, a write after publish or read, or a
    │   │                           write into an imported (read-only) buffer
    │   └── HandleReleasedError     a released handle was used
    └── ExportError                 shared-memory / CUDA IPC export and import failures
        ├── ExportUnavailableError  this buffer cannot be exported (private memory, no IPC)
        │   └── CudaDriverError     a CUDA driver call failed, or no driver (libcuda.so.1)
        ├── DescriptorError         a malformed descriptor
        ├── ForeignExportError      the export belongs to another host or user, or its memory
        │                           is not sealed against shrinking
        ├── ExportBoundsError       size or offset beyond the block (an oversize export)
        └── StaleBufferError        the data is gone: the block was recycled, or its publisher
            │                       exited before this process attached to its memory
            └── RecycledBufferError the block was recycled for a later publish (the reader
                                    fell more than its queue behind); also a
                                    rosidl_buffer BufferOverwrittenError
"""

from __future__ import annotations

from rosidl_buffer.errors import BufferOverwrittenError, BufferReleasedError, RosidlBufferError

__all__ = [
    "WarpBufferError",
    "DeviceUnavailableError",
    "DeviceMemoryError",
    "InvalidSizeError",
    "SizeTypeError",
    "EmptyBufferError",
    "SizeMismatchError",
    "UnsupportedSourceError",
    "InvalidDTypeError",
    "HandleError",
    "WriteHandleError",
    "HandleReleasedError",
    "ExportError",
    "ExportUnavailableError",
    "CudaDriverError",
    "DescriptorError",
    "ForeignExportError",
    "ExportBoundsError",
    "StaleBufferError",
    "RecycledBufferError",
]


class WarpBufferError(RosidlBufferError):
    """Base class of every error raised by warp_buffer and warp_buffer_backend."""


class DeviceUnavailableError(WarpBufferError, RuntimeError):
    """The requested Warp device is not present (e.g. ``"cuda:0"`` on a machine without a GPU)."""


class DeviceMemoryError(WarpBufferError, MemoryError):
    """A CUDA allocation failed (the device is out of memory)."""


class InvalidSizeError(WarpBufferError, ValueError):
    """A buffer size that cannot be allocated (too large for a block)."""


class SizeTypeError(InvalidSizeError, TypeError):
    """A buffer size that is not an integer (``allocate_buffer(16.0)``)."""


class EmptyBufferError(InvalidSizeError):
    """A zero-byte (or negative) buffer size: warp buffers are never empty."""


class SizeMismatchError(WarpBufferError, ValueError):
    """A copy whose source and destination byte counts differ."""


class UnsupportedSourceError(WarpBufferError, TypeError):
    """``to_buffer`` was given something that is not array data (a list, a str, a handle), or a
    destination that is not a write handle."""


class InvalidDTypeError(WarpBufferError, TypeError):
    """A handle's ``view`` was given something that is neither a Warp nor a NumPy data type."""


class HandleError(WarpBufferError, RuntimeError):
    """A read or write handle was used against the rules."""


class WriteHandleError(HandleError):
    """A write the buffer does not allow: a buffer takes one write handle, ever, and no write once
    it was published, read, or when it was imported from another process."""


class HandleReleasedError(HandleError, BufferReleasedError):
    """The handle was released; its storage may no longer be accessed through it."""


class ExportError(WarpBufferError):
    """Exporting a buffer to another process, or importing one, failed."""


class ExportUnavailableError(ExportError):
    """This buffer cannot be exported (it lives in private memory, or IPC is not possible)."""


class CudaDriverError(ExportUnavailableError):
    """A CUDA driver call failed, or no CUDA driver is present (``libcuda.so.1``): the export
    path falls back (staging) as for any unavailable export."""


class DescriptorError(ExportError, ValueError):
    """A descriptor is malformed (unknown version or kind, bad field)."""


class ForeignExportError(ExportError, PermissionError):
    """The export belongs to another host or user (by the kernel's credentials), or its memory
    is not sealed against shrinking."""


class ExportBoundsError(ExportError, ValueError):
    """The export's size or offset reaches beyond its block, or the block is not the size the
    descriptor claims (an oversize export)."""


class StaleBufferError(ExportError):
    """The export no longer holds the published bytes: its block was recycled for a later publish
    (or is being recycled right now), or its publisher exited before this process attached to
    its memory."""


class RecycledBufferError(StaleBufferError, BufferOverwrittenError):
    """The export's block was recycled for a later publish (or is being recycled right now):
    the publisher was more than this reader's delivery queue, and the descriptors a reader may
    hold in hand, ahead when the import came. A keep-last reader's transport counts it as a
    dropped message."""
