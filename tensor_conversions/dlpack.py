"""The framework-neutral core: a zero-copy DLPack view of a tensor in a message's bytes.

:class:`TensorView` does not build DLPack structs. It lays a typed "carrier" array over the
storage and forwards ``__dlpack__`` to it, so NumPy's and Warp's own, well-tested exports carry
dtype, shape, strides, device and ownership:

- host memory (CPU storage, or warp storage on Warp's ``cpu`` device): a NumPy ``ndarray``
  (``byte_offset`` folded into the data pointer; read-only bytes stay read-only, which DLPack 1.x
  signals); bfloat16, which NumPy lacks, uses a Warp array over the same memory;
- device memory: a ``wp.array(ptr=..., copy=False)`` over the handle's memory.

What DLPack cannot say is the stream. The handle behind a device view is opened on the stream
the framework module will use; a consumer that passes another stream to ``__dlpack__`` has that
stream wait for the handle's stream (an event, never a device synchronisation).

Lifetime: the carrier references the storage (NumPy base chain) or the warp_buffer handle (attribute
on the Warp array); every DLPack capsule references its carrier, so memory, handles and the
reader's token a read handle holds (:mod:`warp_buffer.lease`) live as long as the consumer's
tensor, independent of the message object.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from rosidl_buffer.buffer_impl import array_at

from .dtypes import DLDataTypeCode, DType, dtype_from_name
from .errors import InvalidTensorMetadataError, UnsupportedDTypeError
from .metadata import TensorLayout, layout_of
from .storage import backend_of, host_bytes, open_read, open_write

__all__ = ["TensorView", "external_stream", "host_alias", "import_warp", "input_view", "output_view", "view_of", "warp_dtype"]


_WARP: Any = None  # the initialised warp module, so the hot path skips import + wp.init()
MAX_WARP_DIMS = 4  # wp.array's limits: dimensions, and elements per dimension (int32)
MAX_WARP_DIM = 2**31 - 1
_UINT8 = dtype_from_name("uint8")


def import_warp() -> Any:
    """The ``warp`` module with its runtime initialised."""
    global _WARP
    if _WARP is None:
        from warp_buffer import init_warp  # quiet start: nothing of Warp's on stdout

        _WARP = init_warp()
    return _WARP


_WARP_DTYPES: dict[DType, Any] = {}


def warp_dtype(dtype: DType) -> Any:
    """The Warp scalar type of ``dtype`` (bool, ints, uints, float16/32/64, bfloat16).

    Also the rule for warp storage: a dtype without a Warp type (complex) cannot live there, on
    any Warp device, so code that works on Warp's cpu device also works on CUDA.
    """
    found = _WARP_DTYPES.get(dtype)
    if found is None:
        wp = import_warp()
        found = None if dtype.code == DLDataTypeCode.COMPLEX else getattr(wp, dtype.name, None)
        if found is None:
            raise UnsupportedDTypeError(f"Warp has no dtype {dtype.name}")
        _WARP_DTYPES[dtype] = found
    return found


class TensorView:
    """A zero-copy, DLPack-exporting view of a tensor stored in a message's bytes.

    Attributes: ``layout`` (:class:`TensorLayout`), ``device`` (``"cpu"`` or a Warp device such
    as ``"cuda:0"``), ``writable``, ``carrier`` (the NumPy or Warp array forwarded to DLPack) and
    ``handle`` (the warp_buffer read or write handle it holds, or None). A Warp carrier cannot be 0-d: a scalar
    is carried with shape ``(1,)`` and :meth:`reshape_result` restores ``()``.
    """

    __slots__ = ("layout", "device", "writable", "handle", "_storage", "_carrier")

    def __init__(self, storage: Any, layout: TensorLayout, *, writable: bool,
                 handle: Any = None) -> None:
        self.layout = layout
        self.writable = writable
        self.handle = handle
        self._storage = storage  # 1-D uint8: NumPy (host memory) or wp.array (device memory)
        self._carrier: Any = None  # built on first use: a Warp consumer may never need NumPy's
        if type(storage) is np.ndarray:
            self.device = "cpu"  # CPU storage, or warp storage on Warp's cpu device
        else:
            self.device = str(storage.device)
            if len(layout.shape) <= MAX_WARP_DIMS:
                self._carrier = _warp_carrier(storage.ptr, storage.size, self.device, layout,
                                              owner=(storage, handle))
            else:  # no Warp array of it: a consumer may lay it over the bytes (byte_view)
                layout.check_fits(storage.size)

    @property
    def carrier(self) -> Any:
        """The NumPy (host memory; Warp for bfloat16) or Warp (device memory) array forwarded to
        DLPack."""
        carrier = self._carrier
        if carrier is None:
            storage = self._storage
            if type(storage) is np.ndarray:
                carrier = _host_carrier(storage, self.layout, storage)
            else:  # device memory of more than 4 dimensions: the typed refusal
                carrier = _warp_carrier(storage.ptr, storage.size, self.device, self.layout,
                                        owner=(storage, self.handle))
            self._carrier = carrier
        return carrier

    def warp_array(self) -> Any:
        """This view as a ``wp.array`` (a scalar as shape ``(1,)``), zero-copy, built from the
        storage's pointer: Warp's DLPack import refuses read-only arrays and costs ~10 us."""
        carrier = self._carrier
        if carrier is not None and type(carrier) is not np.ndarray:
            return carrier
        storage = self._storage
        if type(storage) is not np.ndarray:  # device memory Warp cannot carry: refused, typed
            return self.carrier
        base = storage.ctypes.data if storage.size else 0
        return _warp_carrier(base, storage.size, "cpu", self.layout, owner=storage)

    @property
    def warp_carried(self) -> bool:
        """Whether the carrier is a Warp array (at most 4 dimensions): device memory, and
        bfloat16 in host memory (NumPy has no bfloat16)."""
        return (type(self._storage) is not np.ndarray
                or self.layout.dtype.code == DLDataTypeCode.BFLOAT)

    def byte_view(self) -> TensorView:
        """The whole storage as a 1-D uint8 view (same memory, handle and writability), for a
        consumer that lays the tensor over the bytes itself: Warp's arrays, the carrier of
        device memory and of bfloat16, have at most 4 dimensions."""
        storage = self._storage
        return TensorView(storage, TensorLayout.contiguous(_UINT8, (storage.size,)),
                          writable=self.writable, handle=self.handle)

    @property
    def dtype(self) -> DType:
        """Element type of the tensor (its layout's)."""
        return self.layout.dtype

    @property
    def shape(self) -> tuple[int, ...]:
        """Dimensions of the tensor as the message describes them (``()`` for a scalar, even
        when the carrier is ``(1,)``)."""
        return self.layout.shape

    def __dlpack_device__(self) -> tuple[int, int]:
        return self.carrier.__dlpack_device__()

    def __dlpack__(self, *, stream: Any = None, max_version: tuple[int, int] | None = None,
                   dl_device: tuple[int, int] | None = None, copy: bool | None = None) -> Any:
        carrier = self.carrier
        if type(carrier) is np.ndarray:
            kwargs: dict[str, Any] = {}
            if max_version is not None:
                kwargs["max_version"] = max_version
            if dl_device is not None:
                kwargs["dl_device"] = dl_device
            if copy is not None:
                kwargs["copy"] = copy
            return carrier.__dlpack__(**kwargs)
        # Warp's __dlpack__ takes only `stream` and always exports a legacy capsule.
        if dl_device is not None and tuple(dl_device) != tuple(carrier.__dlpack_device__()):
            raise BufferError(f"cannot export {self.device} memory to DLPack device {dl_device}")
        if copy:
            raise BufferError("this view only exports zero-copy")
        if self.device != "cpu" and stream is not None and stream != -1:
            order_consumer(self.handle, self.device, stream)
            stream = -1  # ordered above; Warp would otherwise order after its own current stream
        return carrier.__dlpack__(stream=stream)

    def reshape_result(self, tensor: Any) -> Any:
        """Give a consumer's tensor this view's shape (only differs for scalars behind Warp)."""
        if len(tensor.shape) != len(self.layout.shape):
            return tensor.reshape(self.layout.shape)
        return tensor

    def __repr__(self) -> str:
        layout = self.layout
        mode = "writable" if self.writable else "read-only"
        return (f"TensorView({layout.dtype.name}, shape={layout.shape}, strides={layout.strides}, "
                f"device={self.device!r}, {mode})")


_STREAMS: dict[tuple[str, int], Any] = {}  # (device, cudaStream_t) -> external wp.Stream


def external_stream(device: str, cuda_stream: int) -> Any:
    """A ``wp.Stream`` wrapping a framework's raw CUDA stream (DLPack numbering: 1 = legacy
    default, 2 = per-thread default), cached by its value."""
    key = (device, cuda_stream)
    found = _STREAMS.get(key)
    if found is None:
        wp = import_warp()
        raw = 0 if cuda_stream == 1 else cuda_stream
        found = wp.Stream(device, cuda_stream=raw)
        if len(_STREAMS) >= 64:  # frameworks reuse pooled streams: a handful in practice
            _STREAMS.clear()
        _STREAMS[key] = found
    return found


def order_consumer(handle: Any, device: str, stream: int) -> None:
    """Make the consumer's CUDA ``stream`` (a DLPack stream number) wait for the work ordered
    on the handle's stream (which itself waits for the writer)."""
    ours = handle.stream if handle is not None else None
    if ours is None:
        return
    if (ours.cuda_stream or 1) == stream:
        return
    external_stream(device, stream).wait_stream(ours)


def host_alias(array: np.ndarray) -> np.ndarray:
    """A writable alias of a read-only contiguous host array (same memory, keeps it alive), for
    consumers that import only legacy DLPack, which cannot flag read-only memory. Hand it out under
    the read-only contract of ``clone=False``."""
    raw = array_at(array.ctypes.data, array.nbytes, array)
    return np.ndarray(array.shape, array.dtype, buffer=raw, strides=array.strides)


def _host_carrier(storage: np.ndarray, layout: TensorLayout, owner: Any) -> Any:
    if layout.dtype.code == DLDataTypeCode.BFLOAT:  # NumPy has no bfloat16
        base = storage.ctypes.data if storage.size else 0
        return _warp_carrier(base, storage.size, "cpu", layout, owner=owner)
    return layout.ndarray_over(storage)


def _warp_carrier(base_ptr: int, nbytes: int, device: str, layout: TensorLayout, owner: Any) -> Any:
    wp = import_warp()
    itemsize = layout.dtype.itemsize
    layout.check_fits(nbytes)  # against the real storage size
    ptr = base_ptr + layout.byte_offset
    if device != "cpu" and ptr % itemsize:
        raise InvalidTensorMetadataError(
            f"byte_offset {layout.byte_offset} leaves {layout.dtype.name} elements misaligned in "
            f"{device} memory; it must be a multiple of {itemsize}")
    shape, strides = layout.shape, layout.byte_strides
    if not shape:  # Warp has no 0-d arrays
        shape, strides = (1,), (itemsize,)
    if any(d > MAX_WARP_DIM for d in shape):
        raise InvalidTensorMetadataError(
            f"shape {list(layout.shape)}: Warp arrays have dimensions of at most {MAX_WARP_DIM} "
            "elements")
    if len(shape) > MAX_WARP_DIMS:
        raise InvalidTensorMetadataError(
            f"a {len(shape)}-D tensor: Warp arrays have at most {MAX_WARP_DIMS} dimensions "
            f"({layout.dtype.name}{list(layout.shape)}); read it with torch or NumPy")
    carrier = wp.array(ptr=ptr if layout.numel else None, dtype=warp_dtype(layout.dtype),
                       shape=shape, strides=strides, device=device, copy=False)
    carrier._tensor_conversions_owner = owner  # keeps the memory / handle alive with the carrier
    return carrier


def view_of(msg: Any, layout: TensorLayout, *, writable: bool, stream: Any = None,
            replace_if_spent: bool = False) -> TensorView:
    """A view of ``layout`` over ``msg.data``; warp storage opens (or shares) a handle on
    ``stream`` (a ``wp.Stream`` or None for Warp's current one)."""
    data = msg.data
    if backend_of(data) == "cpu":
        return TensorView(host_bytes(data, writable=writable), layout, writable=writable)
    if writable:
        handle = open_write(msg, stream, replace_if_spent=replace_if_spent)
    else:
        handle = open_read(msg, stream)
    host = handle.host_array()  # host memory: NumPy over it, no wp.array (built if asked)
    return TensorView(handle.array if host is None else host, layout, writable=writable,
                      handle=handle)


def output_view(msg: Any, stream: Any = None) -> TensorView:
    """A writable view of ``msg``'s tensor, for filling the message in place.

    CPU storage: the field's host memory (borrowed read-only bytes are copied once first,
    copy-on-write). warp storage: the buffer's single write handle, opened on ``stream``.
    """
    return view_of(msg, layout_of(msg), writable=True, stream=stream)


def input_view(msg: Any, stream: Any = None) -> TensorView:
    """A read-only view of ``msg``'s tensor (aliases the storage); warp storage takes a read
    handle whose ``stream`` is ordered after the writer."""
    return view_of(msg, layout_of(msg), writable=False, stream=stream)
