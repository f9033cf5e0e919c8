"""The four conversion operations, written once over a small per-framework adapter.

A framework module (``tensor_conversions.torch`` / ``.numpy`` / ``.warp``) supplies an
:class:`Adapter`: how to name its dtypes, consume a :class:`TensorView` (its own DLPack import),
copy, and describe a value. All metadata handling lives here and in the core modules.
"""

from __future__ import annotations

import abc
from collections.abc import Sequence
from typing import Any, Generic, TypeVar

import numpy as np

from .dlpack import TensorView, input_view, output_view, view_of_bytes, warp_dtype
from .dtypes import DType
from .errors import TensorSizeError, UnsupportedBackendError
from .metadata import (
    TensorLayout,
    contiguous_strides,
    layout_of,
    normalize_shape,
    tensor_msg_type,
    write_metadata,
)
from .storage import (
    allocate_data,
    backend_of,
    cpu_bytes,
    live_write_lease,
    open_write,
    release_read_lease,
    storage_device,
)

T = TypeVar("T")


class Adapter(abc.ABC, Generic[T]):
    """What the generic operations need to know about one framework."""

    name: str

    @abc.abstractmethod
    def to_dtype(self, dtype: Any) -> DType:
        """Framework dtype (or canonical name) -> :class:`DType`; unsupported raises."""

    @abc.abstractmethod
    def check_dtype(self, dtype: DType) -> None:
        """Raise :class:`UnsupportedDTypeError` if the framework cannot represent ``dtype``."""

    @abc.abstractmethod
    def from_view(self, view: TensorView) -> T:
        """Consume ``view`` zero-copy (the framework's ``from_dlpack``), with the view's shape."""

    @abc.abstractmethod
    def clone(self, view: TensorView) -> T:
        """An independent, contiguous copy of ``view``'s tensor."""

    def check_view_device(self, device: str) -> None:
        """Raise if the framework cannot view memory on ``device`` (checked before any handle
        is opened, so a refused request consumes nothing)."""

    def readonly(self, tensor: T) -> T:
        """Mark a read-only alias where the framework can express it."""
        return tensor

    @abc.abstractmethod
    def describe(self, value: Any) -> tuple[tuple[int, ...], DType, str, str | None]:
        """``(shape, dtype, default backend, default device)`` of a value to send."""

    @abc.abstractmethod
    def copy_into(self, view: TensorView, value: Any) -> None:
        """Copy ``value`` (same shape and dtype) into the writable ``view``."""


def allocate_tensor_msg(adapter: Adapter[Any], shape: Sequence[int] | int, dtype: Any,
                        backend: str = "cpu", device: Any = None) -> Any:
    dt = adapter.to_dtype(dtype)
    adapter.check_dtype(dt)
    dims = normalize_shape(shape)
    # perf: dims is already normalized; TensorLayout.contiguous would normalize it again
    layout = TensorLayout(dt, dims, contiguous_strides(dims), 0)
    return _new_msg(layout, backend, device)


def _new_msg(layout: TensorLayout, backend: str, device: Any) -> Any:
    if backend == "warp":
        warp_dtype(layout.dtype)  # complex has no Warp type: refused before allocating
    data = allocate_data(layout.required_nbytes, backend, device)
    # perf: the metadata fields are built once with their final values (what write_metadata
    # stores: contiguous layouts get empty strides) instead of placeholders then overwritten.
    dt = layout.dtype
    strides = () if layout.is_contiguous else layout.strides
    return tensor_msg_type()(
        dtype_code=dt.code, dtype_bits=dt.bits, dtype_lanes=dt.lanes,
        shape=np.asarray(layout.shape, dtype=np.int64).reshape(-1),
        strides=np.asarray(strides, dtype=np.int64).reshape(-1),
        byte_offset=layout.byte_offset, data=data)


def from_output_tensor_msg(adapter: Adapter[T], msg: Any) -> T:
    layout = layout_of(msg)  # perf: validated once and handed to output_view (was twice)
    adapter.check_dtype(layout.dtype)
    adapter.check_view_device(storage_device(msg.data))
    view = output_view(msg, layout)
    return adapter.from_view(view)


def from_input_tensor_msg(adapter: Adapter[T], msg: Any, clone: bool = True) -> T:
    layout = layout_of(msg)  # perf: validated once and handed to input_view (was twice)
    adapter.check_dtype(layout.dtype)
    if not clone:
        adapter.check_view_device(storage_device(msg.data))
    view = input_view(msg, layout)
    if clone:
        try:
            return adapter.clone(view)
        finally:
            if view.device != "cpu":  # the copy may still be queued on the device
                import warp as wp

                wp.synchronize_device(view.device)
            release_read_lease(view._lease)
    return adapter.readonly(adapter.from_view(view))


def to_tensor_msg(adapter: Adapter[Any], msg_or_value: Any, value: Any = None, *,
                  backend: str | None = None, device: Any = None) -> Any:
    msg_cls = tensor_msg_type()
    if isinstance(msg_or_value, msg_cls):
        if backend is not None or device is not None:
            raise UnsupportedBackendError(
                "backend/device apply to a new message only; the storage of an existing message "
                "is kept")
        if value is None:
            raise TypeError("to_tensor_msg(msg, value): value is missing")
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
        if value is not None:
            raise TypeError("to_tensor_msg takes (msg, value) or (value)")
        value = msg_or_value
        shape, dt, value_backend, value_device = adapter.describe(value)
        layout = TensorLayout.contiguous(dt, shape)
        if backend is None:
            backend, device = value_backend, value_device if device is None else device
        msg = _new_msg(layout, backend, device)
    _copy_to_msg(adapter, msg, layout, value)
    write_metadata(msg, layout)
    return msg


def _copy_to_msg(adapter: Adapter[Any], msg: Any, layout: TensorLayout, value: Any) -> None:
    if layout.numel == 0:
        return
    if backend_of(msg.data) == "cpu":
        view = view_of_bytes(cpu_bytes(msg.data, writable=True), layout, backend="cpu",
                             writable=True)
        adapter.copy_into(view, value)
        return
    shared = live_write_lease(msg.data.get_impl())
    lease = shared or open_write(msg, replace_if_spent=True)
    try:
        view = view_of_bytes(lease.array, layout, backend="warp", writable=True, lease=lease)
        adapter.copy_into(view, value)
        del view
    finally:
        if shared is None:
            # We opened the handle: release it so the message is complete and publishable. The
            # framework may have queued the copy on its own stream: finish it first.
            if str(lease.handle.device) != "cpu":
                import warp as wp

                wp.synchronize_device(str(lease.handle.device))
            lease.release()
