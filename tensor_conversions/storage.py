"""Where a message's bytes live: allocating a ``uint8[]`` field and opening it to read or write.

Two backends: ``"cpu"`` (the ordinary host ``uint8[]``) and ``"warp"`` (Warp device memory from
the ``warp_buffer`` package, on any Warp device, ``"cpu"`` included). A request that cannot be
served raises :class:`UnsupportedBackendError`; storage is never silently put elsewhere.

A warp buffer takes ONE write handle in its life, so writable views of one message share it.
Views hold warp_buffer's handles directly (a handle releases itself when collected). The message
remembers it weakly in its ``_native`` slot, in its one state object (:class:`NativeState`, no
registry keyed by ``id()``), which also carries a loaned message's loan (:mod:`.loan`): while
any view over the handle lives, later views (and ``to_tensor_msg``) reuse it; the handle is
released (the write is complete) when the last view is collected, at publish (the transport
seals the buffer), or earlier through :func:`release_output`. Read views hold a reader's token
of the storage (a read handle's, or the storage's own, see :mod:`warp_buffer.lease`).

Streams: handles are opened on the stream the framework will run on (torch's current stream,
Warp's, CuPy's), so the writer's completion is recorded on the stream that really wrote, and a
reader's stream waits for it; nothing waits for the whole device.
"""

from __future__ import annotations

import threading
import weakref
from typing import Any

import numpy as np

from rosidl_buffer import Buffer, CpuBufferImpl
from rosidl_buffer.messages import Message

from .errors import (InvalidTensorMetadataError, StorageNotWritableError, UnsupportedBackendError,
                     WrongMessageTypeError)

__all__ = [
    "BACKENDS",
    "NativeState",
    "allocate_data",
    "backend_of",
    "host_bytes",
    "live_write_handle",
    "open_read",
    "open_write",
    "release_output",
    "resolve_warp_device",
    "storage_device",
]

BACKENDS = ("cpu", "warp")


def _warp_buffer() -> Any:
    try:
        import warp_buffer
    except ImportError as exc:  # pragma: no cover - warp_buffer ships with this project
        raise UnsupportedBackendError(
            f"the 'warp' backend needs the warp_buffer package: {exc}") from exc
    return warp_buffer


def resolve_warp_device(device: Any = None) -> str:
    """The Warp device string (``"cpu"``, ``"cuda:0"``) for ``device``; None = Warp's default."""
    from warp_buffer.buffer_impl import resolve_device
    from warp_buffer.errors import DeviceUnavailableError

    try:
        return str(resolve_device(device))
    except DeviceUnavailableError as exc:  # this package's type for a device it cannot serve
        raise UnsupportedBackendError(str(exc)) from None


def allocate_data(nbytes: int, backend: str = "cpu", device: Any = None) -> Buffer:
    """A ``data`` buffer of ``nbytes`` in ``backend`` (on ``device`` for warp); cpu is zeroed."""
    if backend == "cpu":
        if device is not None and str(device) != "cpu":
            raise UnsupportedBackendError(
                f"backend 'cpu' stores host memory; device {device!r} cannot be served "
                "(use backend='warp' for device memory)")
        try:
            return Buffer(_aligned_zeros(nbytes))
        except (ValueError, OverflowError) as exc:  # past what NumPy can index
            raise InvalidTensorMetadataError(
                f"a tensor of {nbytes} bytes cannot be held in host memory: {exc}") from None
    if backend == "warp":
        resolved = resolve_warp_device(device)
        if nbytes <= 0:
            raise UnsupportedBackendError(
                "the 'warp' backend cannot hold an empty image or point cloud (warp buffers are "
                "never empty, and their data must be exactly step * height bytes); use "
                "backend='cpu' for zero-size ones")
        return _warp_buffer().allocate_buffer(nbytes, device=resolved)
    raise UnsupportedBackendError(f"unknown backend {backend!r}; supported: {', '.join(BACKENDS)}")


_ALIGN = 64  # cache line; what JAX and SIMD kernels want to import host memory without a copy


def _aligned_zeros(nbytes: int) -> np.ndarray:
    raw = np.zeros(nbytes + _ALIGN, dtype=np.uint8)
    start = -raw.ctypes.data % _ALIGN
    return raw[start:start + nbytes]


def backend_of(buffer: Buffer) -> str:
    """``"cpu"`` or ``"warp"``; any other backend raises :class:`UnsupportedBackendError`."""
    backend = buffer.get_backend_type()
    if backend not in BACKENDS:
        raise UnsupportedBackendError(
            f"message data uses backend {backend!r}; tensor_conversions supports "
            f"{', '.join(BACKENDS)}")
    return backend


