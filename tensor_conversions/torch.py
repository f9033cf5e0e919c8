"""ExperimentalTensor <-> ``torch.Tensor``, through PyTorch's own DLPack import.

Devices: a CPU-backed message gives CPU tensors; a warp-backed message gives tensors on the Warp
device's torch counterpart (``cuda:N``, or CPU for Warp's ``cpu`` device). Every dtype in
:data:`tensor_conversions.SUPPORTED_DTYPES` is supported, bfloat16 and complex included (complex
only in CPU storage: Warp has no complex type).

PyTorch tensors cannot be read-only: a ``clone=False`` input view aliases the message storage and
must be treated as read-only by convention.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, overload

import numpy as np
import torch

from . import _api
from . import loan as _loan
from . import image as _image
from . import pointcloud as _pointcloud
from .dlpack import TensorView, external_stream
from .dtypes import DType, dtype_from_name
from .metadata import TensorLayout
from .errors import UnsupportedBackendError, UnsupportedDTypeError, UnsupportedValueError

__all__ = [
    "allocate_image_msg",
    "from_input_image_msg",
    "from_input_pointcloud_msg",
    "from_output_image_msg",
    "to_image_msg",

    "allocate_tensor_msg",
    "dtype_to_torch",
    "from_input_tensor_msg",
    "from_output_tensor_msg",
    "to_tensor_msg",
    "torch_to_dtype",
]


def torch_to_dtype(dtype: torch.dtype | str) -> DType:
    """``torch.float32`` (or ``"float32"``) -> :class:`DType`."""
    if isinstance(dtype, str):
        return dtype_from_name(dtype.removeprefix("torch."))
    if not isinstance(dtype, torch.dtype):
        raise UnsupportedDTypeError(f"{dtype!r} is not a torch.dtype")
    return dtype_from_name(str(dtype).removeprefix("torch."))


_TORCH_DTYPES: dict[DType, torch.dtype] = {}


def dtype_to_torch(dtype: DType) -> torch.dtype:
    """:class:`DType` -> ``torch.dtype``."""
    found = _TORCH_DTYPES.get(dtype)
    if found is None:
        found = getattr(torch, dtype.name, None)
        if not isinstance(found, torch.dtype):
            raise UnsupportedDTypeError(f"PyTorch has no dtype {dtype.name}")
        _TORCH_DTYPES[dtype] = found
    return found


class _TorchAdapter(_api.Adapter[torch.Tensor]):
    name = "torch"

    def to_dtype(self, dtype: Any) -> DType:
        return dtype if isinstance(dtype, DType) else torch_to_dtype(dtype)

    def check_dtype(self, dtype: DType) -> None:
        dtype_to_torch(dtype)

    def stream(self, device: str) -> Any:
        # torch writes and reads on its current stream: handles are ordered on that one
        stream = torch.cuda.current_stream(torch.device(device))
        return external_stream(device, stream.cuda_stream or 1)

    host_views = True

    def host_input(self, storage: np.ndarray, layout: TensorLayout) -> torch.Tensor | None:
        # perf: torch.from_numpy over warp storage's host memory (~1 us against ~4 through
        # DLPack). Read-only bytes (a received CPU message) take DLPack, which carries the flag
        # (from_numpy would warn).
        if not storage.flags.writeable:
            return None
        return torch.from_numpy(layout.ndarray_over(storage))

    def from_view(self, view: TensorView) -> torch.Tensor:
        return view.reshape_result(torch.from_dlpack(view))

    def clone(self, view: TensorView) -> torch.Tensor:
        source = view.reshape_result(torch.from_dlpack(view))
        return source.clone(memory_format=torch.contiguous_format)

    def describe(self, value: Any) -> tuple[tuple[int, ...], DType, str, str | None]:
        if not isinstance(value, torch.Tensor):
            raise UnsupportedValueError(
                f"tensor_conversions.torch sends torch.Tensor values, not {type(value).__name__}")
        device = value.device
        if device.type == "cpu":
            backend, wp_device = "cpu", None
        elif device.type == "cuda":
            index = device.index if device.index is not None else torch.cuda.current_device()
            backend, wp_device = "warp", f"cuda:{index}"
        else:
            raise UnsupportedBackendError(f"no storage backend for torch device {device}")
        return tuple(value.shape), torch_to_dtype(value.dtype), backend, wp_device

    def copy_into(self, view: TensorView, value: Any) -> None:
        view.reshape_result(torch.from_dlpack(view)).copy_(value)


_ADAPTER = _TorchAdapter()


def allocate_tensor_msg(shape: Sequence[int] | int, dtype: torch.dtype | str,
                        backend: str = "cpu", device: Any = None) -> Any:
    """A new ExperimentalTensor with metadata for ``shape``/``dtype`` and zeroed ``data``.

    ``backend="cpu"``: host storage (``device`` must be None or ``"cpu"``). ``backend="warp"``:
    Warp storage on ``device`` (``"cpu"``, ``"cuda:0"``, ...; None = Warp's default device).
    A backend or device that cannot be served raises :class:`UnsupportedBackendError`.
    """
    return _api.allocate_tensor_msg(_ADAPTER, shape, dtype, backend, device)


def from_output_tensor_msg(msg: Any) -> torch.Tensor:
    """A writable zero-copy tensor over ``msg.data``, for filling the message in place.

    For warp storage the tensor holds the buffer's single write handle until it (and every other
    view sharing it) is garbage-collected, or :func:`tensor_conversions.release_output` is called.
    """
    return _api.from_output_tensor_msg(_ADAPTER, msg)


def loan_tensor_msg(publisher: Any, shape: Sequence[int] | int, dtype: torch.dtype | str,
                    backend: str = "warp", device: Any = None) -> Any:
    """``with loan_tensor_msg(pub, shape, dtype) as msg:`` a loaned ExperimentalTensor from
    ``pub``'s pool (warp storage on ``device``), published when the block ends; an exception
    publishes nothing. :func:`from_output_tensor_msg` of it returns the same writable torch.Tensor
    every loan of that block (built once). The loan ends at publish: on Warp's cpu device the
    memory is read-only until its next loan (a write through a view kept past publish faults);
    on CUDA such a write is not stopped: don't. See :mod:`tensor_conversions.loan`.
    """
    return _loan.loan_tensor_msg(_ADAPTER, publisher, shape, dtype, backend, device)


def from_input_tensor_msg(msg: Any, clone: bool = True) -> torch.Tensor:
    """The tensor of ``msg``: an independent contiguous copy (default) or, with ``clone=False``,
    a zero-copy alias of the storage (treat as read-only) that keeps the storage alive."""
    return _api.from_input_tensor_msg(_ADAPTER, msg, clone)


@overload
def to_tensor_msg(msg: Any, value: torch.Tensor) -> Any: ...
@overload
def to_tensor_msg(value: torch.Tensor, *, backend: str | None = None,
                  device: Any = None) -> Any: ...
def to_tensor_msg(msg_or_value: Any, value: Any = None, *, backend: str | None = None,
                  device: Any = None) -> Any:
    """Copy a tensor into a message as a contiguous row-major payload and refresh the metadata.

    ``to_tensor_msg(msg, value)`` writes into ``msg``'s preallocated storage (too small raises
    :class:`TensorSizeError`) and returns ``msg``. ``to_tensor_msg(value)`` returns a new message:
    CPU storage for a CPU tensor, warp storage on ``cuda:N`` for a CUDA tensor, unless
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


