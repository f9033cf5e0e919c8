"""ExperimentalTensor <-> ``numpy.ndarray``, through NumPy's own DLPack import.

NumPy has no bfloat16: messages of that dtype raise :class:`UnsupportedDTypeError` (use the torch
or warp module). NumPy only addresses host memory: CPU-backed messages and warp-backed messages
on Warp's ``cpu`` device convert zero-copy; for other Warp devices ``from_input_tensor_msg``
copies to the host (``clone=True`` only) and ``to_tensor_msg`` copies host -> device with Warp.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, overload

import numpy as np

from . import _api
from . import loan as _loan
from . import image as _image
from . import pointcloud as _pointcloud
from .dlpack import TensorView, import_warp, warp_dtype
from .dtypes import DType, dtype_from_numpy
from .metadata import TensorLayout
from .errors import UnsupportedBackendError, UnsupportedValueError

__all__ = [
    "allocate_image_msg",
    "allocate_pointcloud_msg",
    "allocate_tensor_msg",
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
]


def _host_only(view: TensorView, what: str) -> None:
    if view.device != "cpu":
        raise UnsupportedBackendError(
            f"NumPy cannot address {view.device} memory ({what}); use clone=True for a host copy, "
            "or the torch/warp module")


class _NumpyAdapter(_api.Adapter[np.ndarray]):
    name = "numpy"

    def to_dtype(self, dtype: Any) -> DType:
        return dtype if isinstance(dtype, DType) else dtype_from_numpy(dtype)

    def check_dtype(self, dtype: DType) -> None:
        dtype.numpy_dtype()

    def check_view_device(self, device: str) -> None:
        if device != "cpu":
            raise UnsupportedBackendError(
                f"NumPy cannot address {device} memory; use clone=True for a host copy, "
                "or the torch/warp module")

    host_views = True
    numpy_dtypes = True

    def host_input(self, storage: np.ndarray, layout: TensorLayout) -> np.ndarray:
        shape, dtype, offset, strides = layout.numpy_args  # (ndarray_over: called with them)
        array = np.ndarray(shape, dtype, buffer=storage, offset=offset, strides=strides)
        array.flags.writeable = False
        return array

    def from_view(self, view: TensorView) -> np.ndarray:
        _host_only(view, "zero-copy view")
        carrier = view.carrier
        # a NumPy carrier is the view itself; a bfloat16 (Warp) carrier never gets here
        return carrier if type(carrier) is np.ndarray else np.from_dlpack(view)

    def clone(self, view: TensorView) -> np.ndarray:
        if view.device == "cpu":
            return np.array(self.from_view(view), order="C", copy=True)
        wp = import_warp()
        source = view.carrier
        host = wp.empty(source.shape, dtype=source.dtype, device="cpu")
        stream = view.handle.stream if view.handle is not None else None
        wp.copy(host, source if source.is_contiguous else source.contiguous(), stream=stream)
        wp.synchronize_stream(stream)  # the host copy must be complete when we return
        return view.reshape_result(host.numpy())

    def readonly(self, tensor: np.ndarray) -> np.ndarray:
        tensor.flags.writeable = False  # the carrier is this view's own array
        return tensor

    def describe(self, value: Any) -> tuple[tuple[int, ...], DType, str, str | None]:
        if not isinstance(value, (np.ndarray, np.generic)):
            raise UnsupportedValueError(
                f"tensor_conversions.numpy sends NumPy arrays, not {type(value).__name__}")
        return tuple(value.shape), dtype_from_numpy(value.dtype), "cpu", None

    def copy_into(self, view: TensorView, value: Any) -> None:
        array = np.asarray(value)
        if view.device == "cpu":
            np.copyto(self.from_view(view), array, casting="no")
            return
        wp = import_warp()
        dtype = warp_dtype(view.dtype)
        source = wp.array(np.ascontiguousarray(array).reshape(-1), dtype=dtype, device="cpu")
        stream = view.handle.stream if view.handle is not None else None
        wp.copy(view.carrier.flatten(), source, stream=stream)  # host -> device on the handle's


_ADAPTER = _NumpyAdapter()


def allocate_tensor_msg(shape: Sequence[int] | int, dtype: Any, backend: str = "cpu",
                        device: Any = None) -> Any:
    """A new ExperimentalTensor with metadata for ``shape``/``dtype`` and zeroed ``data``.

    ``backend="cpu"``: host storage (``device`` must be None or ``"cpu"``). ``backend="warp"``:
    Warp storage on ``device`` (None = Warp's default device). Unservable requests raise
    :class:`UnsupportedBackendError`.
    """
    return _api.allocate_tensor_msg(_ADAPTER, shape, dtype, backend, device)


def from_output_tensor_msg(msg: Any) -> np.ndarray:
    """A writable zero-copy array over ``msg.data`` (host memory only), for filling it in place.

    For warp storage (Warp ``cpu`` device) the array holds the buffer's write handle while it
    lives; see :func:`tensor_conversions.release_output`.
    """
    return _api.from_output_tensor_msg(_ADAPTER, msg)


def loan_tensor_msg(publisher: Any, shape: Sequence[int] | int, dtype: Any,
                    backend: str = "warp", device: Any = None,
                    *, max_loans: int | None = None) -> Any:
    """``with loan_tensor_msg(pub, shape, dtype) as msg:`` a loaned ExperimentalTensor from
    ``pub``'s pool (warp storage on ``device``), published when the block ends; an exception
    publishes nothing. :func:`from_output_tensor_msg` of it returns the same writable np.ndarray
    every loan of that block (built once). The loan ends at publish: on Warp's cpu device the
    memory is read-only until its next loan (a write through a view kept past publish faults);
    on CUDA such a write is not stopped: don't. See :mod:`tensor_conversions.loan`.
    """
    return _loan.loan_tensor_msg(_ADAPTER, publisher, shape, dtype, backend, device,
                                 max_loans=max_loans)


def from_input_tensor_msg(msg: Any, clone: bool = True) -> np.ndarray:
    """The array of ``msg``: a C-contiguous copy (default) or, with ``clone=False``, a read-only
    (``writeable=False``) zero-copy view that keeps the storage alive."""
    return _api.from_input_tensor_msg(_ADAPTER, msg, clone)


@overload
def to_tensor_msg(msg: Any, value: np.ndarray) -> Any: ...
@overload
def to_tensor_msg(value: np.ndarray, *, backend: str | None = None, device: Any = None) -> Any: ...
def to_tensor_msg(msg_or_value: Any, value: Any = None, *, backend: str | None = None,
                  device: Any = None) -> Any:
    """Copy an array into a message as a contiguous row-major payload and refresh the metadata.

    ``to_tensor_msg(msg, value)`` fills ``msg``'s preallocated storage (too small raises
    :class:`TensorSizeError`); ``to_tensor_msg(value)`` returns a new CPU-backed message unless
    ``backend``/``device`` say otherwise.
    """
    return _api.to_tensor_msg(_ADAPTER, msg_or_value, value, backend=backend, device=device)


# ------------------------------------------------------------------ sensor_msgs/msg/Image
def allocate_image_msg(height: int, width: int, encoding: str, backend: str = "cpu",
                       device: Any = None, step: int | None = None) -> Any:
    """A new ``sensor_msgs/msg/Image`` of ``encoding`` with ``step * height`` bytes of storage
    (``step`` defaults to a packed row; a larger one pads each row). See
    :mod:`tensor_conversions.image` for encodings and errors."""
    return _image.allocate_image_msg(_ADAPTER, height, width, encoding, backend, device, step)


def from_output_image_msg(msg: Any) -> np.ndarray:
    """A writable zero-copy HWC view of the image (``(height, width)`` for one channel); the
    row padding is the row stride."""
    return _image.from_output_image_msg(_ADAPTER, msg)


def from_input_image_msg(msg: Any, clone: bool = True) -> np.ndarray:
    """The image as an HWC copy (default) or, with ``clone=False``, a zero-copy alias of the
    storage (treat as read-only) whose row stride is ``step``."""
    return _image.from_input_image_msg(_ADAPTER, msg, clone)


def to_image_msg(value: np.ndarray, encoding: str, *, backend: str | None = None,
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
                              clone: bool = True) -> np.ndarray:
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


def from_output_pointcloud_msg(msg: Any, fields: Sequence[str] | None = None) -> np.ndarray:
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
