"""The framework-neutral DLPack producer: a typed, strided, zero-copy view of a message's bytes.

:class:`TensorView` exposes ``__dlpack__`` / ``__dlpack_device__``, so ``torch.from_dlpack``,
``np.from_dlpack`` and ``wp.from_dlpack`` consume the message storage without a copy. It does not
build DLPack structs itself: it derives a typed "carrier" array from a 1-D uint8 array over the
storage and lets the carrier's own, well-tested DLPack export do the work.

- CPU storage: a NumPy ``ndarray`` over the bytes (``byte_offset`` folded into the data pointer);
  bfloat16, which NumPy lacks, uses a Warp array on Warp's ``cpu`` device over the same memory.
- warp storage: a ``wp.array(ptr=..., copy=False)`` over the handle's memory.

Lifetime: the carrier references the storage (NumPy base chain) or the handle lease (attribute on
the Warp array); every DLPack capsule references its carrier, so shape/stride arrays, handles and
memory live as long as the consumer's tensor, independent of the message object.
"""

from __future__ import annotations

import ctypes
from typing import Any

import numpy as np

from .dtypes import DLDataTypeCode, DType
from .errors import InvalidTensorMetadataError, UnsupportedDTypeError
from .metadata import TensorLayout, layout_of
from .storage import HandleLease, backend_of, cpu_bytes, open_read, open_write

__all__ = ["TensorView", "import_warp", "input_view", "output_view", "view_of_bytes", "warp_dtype"]


_WARP: Any = None  # perf: the initialised warp module, so the hot path skips import + wp.init()


def import_warp() -> Any:
    """The ``warp`` module with its runtime initialised (``wp.from_dlpack`` needs it)."""
    global _WARP
    if _WARP is not None:
        return _WARP
    from warp_buffer import init_warp  # quiet start: nothing of Warp's on stdout

    wp = init_warp()
    _WARP = wp
    return wp


_WARP_DTYPES: dict[DType, Any] = {}  # perf: DType -> Warp scalar type, successful lookups only


def warp_dtype(dtype: DType) -> Any:
    """The Warp scalar type of ``dtype`` (bool, ints, uints, float16/32/64, bfloat16).

    Also the rule for warp storage: a dtype without a Warp type (complex) cannot live there, on
    any Warp device, so code that works on Warp's cpu device also works on CUDA.
    """
    found = _WARP_DTYPES.get(dtype)
    if found is not None:
        return found
    wp = import_warp()
    if dtype.code == DLDataTypeCode.COMPLEX:
        raise UnsupportedDTypeError(f"Warp has no complex dtype ({dtype.name})")
    found = getattr(wp, dtype.name, None)
    if found is None:
        raise UnsupportedDTypeError(f"Warp has no dtype {dtype.name}")
    _WARP_DTYPES[dtype] = found
    return found


class TensorView:
    """A zero-copy, DLPack-exporting view of a tensor stored in a message's ``data`` bytes.

    Attributes: ``dtype`` (:class:`DType`), ``shape``, ``strides`` (elements), ``device``
    (``"cpu"`` or a Warp device such as ``"cuda:0"``), ``backend`` (``"cpu"`` or ``"warp"``) and
    ``writable`` (whether the view was opened for writing). Warp has no 0-d arrays: where the
    carrier is a Warp array a scalar is exported with shape ``(1,)``; :meth:`reshape_result`
    restores the true shape on the consumer's tensor.
    """

    __slots__ = ("dtype", "shape", "strides", "device", "backend", "writable", "_carrier", "_lease",
                 "_storage", "_layout")

    def __init__(self, storage: Any, layout: TensorLayout, *, backend: str, writable: bool,
                 lease: HandleLease | None = None) -> None:
        self.dtype = layout.dtype
        self.shape = layout.shape
        self.strides = layout.strides
        self.backend = backend
        self.writable = writable
        self._lease = lease
        self._storage = storage
        self._layout = layout
        if isinstance(storage, np.ndarray):
            self.device = "cpu"
            self._carrier = _numpy_carrier(storage, layout)
        elif warp_dtype(layout.dtype) and str(storage.device) == "cpu" and \
                layout.dtype.code != DLDataTypeCode.BFLOAT:
            # Warp's cpu device is host memory: a NumPy carrier exports versioned, writable
            # DLPack (NumPy imports Warp's legacy capsules read-only).
            self.device = "cpu"
            self._carrier = _numpy_carrier(_host_bytes(storage.ptr, storage.size,
                                                       owner=(storage, lease)), layout)
        else:
            self.device = str(storage.device)
            self._carrier = _warp_carrier(storage.ptr, storage.size, str(storage.device), layout,
                                          owner=(storage, lease))

    @property
    def carrier(self) -> Any:
        """The array whose DLPack export this view forwards (NumPy or Warp)."""
        return self._carrier

    def __dlpack_device__(self) -> tuple[int, int]:
        return self._carrier.__dlpack_device__()

    def __dlpack__(self, *, stream: Any = None, max_version: tuple[int, int] | None = None,
                   dl_device: tuple[int, int] | None = None, copy: bool | None = None) -> Any:
        if isinstance(self._carrier, np.ndarray):
            kwargs: dict[str, Any] = {}
            if stream is not None:
                kwargs["stream"] = stream
            if max_version is not None:
                kwargs["max_version"] = max_version
            if dl_device is not None:
                kwargs["dl_device"] = dl_device
            if copy is not None:
                kwargs["copy"] = copy
            return self._carrier.__dlpack__(**kwargs)
        # Warp's __dlpack__ takes only `stream` and always exports a legacy capsule.
        if dl_device is not None and tuple(dl_device) != tuple(self.__dlpack_device__()):
            raise BufferError(f"cannot export {self.device} memory to DLPack device {dl_device}")
        if copy:
            raise BufferError("this view only exports zero-copy")
        return self._carrier.__dlpack__(stream=stream)

    def atleast_1d(self) -> TensorView:
        """This view, or for a scalar the same element as shape ``(1,)`` (for Warp consumers)."""
        if self.shape:
            return self
        layout = TensorLayout(self.dtype, (1,), (1,), self._layout.byte_offset)
        return TensorView(self._storage, layout, backend=self.backend, writable=self.writable,
                          lease=self._lease)

    def reshape_result(self, tensor: Any) -> Any:
        """Give a consumer's tensor this view's shape (only differs for scalars behind Warp)."""
        if tuple(tensor.shape) != self.shape:
            return tensor.reshape(self.shape)
        return tensor

    def __repr__(self) -> str:
        mode = "writable" if self.writable else "read-only"
        return (f"TensorView({self.dtype.name}, shape={self.shape}, strides={self.strides}, "
                f"device={self.device!r}, backend={self.backend!r}, {mode})")


