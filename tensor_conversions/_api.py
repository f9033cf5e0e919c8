"""The four conversion operations, written once over a small per-framework adapter.

A framework module (``tensor_conversions.torch``, ``.numpy``, ``.warp``, ``.jax``, ``.cupy``)
supplies an :class:`Adapter`: its dtypes, its stream, its DLPack import (zero-copy view), its copy
and how to describe a value. The image functions (:mod:`.image`) reuse the same adapters.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Generic, TypeVar

import numpy as np

from .dlpack import TensorView, host_alias, import_warp, view_of, warp_dtype
from .dtypes import DType, dtype_from_name
from .errors import (
    InvalidTensorMetadataError,
    TensorSizeError,
    UnsupportedBackendError,
    UnsupportedValueError,
)
from .metadata import (
    TensorLayout,
    check_tensor_msg,
    layout_of,
    tensor_msg_type,
    write_metadata,
)
from .loan import loan_state, loaned_native
from .storage import NativeState, allocate_data, backend_of, live_write_handle, storage_device

from rosidl_buffer import CpuBufferImpl

T = TypeVar("T")


class Adapter(Generic[T]):
    """What the generic operations need to know about one framework (subclassed per module)."""

    name: str = "?"

    def to_dtype(self, dtype: Any) -> DType:
        """Framework dtype (or canonical name) -> :class:`DType`; unsupported raises."""
        raise NotImplementedError

    def check_dtype(self, dtype: DType) -> None:
        """Raise :class:`UnsupportedDTypeError` if the framework cannot represent ``dtype``."""

    def check_view_device(self, device: str) -> None:
        """Raise if the framework cannot view memory on ``device`` (checked before a handle is
        opened, so a refused request consumes nothing)."""

    def stream(self, device: str) -> Any:
        """The ``wp.Stream`` the framework runs on for a CUDA ``device`` (None: Warp's current
        one); never called for cpu storage."""
        return None

    #: Whether :meth:`host_input` builds read-only views over host memory directly.
    host_views = False
    #: Whether the framework has every dtype NumPy has (then a layout NumPy can carry needs no
    #: check of its dtype).
    numpy_dtypes = False

    def host_input(self, storage: np.ndarray, layout: TensorLayout) -> T | None:
        """A read-only zero-copy native of ``layout`` (whose ``numpy_args`` is not None) over
        host ``storage`` (1-D uint8 that keeps the memory alive), or None for the general path;
        called only when :attr:`host_views`."""
        return None

    def from_view(self, view: TensorView) -> T:
        """Consume ``view`` zero-copy (the framework's ``from_dlpack``), with the view's shape."""
        raise NotImplementedError

    def clone(self, view: TensorView) -> T:
        """An independent, contiguous copy of ``view``'s tensor, ordered on the view's stream."""
        raise NotImplementedError

    def readonly(self, tensor: T) -> T:
        """Mark a read-only alias where the framework can express it."""
        return tensor

    def describe(self, value: Any) -> tuple[tuple[int, ...], DType, str, str | None]:
        """``(shape, dtype, default backend, default device)`` of a value to send; a value of
        another kind raises :class:`UnsupportedValueError`."""
        raise NotImplementedError

    def copy_into(self, view: TensorView, value: Any) -> None:
        """Copy ``value`` (same shape and dtype) into the writable ``view``, on its stream."""
        raise NotImplementedError


def _stream(adapter: Adapter[Any], device: str) -> Any:
    return None if device == "cpu" else adapter.stream(device)


def new_msg(layout: TensorLayout, backend: str, device: Any, data: Any = None) -> Any:
    """A new ExperimentalTensor with ``layout``'s metadata and storage for it (``data``, or
    newly allocated)."""
    nbytes = layout.required_nbytes
    if backend == "warp":
        warp_dtype(layout.dtype)  # complex has no Warp type: refused before allocating
        # A warp buffer is never empty: an empty tensor's metadata over one byte, as a loan's
        # (a tensor's storage may be larger than its layout; frames of size zero stay on warp).
        nbytes = max(1, nbytes)
    if data is None:
        data = allocate_data(nbytes, backend, device)
    dt = layout.dtype
    strides = () if layout.is_contiguous else layout.strides
    return tensor_msg_type()(
        dtype_code=dt.code, dtype_bits=dt.bits, dtype_lanes=dt.lanes,
        shape=np.asarray(layout.shape, dtype=np.int64).reshape(-1),
        strides=np.asarray(strides, dtype=np.int64).reshape(-1),
        byte_offset=layout.byte_offset, data=data)


def allocate_tensor_msg(adapter: Adapter[Any], shape: Sequence[int] | int, dtype: Any,
                        backend: str = "cpu", device: Any = None) -> Any:
    dt = adapter.to_dtype(dtype)
    adapter.check_dtype(dt)
    return new_msg(TensorLayout.contiguous(dt, shape), backend, device)


def output_native(adapter: Adapter[T], msg: Any, layout: TensorLayout) -> T:
    """A writable native view of ``layout`` over ``msg.data`` (tensor and image functions)."""
    loaned = loan_state(msg)
    if loaned is not None:  # a loan: the view cached for this block, or one over its memory
        if layout == loaned.layout:
            return loaned.native(adapter)
        adapter.check_dtype(layout.dtype)
        return adapter.from_view(loaned.view_for(layout))
    adapter.check_dtype(layout.dtype)
    device = storage_device(msg.data)
    adapter.check_view_device(device)
    return adapter.from_view(view_of(msg, layout, writable=True, stream=_stream(adapter, device)))


def input_native(adapter: Adapter[T], msg: Any, layout: TensorLayout, clone: bool) -> T:
    """A native copy (``clone``) or read-only alias of ``layout`` over ``msg.data``."""
    adapter.check_dtype(layout.dtype)
    device = storage_device(msg.data)
    if not clone:
        adapter.check_view_device(device)
    view = view_of(msg, layout, writable=False, stream=_stream(adapter, device))
    if not clone:
        return adapter.readonly(adapter.from_view(view))
    try:
        return adapter.clone(view)
    finally:
        # The copy is queued on the handle's stream: releasing records the read's end there
        # (stream-ordered), so nothing waits here. Our own write handle is left to its views.
        handle = view.handle
        if handle is not None and handle is not live_write_handle(msg):
            handle.release()


def from_output_tensor_msg(adapter: Adapter[T], msg: Any) -> T:
    if type(getattr(msg, "_native", None)) is NativeState:  # maybe a loan, left as it was made
        native = loaned_native(adapter, msg)  # its cached view
        if native is not None:
            return native
    return output_native(adapter, msg, layout_of(msg))


def from_input_tensor_msg(adapter: Adapter[T], msg: Any, clone: bool = True) -> T:
    layout = layout_of(msg)
    if not clone and adapter.host_views and layout.numpy_args is not None:
        # perf: the per-frame case of a subscriber (a received message in host memory) built
        # straight over its bytes: no TensorView or DLPack round trip.
        if not adapter.numpy_dtypes:  # (NumPy carries every dtype numpy_args has)
            adapter.check_dtype(layout.dtype)  # the general path's typed error, before any read
        impl = msg.data.get_impl()
        native = None
        if type(impl) is CpuBufferImpl:
            native = adapter.host_input(impl.view(), layout)
        else:
            reader_host = getattr(impl, "reader_host", None)  # warp storage
            if reader_host is not None:
                # Our own unpublished write is read through its write handle; anything else
                # through host memory that holds a reader's token (the view keeps it).
                live = live_write_handle(msg) if type(getattr(
                    msg, "_native", None)) is NativeState else None
                host = live.host_array() if live is not None else reader_host()
                if host is not None:  # None: device memory
                    native = adapter.host_input(host, layout)
        if native is not None:
            return native
    return input_native(adapter, msg, layout, clone)


def to_tensor_msg(adapter: Adapter[Any], msg_or_value: Any, value: Any = None, *,
                  backend: str | None = None, device: Any = None) -> Any:
    if value is not None:
        check_tensor_msg(msg_or_value)
        if backend is not None or device is not None:
            raise UnsupportedBackendError(
                "backend/device apply to a new message only; the storage of an existing message "
                "is kept")
        msg = msg_or_value
        shape, dt, _, _ = adapter.describe(value)
        layout = TensorLayout.contiguous(dt, shape)
        capacity = len(msg.data)
        if layout.required_nbytes > capacity:
            raise TensorSizeError(
                f"{dt.name}{list(shape)} needs {layout.required_nbytes} bytes, the message's data "
                f"holds {capacity}; allocate a larger message")
        backend_of(msg.data)
    else:
        if getattr(msg_or_value, "__msgtype__", None) is not None:
            raise TypeError("to_tensor_msg(msg, value): value is missing")
        value = msg_or_value
        shape, dt, value_backend, value_device = adapter.describe(value)
        layout = TensorLayout.contiguous(dt, shape)
        if backend is None:
            backend, device = value_backend, value_device if device is None else device
        msg = new_msg(layout, backend, device)
    write_value(adapter, msg, layout, value)
    write_metadata(msg, layout)
    return msg


def write_value(adapter: Adapter[Any], msg: Any, layout: TensorLayout, value: Any) -> None:
    """Copy ``value`` into ``msg.data`` as ``layout`` and end the write if we opened it.

    The copy runs on the adapter's stream and the write handle is opened on that same stream, so
    releasing it records completion where the copy really runs (no device synchronisation).
    """
    if layout.numel == 0:
        return
    data = msg.data
    loaned = loan_state(msg)
    if loaned is not None:  # into the loan's own memory (no write handle: the loan has none)
        adapter.copy_into(loaned.view_for(layout), value)
        return
    if backend_of(data) == "cpu":
        adapter.copy_into(view_of(msg, layout, writable=True), value)
        return
    shared = live_write_handle(msg)
    device = storage_device(data)
    stream = _stream(adapter, device)
    view = view_of(msg, layout, writable=True, stream=stream, replace_if_spent=True)
    handle = view.handle
    adapter.copy_into(view, value)
    if shared is None:
        handle.release()  # ours: the message is complete and publishable
    elif device != "cpu" and shared.stream is not None:
        # A live view's handle records completion on ITS stream: order that after our copy.
        ours = stream if stream is not None else import_warp().get_stream(device)
        if ours is not shared.stream:
            shared.stream.wait_stream(ours)


_KDL_CUDA = 2  # DLPack device type of CUDA memory


class DLPackAdapter(Adapter[T]):
    """An adapter for a framework reached only through DLPack (JAX, CuPy, ONNX Runtime).

    Subclasses name the framework's import (``consume``), its value type and which devices it
    addresses. Frameworks that import only compact (C-contiguous) tensors get a zero-copy view of
    contiguous layouts; a strided layout needs ``clone=True`` (one copy). Read-only host bytes are
    handed over through a writable alias (legacy DLPack cannot flag them): the aliasing contract
    of ``clone=False`` applies.
    """

    value_type: Any = object
    contiguous_only = True
    host = True  # can the framework address host memory?

    def reshape(self, view: TensorView, tensor: T) -> T:
        """Restore a scalar's ``()`` shape behind a Warp carrier."""
        return view.reshape_result(tensor)

    def consume(self, producer: Any) -> T:
        """The framework's ``from_dlpack``."""
        raise NotImplementedError

    def to_dtype(self, dtype: Any) -> DType:
        if isinstance(dtype, DType):
            return dtype
        try:
            name = np.dtype(dtype).name
        except TypeError:
            name = str(dtype)
        return dtype_from_name(name)

    def check_view_device(self, device: str) -> None:
        if device == "cpu" and not self.host:
            raise UnsupportedBackendError(
                f"{self.name} cannot address host memory; use clone=True for a device copy")

    def from_view(self, view: TensorView) -> T:
        if self.contiguous_only and not view.layout.is_contiguous:
            raise InvalidTensorMetadataError(
                f"{self.name} imports only contiguous tensors; strides {list(view.layout.strides)} "
                "need clone=True (one copy)")
        carrier = view.carrier
        if type(carrier) is np.ndarray and not carrier.flags.writeable:
            return self.consume(host_alias(carrier))
        return self.reshape(view, self.consume(view))

    def clone(self, view: TensorView) -> T:
        carrier = view.carrier
        if type(carrier) is np.ndarray:
            return self.consume(np.array(carrier, order="C", copy=True))
        wp = import_warp()
        copy = carrier.contiguous() if not carrier.is_contiguous else wp.clone(carrier)
        return self.reshape(view, self.consume(copy))

    def describe(self, value: Any) -> tuple[tuple[int, ...], DType, str, str | None]:
        if not isinstance(value, self.value_type):
            raise UnsupportedValueError(
                f"tensor_conversions.{self.name} sends {self.value_type.__name__} values, not "
                f"{type(value).__name__}")
        kind, index = value.__dlpack_device__()
        shape, dtype = self.shape_dtype(value)
        if int(kind) == _KDL_CUDA:
            return shape, dtype, "warp", f"cuda:{index}"
        return shape, dtype, "cpu", None

    def shape_dtype(self, value: Any) -> tuple[tuple[int, ...], DType]:
        return tuple(value.shape), self.to_dtype(value.dtype)

    def copy_into(self, view: TensorView, value: Any) -> None:
        carrier = view.carrier
        if type(carrier) is np.ndarray:
            np.copyto(carrier, np.from_dlpack(value).reshape(carrier.shape), casting="no")
            return
        wp = import_warp()
        source = wp.from_dlpack(value)
        stream = view.handle.stream if view.handle is not None else None
        wp.copy(carrier, source.reshape(carrier.shape) if source.shape != carrier.shape
                else source, stream=stream)
