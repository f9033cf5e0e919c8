"""ExperimentalTensor <-> ``torch.Tensor``, through PyTorch's own DLPack import.

Devices: a CPU-backed message gives CPU tensors; a warp-backed message gives tensors on the Warp
device's torch counterpart (``cuda:N``, or CPU for Warp's ``cpu`` device). Every dtype in
:data:`tensor_conversions.SUPPORTED_DTYPES` is supported, bfloat16 and complex included (complex
only in CPU storage: Warp has no complex type).

**Zero-copy input views are read-only, and torch enforces it.** A ``clone=False`` input view
(``from_input_tensor_msg``, ``from_input_image_msg``, ``from_input_pointcloud_msg``) aliases the
message's storage, which for a message received from another process is the publisher's memory
mapped read-only. PyTorch has no read-only tensor flag (NumPy's ``writeable``), so such a view
is made with torch's refusal of mutable data pointers on its storage: every write through it or
any view of it (``fill_``, ``t[i] = v``, ``add_``, ``copy_``, ``out=``) raises ``RuntimeError``
("Cannot access data pointer of Tensor ...") instead of killing the process with SIGSEGV. Reads
and computations that make new tensors (``conv2d``, ``sum``, ``.float()``, ``clone()``) work.
Calls that need a mutable pointer raise the same error: ``.numpy()``, ``data_ptr()``,
``__dlpack__`` (so ``wp.from_torch``) and pickling; use the ``numpy`` / ``warp`` modules for those
consumers, or ``clone=True`` (the default), which returns a private, writable copy.

One exception to the alias: torch needs complex elements aligned to their size (complex128: 16
bytes), which CDR's 4-byte alignment of received bytes often breaks; such a tensor comes back as
one aligned copy (and a writable view over misaligned complex storage is refused with
:class:`InvalidTensorMetadataError`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, overload

import numpy as np

try:
    import torch
except ImportError as _error:  # an optional extra: say which
    raise ImportError(f"tensor_conversions.torch needs PyTorch: "
                      f"pip install 'warp-buffer[torch]' ({_error})") from _error

from . import _api
from . import loan as _loan
from . import image as _image
from . import pointcloud as _pointcloud
from .dlpack import MAX_WARP_DIMS, TensorView, external_stream
from .dtypes import DLDataTypeCode, DType, dtype_from_name
from .errors import (
    InvalidTensorMetadataError,
    UnsupportedBackendError,
    UnsupportedDTypeError,
    UnsupportedValueError,
)
from .metadata import TensorLayout

__all__ = [
    "allocate_image_msg",
    "allocate_pointcloud_msg",
    "allocate_tensor_msg",
    "dtype_to_torch",
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


# c10::complex<T> is alignas(2 * sizeof(T)) and torch's kernels rely on it (a clone of a complex128
# tensor 8 bytes off a 16-byte boundary crashes the process). CDR aligns a buffer field's bytes to
# 4 only, so a received complex tensor is often misaligned: such host memory is read through an
# aligned copy and never aliased. Every other dtype works at any address.
_ALIGNMENT = {torch.complex128: 16, torch.complex64: 8}


def _misaligned(view: TensorView) -> bool:
    """Whether torch would get complex elements off their alignment from host ``view``."""
    need = _ALIGNMENT.get(dtype_to_torch(view.dtype))
    if need is None or view.device != "cpu" or not view.layout.numel:
        return False
    carrier = view.carrier
    return carrier.ctypes.data % need != 0 or any(s % need for s in carrier.strides)


def _aligned_copy(view: TensorView) -> torch.Tensor:
    """A contiguous torch copy of misaligned host ``view``, made by NumPy (which reads any
    address) into memory aligned for the dtype."""
    source = view.carrier
    need = _ALIGNMENT[dtype_to_torch(view.dtype)]
    raw = np.empty(source.nbytes + need, dtype=np.uint8)
    start = -raw.ctypes.data % need
    copy = np.ndarray(source.shape, source.dtype, buffer=raw, offset=start)
    copy[...] = source
    return torch.from_numpy(copy)


def _misaligned_error(view: TensorView) -> InvalidTensorMetadataError:
    return InvalidTensorMetadataError(
        f"byte_offset {view.layout.byte_offset} and strides {list(view.layout.strides)} "
        f"leave {view.dtype.name} elements off the {_ALIGNMENT[dtype_to_torch(view.dtype)]}"
        "-byte alignment torch needs; a writable torch view cannot be made over them")


def _over_bytes(view: TensorView) -> torch.Tensor:
    """The tensor of ``view`` laid over its bytes by torch itself (``view`` dtype, then
    ``as_strided``): for what Warp's arrays cannot carry (more than 4 dimensions, see
    :func:`_needs_bytes`). Same memory, ordering and lifetime as the DLPack path: the bytes come
    through the view's own DLPack export."""
    layout = view.layout
    raw = torch.from_dlpack(view.byte_view())
    dtype = dtype_to_torch(layout.dtype)
    if not layout.numel:
        return torch.empty(layout.shape, dtype=dtype, device=raw.device)
    itemsize = layout.dtype.itemsize
    start = layout.byte_offset
    if start % itemsize:
        raise InvalidTensorMetadataError(
            f"byte_offset {start} is not a multiple of the {itemsize}-byte {layout.dtype.name} "
            "element; torch cannot lay this tensor over the bytes")
    span = layout.span_bytes
    elements = raw[start:start + span + (-span % itemsize)].view(dtype)
    return elements.as_strided(layout.shape, layout.strides)


