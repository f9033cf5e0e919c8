"""The user API: allocate warp buffers, write and read them through handles, copy into them.

A write looks like::

    buffer = warp_buffer.allocate_buffer(nbytes)
    with warp_buffer.from_output_buffer(buffer) as out:
        wp.launch(my_kernel, dim=n, inputs=[out.view(wp.float32, (n,))], device=out.device)
    msg.data = buffer  # publish

and a read::

    with warp_buffer.from_input_buffer(msg.data) as view:
        wp.launch(consume, dim=n, inputs=[view.view(wp.float32, (n,))], device=view.device)

Handles release on ``with`` exit, on :meth:`release` and on garbage collection. Releasing a write
handle records the write's completion (a CUDA event on its stream; cpu work is synchronous); a
read handle orders its stream after that record. A read handle holds a reader's token of the
buffer (:mod:`warp_buffer.lease`), and so does everything made from it (``array``, ``view()``,
``host_array()``): the bytes stay as they were read until the last of them is gone.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence
from typing import Any

import numpy as np
import warp as wp

from rosidl_buffer import Buffer
from rosidl_buffer.buffer_impl import CpuBufferImpl, array_at

from . import cuda, kernels
from .buffer_impl import WarpBufferImpl, wrap_bytes
from .errors import (
    EmptyBufferError,
    HandleError,
    HandleReleasedError,
    InvalidDTypeError,
    InvalidSizeError,
    SizeMismatchError,
    SizeTypeError,
    UnsupportedSourceError,
    WriteHandleError,
)

__all__ = [
    "allocate_buffer",
    "from_output_buffer",
    "from_input_buffer",
    "to_buffer",
    "WriteHandle",
    "ReadHandle",
]


def allocate_buffer(nbytes: int, device: Any = None) -> Buffer:
    """A new warp-backed :class:`~rosidl_buffer.Buffer` of ``nbytes`` uninitialised bytes.

    ``device`` is a Warp device name (``"cpu"``, ``"cuda:0"``) or ``wp.Device``; None follows
    Warp's default device. Raises :class:`EmptyBufferError` for ``nbytes <= 0`` and
    :class:`DeviceUnavailableError` for a device this machine does not have.
    """
    if isinstance(nbytes, bool) or not isinstance(nbytes, (int, np.integer)):
        raise SizeTypeError(f"nbytes must be an int, got {type(nbytes).__name__}")
    return Buffer(WarpBufferImpl.allocate(int(nbytes), device))


class _KeepAlive:
    """Deleter of a reinterpreting view: holds the base array until the view is collected."""

    __slots__ = ("base",)

    def __init__(self, base: wp.array) -> None:
        self.base = base

    def __call__(self, ptr: int, size: int) -> None:
        self.base = None


def _warp_dtype(dtype: Any) -> Any:
    if dtype is float:
        return wp.float32
    if dtype is int:
        return wp.int32
    if isinstance(dtype, type) and (wp.types.type_is_value(dtype) or hasattr(dtype, "_wp_scalar_type_")):
        return dtype
    try:
        return wp.dtype_from_numpy(np.dtype(dtype))
    except Exception:
        raise InvalidDTypeError(f"{dtype!r} is neither a Warp nor a NumPy data type") from None


_MAX_VIEW_DIMS = 4  # wp.array's limit


def _view_shape(shape: Any) -> tuple[int, ...]:
    """A view's shape: 1 to 4 non-negative whole numbers (2.9 is refused, not truncated)."""
    dims = (shape,) if isinstance(shape, (int, np.integer)) else shape
    try:
        dims = tuple(dims)
    except TypeError:
        raise SizeTypeError(f"shape must be an int or a sequence of ints, got {shape!r}") from None
    if not all(isinstance(d, (int, np.integer)) and not isinstance(d, bool) for d in dims):
        raise SizeTypeError(f"shape must hold whole numbers, got {shape!r}")
    dims = tuple(int(d) for d in dims)
    if any(d < 0 for d in dims):
        raise InvalidSizeError(f"negative dimension in shape {dims}")
    if not 1 <= len(dims) <= _MAX_VIEW_DIMS:
        raise InvalidSizeError(f"a view has 1 to {_MAX_VIEW_DIMS} dimensions (Warp arrays), "
                               f"got shape {dims}")
    return dims


