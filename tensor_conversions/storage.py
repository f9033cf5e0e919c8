"""Where a tensor message's bytes live: allocating ``data`` and opening it for reading or writing.

Two backends: ``"cpu"`` (the ordinary host ``uint8[]``) and ``"warp"`` (Warp device memory from
the ``warp_buffer`` package, on any Warp device, ``"cpu"`` included). A request that cannot be
served raises :class:`UnsupportedBackendError`; storage is never silently put elsewhere.

Warp buffers accept ONE write handle in their life. Writable views therefore share a
:class:`HandleLease` per buffer: while any view over it lives, later views (and
``to_tensor_msg``) reuse the same write handle; the handle is released (the write is complete)
when the last such view is garbage-collected, or earlier through :func:`release_output`.
"""

from __future__ import annotations

import ctypes
import threading
import weakref
from typing import Any

import numpy as np

from rosidl_buffer import Buffer, CpuBufferImpl

from .errors import TensorConversionError, UnsupportedBackendError

__all__ = [
    "BACKENDS",
    "HandleLease",
    "allocate_data",
    "backend_of",
    "cpu_bytes",
    "live_write_lease",
    "open_read",
    "open_write",
    "release_output",
    "release_read_lease",
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
    if not hasattr(warp_buffer, "allocate_buffer"):  # pragma: no cover - incomplete install
        raise UnsupportedBackendError("the installed warp_buffer package has no allocate_buffer")
    return warp_buffer


def resolve_warp_device(device: Any = None) -> str:
    """The Warp device string (``"cpu"``, ``"cuda:0"``) for ``device``; None = Warp's default."""
    from .dlpack import import_warp

    wp = import_warp()
    try:
        return str(wp.get_device(device))
    except Exception as exc:  # Warp raises RuntimeError/ValueError for unknown or absent devices
        raise UnsupportedBackendError(f"Warp device {device!r} is not available: {exc}") from None


def allocate_data(nbytes: int, backend: str = "cpu", device: Any = None) -> Buffer:
    """A zero-filled ``data`` buffer of ``nbytes`` in ``backend`` (on ``device`` for warp)."""
    if backend == "cpu":
        if device is not None and str(device) != "cpu":
            raise UnsupportedBackendError(
                f"backend 'cpu' stores host memory; device {device!r} cannot be served "
                "(use backend='warp' for device memory)")
        return Buffer(np.zeros(nbytes, dtype=np.uint8))
    if backend == "warp":
        resolved = resolve_warp_device(device)
        if nbytes <= 0:
            raise UnsupportedBackendError(
                "the 'warp' backend cannot hold an empty tensor (warp buffers are never empty); "
                "use backend='cpu' for zero-size tensors")
        return _warp_buffer().allocate_buffer(nbytes, device=resolved)
    raise UnsupportedBackendError(f"unknown backend {backend!r}; supported: {', '.join(BACKENDS)}")


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


# --------------------------------------------------------------------------------------- CPU
def _writable_alias(array: np.ndarray) -> np.ndarray:
    """A writable alias of read-only bytes (borrowed from a received message), keeping them alive.

    DLPack's legacy protocol cannot flag read-only memory, so a read-only view needs a writable
    carrier; callers hand it out only as a read-only view (documented aliasing contract).
    """
    if array.flags.writeable or array.size == 0:
        return array if array.flags.writeable else np.zeros(0, dtype=np.uint8)
    raw = (ctypes.c_uint8 * array.nbytes).from_address(array.ctypes.data)
    raw._owner = array  # type: ignore[attr-defined]  # keeps the borrowed bytes alive
    return np.frombuffer(raw, dtype=np.uint8)


def cpu_bytes(buffer: Buffer, *, writable: bool) -> np.ndarray:
    """The host bytes of a CPU buffer as a 1-D uint8 array (no copy except copy-on-write)."""
    impl = buffer.get_impl()
    if not isinstance(impl, CpuBufferImpl):
        raise UnsupportedBackendError(f"expected CPU storage, got {buffer.get_backend_type()!r}")
    if writable:
        return impl.writable_view()
    return _writable_alias(impl.view())


# -------------------------------------------------------------------------------------- warp
def _release_quietly(handle: Any) -> None:
    try:
        handle.release()
    except Exception:  # already released, or the interpreter is shutting down
        pass


class HandleLease:
    """Owns one warp_buffer read or write handle; releases it when the lease is collected.

    Every carrier handed to a framework references the lease, so the handle lives exactly as long
    as the last tensor that can touch the memory.
    """

    __slots__ = ("handle", "buffer", "_finalizer", "__weakref__")

    def __init__(self, handle: Any, buffer: Buffer) -> None:
        self.handle = handle
        self.buffer = buffer
        self._finalizer = weakref.finalize(self, _release_quietly, handle)

    @property
    def array(self) -> Any:
        return self.handle.array

    def release(self) -> None:
        self._finalizer()


_write_leases: weakref.WeakValueDictionary[int, HandleLease] = weakref.WeakValueDictionary()
_lock = threading.Lock()


def live_write_lease(impl: Any) -> HandleLease | None:
    """The write lease currently held by views of the storage ``impl``, if any."""
    lease = _write_leases.get(id(impl))
    if lease is not None and lease.buffer.get_impl() is impl and lease._finalizer.alive:
        return lease
    return None


def release_read_lease(lease: HandleLease | None) -> None:
    """Release a lease taken by :func:`open_read`, unless it is a shared write lease."""
    if lease is None:
        return
    with _lock:
        shared = live_write_lease(lease.buffer.get_impl()) is lease
    if not shared:
        lease.release()


def open_write(msg: Any, *, replace_if_spent: bool = False) -> HandleLease:
    """The write lease of ``msg.data`` (warp storage): the live one, or a new write handle.

    ``replace_if_spent``: if the buffer has already used its one write handle (written and
    released, read or published), give ``msg.data`` a fresh warp buffer of the same size on the
    same device instead of failing (used by ``to_tensor_msg``, which rewrites all of it).
    """
    buffer = msg.data
    impl = buffer.get_impl()
    with _lock:
        lease = live_write_lease(impl)
        if lease is not None:
            return lease
        wb = _warp_buffer()
        try:
            handle = wb.from_output_buffer(buffer)
        except wb.errors.WriteHandleError as exc:
            if not replace_if_spent:
                raise TensorConversionError(
                    f"cannot write this warp-backed message: {exc}. A warp buffer takes one write "
                    "in its life; use to_tensor_msg (which gives the message a fresh buffer) or "
                    "allocate a new message") from exc
            buffer = wb.allocate_buffer(buffer.size(), device=str(impl.device))
            msg.data = buffer
            impl = buffer.get_impl()
            handle = wb.from_output_buffer(buffer)
        lease = HandleLease(handle, buffer)
        _write_leases[id(impl)] = lease
        return lease


def release_output(msg: Any) -> bool:
    """Release the write handle held by writable views of ``msg`` (warp storage) now.

    Returns True if a handle was released. Views created earlier must not be written afterwards.
    For CPU storage there is nothing to release (returns False).
    """
    if msg.data.get_backend_type() != "warp":
        return False
    with _lock:
        lease = live_write_lease(msg.data.get_impl())
        if lease is None:
            return False
        lease.release()
        return True


def open_read(msg: Any) -> HandleLease:
    """A read lease on ``msg.data`` (warp storage), synchronised with the writer by warp_buffer."""
    buffer = msg.data
    with _lock:
        live = live_write_lease(buffer.get_impl())
    if live is not None:
        # Reading our own unpublished write: the data is ours, reuse the write handle.
        return live
    handle = _warp_buffer().from_input_buffer(buffer)
    return HandleLease(handle, buffer)