# torch has no read-only tensor, but a storage can refuse its mutable data pointer (torch's own
# FakeTensor uses this): every kernel that writes asks for it, so writes raise instead of
# faulting on memory mapped read-only. Private API, checked at import: torch is pinned.
_refuse_writes = torch._C._set_throw_on_mutable_data_ptr


def _needs_bytes(view: TensorView) -> bool:
    """Past Warp's 4 dimensions, where a Warp array carries the tensor."""
    return len(view.layout.shape) > MAX_WARP_DIMS and view.warp_carried


def _alias(view: TensorView) -> torch.Tensor:
    """A torch tensor over ``view``'s memory (its elements aligned for torch)."""
    if _needs_bytes(view):
        return _over_bytes(view)
    return view.reshape_result(torch.from_dlpack(view))


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
        if not storage.flags.writeable or layout.dtype.code == DLDataTypeCode.COMPLEX:
            return None  # complex: the general path checks the alignment
        # (writable-looking: warp storage's host array cannot say its mapping is read-only)
        return self.readonly(torch.from_numpy(layout.ndarray_over(storage)))

    def from_view(self, view: TensorView) -> torch.Tensor:
        if _misaligned(view):
            if view.writable:
                raise _misaligned_error(view)
            return view.reshape_result(_aligned_copy(view))  # one copy, documented
        return _alias(view)

    def readonly(self, tensor: torch.Tensor) -> torch.Tensor:
        _refuse_writes(tensor)
        return tensor

    def clone(self, view: TensorView) -> torch.Tensor:
        if _misaligned(view):
            return view.reshape_result(_aligned_copy(view))
        return _alias(view).clone(memory_format=torch.contiguous_format)

    def describe(self, value: Any) -> tuple[tuple[int, ...], DType, str, str | None]:
        if not isinstance(value, torch.Tensor):
            raise UnsupportedValueError(
                f"tensor_conversions.torch sends torch.Tensor values, not {type(value).__name__}")
        if value.is_nested:  # a message holds dense elements
            raise UnsupportedValueError("tensor_conversions.torch sends dense (strided) "
                                        "tensors, not a nested one: pad it first "
                                        "(.to_padded_tensor(0))")
        if value.layout != torch.strided:
            raise UnsupportedValueError(
                f"tensor_conversions.torch sends dense (strided) tensors, not a "
                f"{str(value.layout).removeprefix('torch.')} one: convert it first (.to_dense())")
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
        self.from_view(view).copy_(value)  # a writable view: misaligned storage refused there


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
                    backend: str = "warp", device: Any = None,
                    *, max_loans: int | None = None) -> Any:
    """``with loan_tensor_msg(pub, shape, dtype) as msg:`` a loaned ExperimentalTensor from
    ``pub``'s pool (warp storage on ``device``), published when the block ends; an exception
    publishes nothing. :func:`from_output_tensor_msg` of it returns the same writable torch.Tensor
    every loan of that block (built once). The loan ends at publish: on Warp's cpu device the
    memory is read-only until its next loan (a write through a view kept past publish faults);
    on CUDA such a write is not stopped: don't. See :mod:`tensor_conversions.loan`.
    """
    return _loan.loan_tensor_msg(_ADAPTER, publisher, shape, dtype, backend, device,
                                 max_loans=max_loans)


def from_input_tensor_msg(msg: Any, clone: bool = True) -> torch.Tensor:
    """The tensor of ``msg``: an independent contiguous copy (default) or, with ``clone=False``,
    a zero-copy alias of the storage that keeps the storage alive and refuses writes
    (RuntimeError; so do ``.numpy()`` and ``data_ptr()``: see the module docstring)."""
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
    storage whose row stride is ``step``, which refuses writes (RuntimeError)."""
    return _image.from_input_image_msg(_ADAPTER, msg, clone)


def to_image_msg(value: torch.Tensor, encoding: str, *, backend: str | None = None,
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
                              clone: bool = True) -> torch.Tensor:
    """An ``(N, F)`` tensor of the cloud's points (``F``: a column per field, ``count`` of
    them for a multi-count field): a zero-copy strided view where the layout allows (then
    ``clone`` copies it; the view refuses writes), else one float32 host copy; see
    :mod:`tensor_conversions.pointcloud`."""
    return _pointcloud.from_input_pointcloud_msg(_ADAPTER, msg, fields, clone)


def allocate_pointcloud_msg(width: int, fields: Sequence[str], dtype: torch.dtype | str,
                            height: int = 1, backend: str = "cpu", device: Any = None) -> Any:
    """A new ``sensor_msgs/msg/PointCloud2`` of ``height * width`` points whose ``fields``
    (names) are packed values of one ``dtype`` (``point_step = len(fields) * itemsize``, this
    machine's byte order), storage zeroed (``backend``/``device`` as for tensors)."""
    return _pointcloud.allocate_pointcloud_msg(_ADAPTER, width, fields, dtype, height, backend,
                                               device)


def from_output_pointcloud_msg(msg: Any, fields: Sequence[str] | None = None) -> torch.Tensor:
    """A writable zero-copy ``(N, F)`` view of the cloud's points (``fields``: all by default)
    for filling it in place; the fields must be one strided view (as
    :func:`allocate_pointcloud_msg` makes them), else :class:`InvalidTensorMetadataError`."""
    return _pointcloud.from_output_pointcloud_msg(_ADAPTER, msg, fields)


def loan_pointcloud_msg(publisher: Any, width: int, fields: Sequence[str], dtype: torch.dtype | str,
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