def _host_bytes(ptr: int | None, nbytes: int, owner: Any) -> np.ndarray:
    """A writable 1-D uint8 NumPy array over host memory at ``ptr`` that keeps ``owner`` alive."""
    if not ptr or nbytes == 0:
        return np.zeros(0, dtype=np.uint8)
    raw = (ctypes.c_uint8 * nbytes).from_address(ptr)
    raw._owner = owner  # type: ignore[attr-defined]
    return np.frombuffer(raw, dtype=np.uint8)


def _numpy_carrier(storage: np.ndarray, layout: TensorLayout) -> Any:
    if layout.dtype.code == DLDataTypeCode.BFLOAT:
        base = storage.ctypes.data if storage.size else 0
        return _warp_carrier(base, storage.size, "cpu", layout, owner=storage)
    if layout.numel == 0:
        return np.empty(layout.shape, dtype=layout.dtype.numpy_dtype())
    return np.ndarray(layout.shape, dtype=layout.dtype.numpy_dtype(), buffer=storage,
                      offset=layout.byte_offset, strides=layout.byte_strides)


def _warp_carrier(base_ptr: int, nbytes: int, device: str, layout: TensorLayout, owner: Any) -> Any:
    wp = import_warp()
    itemsize = layout.dtype.itemsize
    if layout.required_nbytes > nbytes:  # re-checked against the real storage size
        layout.check_fits(nbytes)
    ptr = base_ptr + layout.byte_offset
    if device != "cpu" and ptr % itemsize:
        raise InvalidTensorMetadataError(
            f"byte_offset {layout.byte_offset} leaves {layout.dtype.name} elements misaligned in "
            f"{device} memory; it must be a multiple of {itemsize}")
    shape, strides = layout.shape, layout.byte_strides
    if not shape:  # Warp has no 0-d arrays
        shape, strides = (1,), (itemsize,)
    carrier = wp.array(ptr=ptr if layout.numel else None, dtype=warp_dtype(layout.dtype),
                       shape=shape, strides=strides, device=device, copy=False)
    carrier._tensor_conversions_owner = owner  # keeps the memory / handle alive with the carrier
    return carrier


def view_of_bytes(storage: Any, layout: TensorLayout, *, backend: str, writable: bool,
                  lease: HandleLease | None = None) -> TensorView:
    """A :class:`TensorView` of ``layout`` over 1-D uint8 ``storage`` (NumPy or ``wp.array``)."""
    return TensorView(storage, layout, backend=backend, writable=writable, lease=lease)


def output_view(msg: Any, layout: TensorLayout | None = None) -> TensorView:
    """A writable view of ``msg``'s tensor, for filling the message in place.

    CPU storage: a view of the field's host memory (a borrowed, read-only ``data`` is copied once
    first, copy-on-write). warp storage: opens (or shares) the buffer's single write handle; the
    view's carriers keep it alive, see :mod:`tensor_conversions.storage`.
    """
    if layout is None:  # perf: callers that already validated the layout pass it in
        layout = layout_of(msg)
    if backend_of(msg.data) == "cpu":
        return TensorView(cpu_bytes(msg.data, writable=True), layout, backend="cpu", writable=True)
    lease = open_write(msg)
    return TensorView(lease.array, layout, backend="warp", writable=True, lease=lease)


def input_view(msg: Any, layout: TensorLayout | None = None) -> TensorView:
    """A view of ``msg``'s tensor for reading (aliases the storage: treat it as read-only).

    warp storage: takes a read handle (synchronised with the writer) held by the view's carriers.
    """
    if layout is None:  # perf: callers that already validated the layout pass it in
        layout = layout_of(msg)
    if backend_of(msg.data) == "cpu":
        host = cpu_bytes(msg.data, writable=False)
        return TensorView(host, layout, backend="cpu", writable=False)
    lease = open_read(msg)
    return TensorView(lease.array, layout, backend="warp", writable=False, lease=lease)