def storage_device(buffer: Buffer) -> str:
    """The device of a message's storage: ``"cpu"`` for host memory, else the Warp device."""
    if backend_of(buffer) == "cpu":
        return "cpu"
    return str(buffer.get_impl().device)


def host_bytes(buffer: Buffer, *, writable: bool) -> np.ndarray:
    """The bytes of a CPU buffer as a 1-D uint8 array, no copy (except copy-on-write of borrowed
    bytes when ``writable``). Read-only bytes stay read-only: DLPack 1.x carries the flag."""
    impl = buffer.get_impl()
    if not isinstance(impl, CpuBufferImpl):
        raise UnsupportedBackendError(f"expected CPU storage, got {buffer.get_backend_type()!r}")
    return impl.writable_view() if writable else impl.view()


# -------------------------------------------------------------------------------------- warp
class NativeState:
    """What tensor_conversions keeps on a message (its ``_native`` slot, one type): the write
    handle of ``buffer``, weakly, and a loaned message's loan (:class:`.loan.LoanState`, None
    otherwise). Dropped by deepcopy and pickling (handles belong to one message, a copy is not
    loaned)."""

    __slots__ = ("buffer", "write", "loan")

    def __init__(self, loan: Any = None) -> None:
        self.buffer: Buffer | None = None
        self.write: weakref.ref[Any] | None = None
        self.loan = loan

    def __deepcopy__(self, memo: dict[int, Any]) -> NativeState:
        return NativeState()

    def __reduce__(self) -> tuple[Any, ...]:
        return (NativeState, ())


_lock = threading.Lock()


def _state(msg: Any) -> NativeState:
    state = getattr(msg, "_native", None)
    if type(state) is not NativeState:
        state = NativeState()
        object.__setattr__(msg, "_native", state)
    return state


def live_write_handle(msg: Any) -> Any:
    """The write handle that views of ``msg.data`` hold now, if any (and still usable)."""
    state = getattr(msg, "_native", None)
    if type(state) is not NativeState or state.write is None or state.buffer is not msg.data:
        return None
    handle = state.write()
    if handle is None:
        return None
    try:
        handle.array  # released or sealed (published, read) handles refuse access: spent
    except Exception:
        return None
    return handle


def open_write(msg: Any, stream: Any = None, *, replace_if_spent: bool = False) -> Any:
    """The write handle of ``msg.data`` (warp storage): the live one, or a new write handle on
    ``stream`` (a ``wp.Stream``; None = Warp's current stream of the device).

    ``replace_if_spent``: if the buffer has used its one write handle (written, read or
    published), give ``msg.data`` a fresh warp buffer of the same size and device instead of
    failing (``to_tensor_msg`` rewrites all of it).
    """
    with _lock:
        handle = live_write_handle(msg)
        if handle is not None:
            return handle
        buffer = msg.data
        wb = _warp_buffer()
        try:
            handle = wb.from_output_buffer(buffer, stream)
        except wb.errors.WriteHandleError as exc:
            if not replace_if_spent:
                raise StorageNotWritableError(
                    f"cannot write this warp-backed message: {exc}. A warp buffer takes one write "
                    "in its life; use to_tensor_msg (which gives the message a fresh buffer) or "
                    "allocate a new message") from exc
            buffer = wb.allocate_buffer(buffer.size(), device=str(buffer.get_impl().device))
            msg.data = buffer
            handle = wb.from_output_buffer(buffer, stream)
        state = _state(msg)
        state.buffer, state.write = buffer, weakref.ref(handle)
        return handle


def open_read(msg: Any, stream: Any = None) -> Any:
    """A read handle on ``msg.data`` (warp storage); ``stream`` (None = Warp's current stream)
    is ordered after the writer by warp_buffer. Our own unpublished write is read through its
    write handle."""
    live = live_write_handle(msg)
    if live is not None:
        return live
    return _warp_buffer().from_input_buffer(msg.data, stream)


def release_output(msg: Any) -> bool:
    """Release the write handle held by writable views of ``msg`` (warp storage) now.

    Returns True if a handle was released. Views created earlier must not be written afterwards.
    For CPU storage there is nothing to release (returns False); anything but a message is
    :class:`WrongMessageTypeError`.
    """
    if not isinstance(msg, Message):
        raise WrongMessageTypeError(f"release_output takes a message, not {type(msg).__name__}")
    with _lock:
        handle = live_write_handle(msg)
        if handle is None:
            return False
        handle.release()
        return True
