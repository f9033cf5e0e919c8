"""ExperimentalTensor <-> ONNX Runtime ``OrtValue``, through ``OrtValue.from_dlpack``.

Install with ``pip install warp-buffer[onnx]`` (``onnxruntime``, CPU; ``onnxruntime-gpu`` for
CUDA memory). ONNX Runtime imports and exports DLPack on its public ``OrtValue`` (tested with 1.32;
earlier releases kept it on a private class), contiguous tensors only: a contiguous
payload converts zero-copy (``clone=False``), a strided one needs ``clone=True``. An ``OrtValue``
is an inference input, not a buffer to fill, so :func:`from_output_tensor_msg` raises; outputs
go back with :func:`to_tensor_msg` (they export DLPack).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

try:
    import onnxruntime as ort
except ImportError as _error:  # an optional extra: say which
    raise ImportError(f"tensor_conversions.onnx needs ONNX Runtime: "
                      f"pip install 'warp-buffer[onnx]' ({_error})") from _error

from . import _api
from .dtypes import DLDataTypeCode, DType, dtype_from_name
from .errors import UnsupportedBackendError, UnsupportedDTypeError

__all__ = ["allocate_tensor_msg", "from_input_tensor_msg", "from_output_tensor_msg",
           "to_tensor_msg"]

_ORT_NAMES = {"float": "float32", "double": "float64"}  # "tensor(float)" -> canonical names


class _OrtAdapter(_api.DLPackAdapter[ort.OrtValue]):
    name = "onnx"
    value_type = ort.OrtValue

    def check_dtype(self, dtype: DType) -> None:
        if dtype.code == DLDataTypeCode.COMPLEX:  # (its NumPy and DLPack bridges refuse them)
            raise UnsupportedDTypeError(f"ONNX Runtime's OrtValue has no {dtype.name} tensors")

    def consume(self, producer: Any) -> ort.OrtValue:
        try:
            return ort.OrtValue.from_dlpack(producer.__dlpack__())
        except RuntimeError as exc:  # its DLPack import refuses a dtype (bool in some releases)
            raise UnsupportedDTypeError(f"ONNX Runtime cannot import this tensor through "
                                        f"DLPack ({exc}); clone=True copies it instead") from None

    def reshape(self, view: Any, tensor: ort.OrtValue) -> ort.OrtValue:
        return tensor  # OrtValues cannot be reshaped: a scalar behind Warp stays shape (1,)

    def clone(self, view: Any) -> ort.OrtValue:
        carrier = view.carrier
        if type(carrier) is np.ndarray:
            return ort.OrtValue.ortvalue_from_numpy(np.array(carrier, order="C", copy=True))
        return super().clone(view)

    def copy_into(self, view: Any, value: Any) -> None:
        carrier = view.carrier
        if type(carrier) is np.ndarray and value.device_name().lower() == "cpu":
            # its own NumPy export keeps bool (its DLPack export made it uint8 in 1.30)
            np.copyto(carrier, value.numpy().reshape(carrier.shape), casting="no")
            return
        super().copy_into(view, value)

    def shape_dtype(self, value: Any) -> tuple[tuple[int, ...], DType]:
        name = value.data_type().removeprefix("tensor(").removesuffix(")")
        return tuple(value.shape()), dtype_from_name(_ORT_NAMES.get(name, name))


_ADAPTER = _OrtAdapter()


def from_output_tensor_msg(msg: Any) -> ort.OrtValue:
    """Not available: an OrtValue is not filled in place. Raises
    :class:`UnsupportedBackendError`."""
    raise UnsupportedBackendError(
        "ONNX Runtime values are not filled in place; run the session, then "
        "tensor_conversions.onnx.to_tensor_msg(msg, output)")


def allocate_tensor_msg(shape: Sequence[int] | int, dtype: Any, backend: str = "cpu",
                        device: Any = None) -> Any:
    """A new ExperimentalTensor for ``shape``/``dtype`` (a NumPy dtype), storage as in
    :func:`tensor_conversions.torch.allocate_tensor_msg`."""
    return _api.allocate_tensor_msg(_ADAPTER, shape, dtype, backend, device)


def from_input_tensor_msg(msg: Any, clone: bool = True) -> ort.OrtValue:
    """The tensor of ``msg``: an independent copy (default) or, with ``clone=False``, a
    zero-copy alias of a contiguous payload (treat as read-only)."""
    return _api.from_input_tensor_msg(_ADAPTER, msg, clone)


def to_tensor_msg(msg_or_value: Any, value: Any = None, *, backend: str | None = None,
                  device: Any = None) -> Any:
    """Copy a OrtValue value into a message (``to_tensor_msg(msg, value)`` fills preallocated
    storage, ``to_tensor_msg(value)`` makes a new message on the value's device)."""
    return _api.to_tensor_msg(_ADAPTER, msg_or_value, value, backend=backend, device=device)