def _check_stream(device: Any, stream: Any) -> Any:
    if device.is_cpu:
        if stream is not None:
            raise HandleError("the cpu device has no streams: pass stream=None")
        return None
    if stream is None:
        return wp.get_stream(device)
    if not isinstance(stream, wp.Stream):
        raise TypeError(f"stream must be a wp.Stream, got {type(stream).__name__}")
    if stream.device != device:
        raise HandleError(f"stream of {stream.device} cannot access a buffer on {device}")
    return stream


class _Handle:
    """What both handles share: the storage as ``wp.array``, views, pointer and lifetime."""

    _kind = "handle"
    _token: Any = None  # a read handle's token: what its arrays and views keep

    def __init__(self, buffer: Buffer, impl: WarpBufferImpl, stream: Any,
                 promoted: Buffer | None) -> None:
        self._buffer = buffer
        self._impl = impl
        self._stream = stream
        self._promoted = promoted
        self._released = False

    def _usable(self) -> WarpBufferImpl:
        if self._released:
            raise HandleReleasedError(f"this {self._kind} handle was released")
        return self._impl

    @property
    def array(self) -> wp.array:
        """The buffer's bytes: a 1-D ``wp.array`` of uint8 on :attr:`device` (no copy)."""
        return self._usable().wp_array

    def view(self, dtype: Any, shape: int | Sequence[int] | None = None) -> wp.array:
        """The bytes reinterpreted as a ``wp.array`` of ``dtype`` and ``shape`` (no copy).

        ``dtype`` is a Warp type (``wp.float32``, ``wp.vec3``) or a NumPy dtype; ``shape``
        defaults to as many elements as the buffer holds. The view may cover less than the
        buffer, never more. It keeps the storage alive for as long as it exists.
        """
        base = self.array
        dtype = _warp_dtype(dtype)
        itemsize = wp.types.type_size_in_bytes(dtype)
        nbytes = base.shape[0]
        if shape is None:
            if nbytes % itemsize:
                raise SizeMismatchError(
                    f"{nbytes} bytes are not a whole number of {itemsize}-byte elements"
                )
            shape = (nbytes // itemsize,)
        else:
            shape = _view_shape(shape)
        need = math.prod(shape) * itemsize
        if need > nbytes:
            raise SizeMismatchError(
                f"a {shape} view of {itemsize}-byte elements needs {need} bytes; "
                f"the buffer has {nbytes}"
            )
        scalar = getattr(dtype, "_wp_scalar_type_", dtype)
        if base.ptr % wp.types.type_size_in_bytes(scalar):
            raise HandleError(f"the buffer's address is not aligned for {dtype}")
        keep = base if self._token is None else (base, self._token)
        return wp.array(ptr=base.ptr, dtype=dtype, shape=shape, device=base.device,
                        deleter=_KeepAlive(keep))

    def host_array(self) -> np.ndarray | None:
        """The bytes as a 1-D uint8 NumPy array over the host memory itself (no copy) that keeps
        this handle, and so the storage and a read handle's token, alive; None when the storage
        is device memory.

        What a host consumer (NumPy, or torch on cpu) needs, without a ``wp.array``: about 1 us
        against about 10 for :attr:`array`, per frame. Its flags say writable (legacy DLPack
        cannot carry read-only): an imported buffer's memory is mapped read-only, so treat it
        as such.
        """
        impl = self._usable()
        host = impl.host
        if host is None:
            return None
        return array_at(impl.data_ptr or host.ctypes.data, host.size, self)

    @property
    def ptr(self) -> int:
        """Address of the first byte (device address on CUDA)."""
        return self.array.ptr

    @property
    def device(self) -> str:
        """Warp device name of the storage, e.g. ``"cpu"`` or ``"cuda:0"``."""
        return self._impl.device

    @property
    def stream(self) -> Any:
        """The CUDA stream the handle orders its work on (None on cpu)."""
        return self._stream

    @property
    def buffer(self) -> Buffer:
        """The warp buffer this handle accesses (the promoted one, if promotion happened)."""
        return self._buffer

    def get_promoted_buffer(self) -> Buffer | None:
        """The warp buffer allocated because a non-warp buffer was passed, else None."""
        return self._promoted

    def release(self) -> None:
        """End access (idempotent). Also runs on ``with`` exit and garbage collection."""
        if not self._released:
            self._released = True
            self._on_release()

    def _on_release(self) -> None:
        pass

    def _on_collect(self) -> None:
        """What release does, from a finalizer: no lock taken (it may run anywhere)."""

    def __enter__(self) -> Any:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    def __del__(self) -> None:
        if sys.is_finalizing() or self._released:
            return
        self._released = True
        try:
            self._on_collect()
        except Exception:  # pragma: no cover - interpreter shutdown
            pass

    def __repr__(self) -> str:
        state = "released" if self._released else "open"
        return f"{type(self).__name__}({self._impl!r}, {state})"


class WriteHandle(_Handle):
    """Write access to a warp buffer (one per buffer, ever). See :func:`from_output_buffer`."""

    _kind = "write"

    def __init__(self, buffer: Buffer, impl: WarpBufferImpl, stream: Any,
                 promoted: Buffer | None, explicit: Any = None) -> None:
        self._released = True  # a refused handle has nothing to release
        # The write's completion is recorded on the stream the user named, else on the current
        # streams when it ends (Warp's joined with torch's: cuda.write_stream).
        self._state = impl.open_writer(explicit)
        super().__init__(buffer, impl, stream, promoted)

    def _usable(self) -> WarpBufferImpl:
        impl = super()._usable()
        if self._state.sealed is not None:
            raise WriteHandleError(
                f"the buffer was {self._state.sealed} while this write handle was open; "
                "writes after that are not allowed"
            )
        return impl

    def _on_release(self) -> None:
        self._impl.close_writer(self._state)

    def _on_collect(self) -> None:
        self._impl.lease.end_write_quietly(self._state)  # type: ignore[union-attr]


class ReadHandle(_Handle):
    """Read access to a warp buffer, ordered after its writer. See :func:`from_input_buffer`.

    It holds a reader's token, and so do its ``array``, its views and its ``host_array()``:
    the bytes are not rewritten (a loan re-armed) nor an import's hold dropped while any of
    them lives. Releasing it records the read's last use on its stream (CUDA): the block is
    not reused, nor an import's hold dropped, before the reads queued so far completed."""

    _kind = "read"
    _arr: wp.array | None = None

    def __init__(self, buffer: Buffer, impl: WarpBufferImpl, stream: Any,
                 promoted: Buffer | None, explicit: Any = None) -> None:
        super().__init__(buffer, impl, stream, promoted)
        self._explicit = explicit  # the stream the user named (None: the current ones)
        self._token = impl.reader_token()

    @property
    def array(self) -> wp.array:
        """The buffer's bytes: a 1-D ``wp.array`` of uint8 on :attr:`device` (no copy), which
        holds this handle's token."""
        impl = self._usable()
        lease = impl.lease
        if lease is None or not lease.rearmable:
            return impl.wp_array  # the import's own array holds its token; a plain buffer's,
        array = self._arr  # its lease
        if array is None:
            array = self._arr = wrap_bytes(impl.wp_array.ptr, impl.size(), impl.wp_device,
                                           self._token)
        return array

    def _on_release(self) -> None:
        impl = self._impl
        if not impl.wp_device.is_cpu:
            impl.record_use(cuda.write_stream(impl.wp_device, self._explicit))

    def _on_collect(self) -> None:
        impl = self._impl
        if not impl.wp_device.is_cpu:  # recorded without a lock (cuda.note_use)
            cuda.note_use(impl.block if impl.block is not None else impl,
                          cuda.write_stream(impl.wp_device, self._explicit))


def _require_buffer(buffer: Any) -> Buffer:
    if not isinstance(buffer, Buffer):
        raise UnsupportedSourceError(
            f"expected a rosidl_buffer.Buffer, got {type(buffer).__name__} (to_buffer makes one)")
    return buffer


def from_output_buffer(buffer: Buffer, stream: Any = None) -> WriteHandle:
    """A write handle on ``buffer``; use it as a context manager.

    A warp buffer takes one write handle in its life, and none once published or read (each
    raises :class:`WriteHandleError`). A buffer of another backend (CPU) is promoted: a new
    warp buffer of the same byte size is allocated, without copying, on the device of
    ``stream`` or Warp's default device, and is returned by :meth:`get_promoted_buffer`.
    Writes are ordered on ``stream`` (CUDA; default: the device's current stream).
    """
    buffer = _require_buffer(buffer)
    impl = buffer.get_impl()
    promoted = None
    if not isinstance(impl, WarpBufferImpl):
        if buffer.nbytes <= 0:
            raise EmptyBufferError("cannot write into an empty buffer: warp buffers hold >= 1 byte")
        device = stream.device if stream is not None else None
        promoted = allocate_buffer(buffer.nbytes, device)
        buffer, impl = promoted, promoted.get_impl()
    explicit = stream
    stream = _check_stream(impl.wp_device, stream)
    return WriteHandle(buffer, impl, stream, promoted, explicit)


def from_input_buffer(buffer: Buffer, stream: Any = None) -> ReadHandle:
    """A read handle on ``buffer``, ordered after the buffer's write.

    On CUDA the handle's ``stream`` waits on the writer's event (an interprocess event for an
    import); on cpu the write is complete once its handle was released. Reading ends the buffer's
    writable life (an open write handle is sealed). A buffer of another backend is promoted by
    copying it into a new warp buffer (kept by :meth:`get_promoted_buffer`).
    """
    buffer = _require_buffer(buffer)
    impl = buffer.get_impl()
    promoted = None
    if not isinstance(impl, WarpBufferImpl):
        if buffer.nbytes <= 0:
            raise EmptyBufferError("cannot read an empty buffer as a warp buffer")
        host = impl.view() if isinstance(impl, CpuBufferImpl) else buffer.to_numpy()
        device = stream.device if stream is not None else None
        promoted = allocate_buffer(buffer.nbytes, device)
        new_impl = promoted.get_impl()
        _copy_into(new_impl, _as_bytes(host), _check_stream(new_impl.wp_device, stream))
        buffer, impl = promoted, new_impl
    explicit = stream
    stream = _check_stream(impl.wp_device, stream)
    impl.mark_read()
    impl.wait_for_writer(stream)
    return ReadHandle(buffer, impl, stream, promoted, explicit)


def _as_bytes(src: Any) -> np.ndarray | wp.array:
    """``src`` as contiguous bytes without copying when possible: a 1-D uint8 NumPy array (host)
    or a 1-D uint8 ``wp.array`` (any device; keeps ``src`` alive)."""
    if isinstance(src, Buffer):
        impl = src.get_impl()
        if isinstance(impl, WarpBufferImpl):
            return impl.wp_array
        return np.ascontiguousarray(impl.view() if isinstance(impl, CpuBufferImpl)
                                    else src.to_numpy()).view(np.uint8).reshape(-1)
    if isinstance(src, _Handle):
        raise UnsupportedSourceError(
            f"to_buffer copies data, not a {type(src).__name__}: pass its buffer or its array")
    if isinstance(src, (str, list, tuple)):
        raise UnsupportedSourceError(
            f"to_buffer takes array data (a wp.array, a DLPack tensor, a NumPy array, bytes or a "
            f"Buffer), not a {type(src).__name__}; wrap a sequence in np.asarray first")
    if isinstance(src, memoryview) and not src.c_contiguous:
        return np.ascontiguousarray(np.asarray(src)).reshape(-1).view(np.uint8)  # one copy
    if isinstance(src, (bytes, bytearray, memoryview)):
        return np.frombuffer(src, dtype=np.uint8)
    if isinstance(src, np.ndarray):
        if src.dtype.hasobject:
            raise UnsupportedSourceError(
                f"to_buffer copies array data, not an array of Python objects ({src.dtype})")
        return np.ascontiguousarray(src).reshape(-1).view(np.uint8)
    if isinstance(src, wp.array):
        array = src
    elif hasattr(src, "__dlpack__"):
        if hasattr(src, "is_contiguous") and hasattr(src, "contiguous") and not src.is_contiguous():
            src = src.contiguous()  # torch and friends: a strided view becomes one copy
        try:
            array = wp.from_dlpack(src)
        except Exception:
            try:
                return np.ascontiguousarray(np.from_dlpack(src)).reshape(-1).view(np.uint8)
            except Exception as exc:
                raise UnsupportedSourceError(
                    f"cannot read {type(src).__name__} through DLPack: {exc}") from None
    else:
        raise UnsupportedSourceError(
            f"to_buffer takes a wp.array, a DLPack-capable tensor, a NumPy array, bytes or a "
            f"Buffer, not {type(src).__name__}"
        )
    if not array.is_contiguous:
        array = array.contiguous()
    nbytes = array.size * wp.types.type_size_in_bytes(array.dtype)
    if array.dtype == wp.uint8 and array.ndim == 1:
        return array
    return wrap_bytes(array.ptr, nbytes, array.device, _KeepAlive(array))


def _order_after_source(src: Any, stream: Any) -> None:
    """``wp.from_dlpack`` (and a ``wp.array`` written by Warp) orders only the source device's
    *current* stream after the producer's writes: a copy on another stream waits for it."""
    if isinstance(src, wp.array) and src.device.is_cuda:
        current = src.device.stream
        if stream.cuda_stream != current.cuda_stream:
            stream.wait_stream(current)


def _copy_into(impl: WarpBufferImpl, src: np.ndarray | wp.array, stream: Any) -> Any:
    """Copy ``src`` into ``impl``; returns the CUDA stream the copy ran on (None: it is done)."""
    dst = impl.wp_array
    nbytes = src.shape[0] if isinstance(src, np.ndarray) else src.shape[0]
    if nbytes != dst.shape[0]:
        raise SizeMismatchError(
            f"source has {nbytes} bytes, the destination buffer {dst.shape[0]}"
        )
    if impl.host is not None:  # cpu: a plain host copy runs at memory speed
        if isinstance(src, wp.array):
            if src.device.is_cpu:
                src = src.numpy()
            else:  # device to host: done when we return; wait for this copy only
                copy_stream = cuda.write_stream(src.device)
                wp.copy(dst, src, stream=copy_stream)
                wp.synchronize_event(copy_stream.record_event())
                return None
        np.copyto(impl.host, src)
        return None
    stream = cuda.write_stream(impl.wp_device, stream)  # the stream the copy (the write) runs on
    if isinstance(src, np.ndarray):
        src = wp.array(ptr=src.ctypes.data, dtype=wp.uint8, shape=(nbytes,), device="cpu",
                       deleter=_KeepAlive(src))  # type: ignore[arg-type]
    else:
        _order_after_source(src, stream)
    if src.device == dst.device:
        kernels.copy_bytes(dst, src, stream)
    else:
        wp.copy(dst, src, stream=stream)
    impl.complete_write(stream)
    return stream


def to_buffer(src: Any, write_handle: WriteHandle, stream: Any = None) -> None:
    """Copy ``src`` (a ``wp.array``, a torch tensor or anything with ``__dlpack__``, a NumPy
    array, bytes, or a Buffer) into the storage of ``write_handle``.

    The byte sizes must match exactly (:class:`SizeMismatchError` otherwise). Anything else (a
    list, a str, a read handle) raises :class:`UnsupportedSourceError` (a ``TypeError``). A copy
    into cpu memory is a plain host copy; one between CUDA buffers runs the copy kernel; a
    cross-device one (host to GPU) is a Warp copy on ``stream`` (default: the handle's stream).
    """
    if not isinstance(write_handle, WriteHandle):
        raise UnsupportedSourceError(
            f"to_buffer copies into a WriteHandle, got {type(write_handle).__name__}")
    impl = write_handle._usable()
    state = write_handle._state
    if stream is not None:
        _check_stream(impl.wp_device, stream)
    copied_on = _copy_into(impl, _as_bytes(src), stream if stream is not None else state.stream)
    if copied_on is not None:
        # The write ends with an event on the handle's stream: order it after this copy when
        # the copy ran elsewhere (an explicit stream), device-side.
        writes = cuda.write_stream(impl.wp_device, state.stream)
        if writes.cuda_stream != copied_on.cuda_stream:
            writes.wait_stream(copied_on)
