"""ExperimentalTensor <-> ``wp.array``, through Warp's own DLPack import.

Devices: a warp-backed message gives arrays on its Warp device; a CPU-backed message gives arrays
on Warp's ``cpu`` device over the host memory. Warp has no 0-d arrays, so a scalar tensor
(shape ``()``) converts to shape ``(1,)``; and no complex types (those raise
:class:`UnsupportedDTypeError`). Every other supported dtype works, bool and bfloat16 included.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, overload

import warp as wp

from . import _api
from . import loan as _loan
from . import image as _image
from . import pointcloud as _pointcloud
from .dlpack import TensorView, import_warp, warp_dtype
from .dtypes import DType, dtype_from_name
from .errors import UnsupportedDTypeError, UnsupportedValueError

import_warp()  # at import: Warp starts quietly, before the application's first Warp call

__all__ = [
    "allocate_image_msg",
    "allocate_pointcloud_msg",
    "allocate_tensor_msg",
    "dtype_to_warp",
    "from_input_image_msg",
    "from_input_pointcloud_msg",
    "from_input_tensor_msg",
    "from_output_image_msg",
    "from_output_pointcloud_msg",
    "from_output_tensor_msg",
    "loan_image_msg",
    "loan_pointcloud_msg",
    "loan_tensor_msg",
    "to_image_msg",
    "to_tensor_msg",
    "warp_to_dtype",
]


def warp_to_dtype(dtype: Any) -> DType:
    """``wp.float32`` (or ``"float32"``) -> :class:`DType`; vector/struct types raise."""
    if isinstance(dtype, str):
        return dtype_from_name(dtype)
    if hasattr(dtype, "_wp_scalar_type_") or not isinstance(dtype, type):
        raise UnsupportedDTypeError(
            f"{dtype!r} is not a Warp scalar type; view vector data with a scalar dtype")
    name = getattr(dtype, "__name__", "")
    if getattr(wp, name, None) is not dtype:
        raise UnsupportedDTypeError(f"{dtype!r} is not a Warp scalar type")
    return dtype_from_name(name)


def dtype_to_warp(dtype: DType) -> Any:
    """:class:`DType` -> Warp scalar type."""
    return warp_dtype(dtype)


def as_warp(view: TensorView) -> wp.array:
    """``view`` as a ``wp.array`` (a scalar as shape ``(1,)``), zero-copy."""
    return view.warp_array()


class _WarpAdapter(_api.Adapter[wp.array]):
    name = "warp"

    def to_dtype(self, dtype: Any) -> DType:
        return dtype if isinstance(dtype, DType) else warp_to_dtype(dtype)

    def check_dtype(self, dtype: DType) -> None:
        warp_dtype(dtype)

    def stream(self, device: str) -> Any:
        return None  # Warp's current stream of the device

    def from_view(self, view: TensorView) -> wp.array:
        return as_warp(view)

    def clone(self, view: TensorView) -> wp.array:
        source = as_warp(view)
        return source.contiguous() if not source.is_contiguous else wp.clone(source)

    def describe(self, value: Any) -> tuple[tuple[int, ...], DType, str, str | None]:
        if not isinstance(value, wp.array):
            raise UnsupportedValueError(
                f"tensor_conversions.warp sends wp.array values, not {type(value).__name__}")
        return tuple(value.shape), warp_to_dtype(value.dtype), "warp", str(value.device)

    def copy_into(self, view: TensorView, value: Any) -> None:
        dest = as_warp(view)
        if str(value.device) != str(dest.device) and not value.is_contiguous:
            value = value.contiguous()  # Warp copies across devices only contiguous arrays
        if tuple(dest.shape) != tuple(value.shape):  # scalar carried as (1,)
            value = value.reshape(dest.shape)
        wp.copy(dest, value)


_ADAPTER = _WarpAdapter()


def allocate_tensor_msg(shape: Sequence[int] | int, dtype: Any, backend: str = "cpu",
                        device: Any = None) -> Any:
    """A new ExperimentalTensor with metadata for ``shape``/``dtype`` and zeroed ``data``.

    ``backend="cpu"``: host storage (``device`` None or ``"cpu"``). ``backend="warp"``: Warp
    storage on ``device`` (None = Warp's default device). Unservable requests raise
    :class:`UnsupportedBackendError`.
    """
    return _api.allocate_tensor_msg(_ADAPTER, shape, dtype, backend, device)


def from_output_tensor_msg(msg: Any) -> wp.array:
    """A writable zero-copy array over ``msg.data``, for filling the message in place.

    For warp storage the array holds the buffer's single write handle until it (and every view
    sharing it) is collected, or :func:`tensor_conversions.release_output` is called.
    """
    return _api.from_output_tensor_msg(_ADAPTER, msg)


def loan_tensor_msg(publisher: Any, shape: Sequence[int] | int, dtype: Any,
                    backend: str = "warp", device: Any = None,
                    *, max_loans: int | None = None) -> Any:
    """``with loan_tensor_msg(pub, shape, dtype) as msg:`` a loaned ExperimentalTensor from
    ``pub``'s pool (warp storage on ``device``), published when the block ends; an exception
    publishes nothing. :func:`from_output_tensor_msg` of it returns the same writable wp.array
    every loan of that block (built once). The loan ends at publish: on Warp's cpu device the
    memory is read-only until its next loan (a write through a view kept past publish faults);
    on CUDA such a write is not stopped: don't. See :mod:`tensor_conversions.loan`.
    """
    return _loan.loan_tensor_msg(_ADAPTER, publisher, shape, dtype, backend, device,
                                 max_loans=max_loans)


def from_input_tensor_msg(msg: Any, clone: bool = True) -> wp.array:
    """The array of ``msg``: a contiguous copy on the same device (default) or, with
    ``clone=False``, a zero-copy alias (treat as read-only) that keeps the storage alive."""
    return _api.from_input_tensor_msg(_ADAPTER, msg, clone)


@overload
def to_tensor_msg(msg: Any, value: wp.array) -> Any: ...
@overload
def to_tensor_msg(value: wp.array, *, backend: str | None = None, device: Any = None) -> Any: ...
def to_tensor_msg(msg_or_value: Any, value: Any = None, *, backend: str | None = None,
                  device: Any = None) -> Any:
    """Copy a Warp array into a message as a contiguous payload and refresh the metadata.

    ``to_tensor_msg(msg, value)`` fills ``msg``'s preallocated storage (too small raises
    :class:`TensorSizeError`); ``to_tensor_msg(value)`` returns a new warp-backed message on the
    array's device unless ``backend``/``device`` say otherwise.
    """
    return _api.to_tensor_msg(_ADAPTER, msg_or_value, value, backend=backend, device=device)


# ------------------------------------------------------------------ sensor_msgs/msg/Image
def allocate_image_msg(height: int, width: int, encoding: str, backend: str = "cpu",
                       device: Any = None, step: int | None = None) -> Any:
    """A new ``sensor_msgs/msg/Image`` of ``encoding`` with ``step * height`` bytes of storage
    (``step`` defaults to a packed row; a larger one pads each row). See
    :mod:`tensor_conversions.image` for encodings and errors."""
    return _image.allocate_image_msg(_ADAPTER, height, width, encoding, backend, device, step)


def from_output_image_msg(msg: Any) -> wp.array:
    """A writable zero-copy HWC view of the image (``(height, width)`` for one channel); the
    row padding is the row stride."""
    return _image.from_output_image_msg(_ADAPTER, msg)


def from_input_image_msg(msg: Any, clone: bool = True) -> wp.array:
    """The image as an HWC copy (default) or, with ``clone=False``, a zero-copy alias of the
    storage (treat as read-only) whose row stride is ``step``."""
    return _image.from_input_image_msg(_ADAPTER, msg, clone)


def to_image_msg(value: wp.array, encoding: str, *, backend: str | None = None,
                 device: Any = None) -> Any:
    """A new Image of ``encoding`` holding a copy of ``value`` (shape ``(h, w)`` or
    ``(h, w, channels)``, the encoding's dtype), rows packed."""
    return _image.to_image_msg(_ADAPTER, value, encoding, backend=backend, device=device)


def loan_image_msg(publisher: Any, height: int, width: int, encoding: str,
                   backend: str = "warp", device: Any = None, step: int | None = None,
                   *, max_loans: int | None = None) -> Any:
    """``with loan_image_msg(pub, height, width, encoding) as msg:`` a loaned
    ``sensor_msgs/msg/Image`` from ``pub``'s pool (the arguments of :func:`allocate_image_msg`,
    warp storage on ``device``), published when the block ends; an exception publishes nothing.
    :func:`from_output_image_msg` of it returns the same writable view every loan of that block
    (built once). The loan ends at publish, as for :func:`loan_tensor_msg`; see
    :mod:`tensor_conversions.loan`.
    """
    return _loan.loan_image_msg(_ADAPTER, publisher, height, width, encoding, backend, device,
                                step, max_loans=max_loans)


# ------------------------------------------------------------ sensor_msgs/msg/PointCloud2
def from_input_pointcloud_msg(msg: Any, fields: Sequence[str] = ("x", "y", "z"),
                              clone: bool = True) -> wp.array:
    """An ``(N, F)`` tensor of the cloud's points (``F``: a column per field, ``count`` of
    them for a multi-count field): a zero-copy strided view where
    the layout allows (then ``clone`` copies it), else one float32 host copy; see
    :mod:`tensor_conversions.pointcloud`."""
    return _pointcloud.from_input_pointcloud_msg(_ADAPTER, msg, fields, clone)


def allocate_pointcloud_msg(width: int, fields: Sequence[str], dtype: Any,
                            height: int = 1, backend: str = "cpu", device: Any = None) -> Any:
    """A new ``sensor_msgs/msg/PointCloud2`` of ``height * width`` points whose ``fields``
    (names) are packed values of one ``dtype`` (``point_step = len(fields) * itemsize``, this
    machine's byte order), storage zeroed (``backend``/``device`` as for tensors)."""
    return _pointcloud.allocate_pointcloud_msg(_ADAPTER, width, fields, dtype, height, backend,
                                               device)


def from_output_pointcloud_msg(msg: Any, fields: Sequence[str] | None = None) -> wp.array:
    """A writable zero-copy ``(N, F)`` view of the cloud's points (``fields``: all by default)
    for filling it in place; the fields must be one strided view (as
    :func:`allocate_pointcloud_msg` makes them), else :class:`InvalidTensorMetadataError`."""
    return _pointcloud.from_output_pointcloud_msg(_ADAPTER, msg, fields)


def loan_pointcloud_msg(publisher: Any, width: int, fields: Sequence[str], dtype: Any,
                        height: int = 1, backend: str = "warp", device: Any = None,
                        *, max_loans: int | None = None) -> Any:
    """``with loan_pointcloud_msg(pub, width, ("x", "y", "z"), dtype) as msg:`` a loaned
    PointCloud2 from ``pub``'s pool (the arguments of :func:`allocate_pointcloud_msg`, warp
    storage on ``device``), published when the block ends. :func:`from_output_pointcloud_msg`
    of it returns the same writable ``(N, F)`` view every loan of that block. The loan ends at
    publish, as for :func:`loan_tensor_msg`; see :mod:`tensor_conversions.loan`.
    """
    return _loan.loan_pointcloud_msg(_ADAPTER, publisher, width, fields, dtype, height, backend,
                                     device, max_loans=max_loans)