def from_output_image_msg(msg: Any) -> torch.Tensor:
    """A writable zero-copy HWC view of the image (``(height, width)`` for one channel); the
    row padding is the row stride."""
    return _image.from_output_image_msg(_ADAPTER, msg)


def from_input_image_msg(msg: Any, clone: bool = True) -> torch.Tensor:
    """The image as an HWC copy (default) or, with ``clone=False``, a zero-copy alias of the
    storage (treat as read-only) whose row stride is ``step``."""
    return _image.from_input_image_msg(_ADAPTER, msg, clone)


def to_image_msg(value: torch.Tensor, encoding: str, *, backend: str | None = None,
                 device: Any = None) -> Any:
    """A new Image of ``encoding`` holding a copy of ``value`` (shape ``(h, w)`` or
    ``(h, w, channels)``, the encoding's dtype), rows packed."""
    return _image.to_image_msg(_ADAPTER, value, encoding, backend=backend, device=device)


# ------------------------------------------------------------ sensor_msgs/msg/PointCloud2
def from_input_pointcloud_msg(msg: Any, fields: Sequence[str] = ("x", "y", "z"),
                              clone: bool = True) -> torch.Tensor:
    """An ``(N, F)`` tensor of the cloud's points (``F``: a column per field, ``count`` of
    them for a multi-count field): a zero-copy strided view where
    the layout allows (then ``clone`` copies it), else one float32 host copy; see
    :mod:`tensor_conversions.pointcloud`."""
    return _pointcloud.from_input_pointcloud_msg(_ADAPTER, msg, fields, clone)
