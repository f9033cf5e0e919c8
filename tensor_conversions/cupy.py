"""ExperimentalTensor <-> ``cupy.ndarray``, through CuPy's own DLPack import.

Install with ``pip install warp-buffer[cupy]`` (a CUDA machine; tests skip elsewhere). CuPy
addresses device memory only: warp storage on ``cuda:N`` converts zero-copy, strided layouts
included; host storage needs ``clone=True`` (one host -> device copy). Handles are opened on
CuPy's current stream, so writes and reads are ordered where CuPy runs them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

try:
    import cupy
except ImportError as _error:  # an optional extra: say which
    raise ImportError(f"tensor_conversions.cupy needs CuPy: "
                      f"pip install 'warp-buffer[cupy]' ({_error})") from _error

from . import _api
from .dlpack import TensorView, external_stream

__all__ = ["allocate_tensor_msg", "from_input_tensor_msg", "from_output_tensor_msg",
           "to_tensor_msg"]


class _CupyAdapter(_api.DLPackAdapter[cupy.ndarray]):
    name = "cupy"
    value_type = cupy.ndarray
    contiguous_only = False
    host = False

    def stream(self, device: str) -> Any:
        return external_stream(device, cupy.cuda.get_current_stream().ptr or 1)

    def consume(self, producer: Any) -> cupy.ndarray:
        return cupy.from_dlpack(producer)

    def clone(self, view: TensorView) -> cupy.ndarray:
        if view.device == "cpu":
            return cupy.asarray(view.carrier)  # host -> device copy
        return view.reshape_result(cupy.from_dlpack(view)).copy()

    def copy_into(self, view: TensorView, value: Any) -> None:
        if view.device == "cpu":
            view.carrier[...] = cupy.asnumpy(value)
            return
        view.reshape_result(cupy.from_dlpack(view))[...] = value  # on CuPy's current stream


_ADAPTER = _CupyAdapter()


def from_output_tensor_msg(msg: Any) -> cupy.ndarray:
    """A writable zero-copy array over warp storage on a CUDA device."""
    return _api.from_output_tensor_msg(_ADAPTER, msg)


def allocate_tensor_msg(shape: Sequence[int] | int, dtype: Any, backend: str = "cpu",
                        device: Any = None) -> Any:
    """A new ExperimentalTensor for ``shape``/``dtype`` (a NumPy dtype), storage as in
    :func:`tensor_conversions.torch.allocate_tensor_msg`."""
    return _api.allocate_tensor_msg(_ADAPTER, shape, dtype, backend, device)


def from_input_tensor_msg(msg: Any, clone: bool = True) -> cupy.ndarray:
    """The tensor of ``msg``: an independent copy (default) or, with ``clone=False``, a
    zero-copy alias of a contiguous payload (treat as read-only)."""
    return _api.from_input_tensor_msg(_ADAPTER, msg, clone)


def to_tensor_msg(msg_or_value: Any, value: Any = None, *, backend: str | None = None,
                  device: Any = None) -> Any:
    """Copy a cupy.ndarray value into a message (``to_tensor_msg(msg, value)`` fills preallocated
    storage, ``to_tensor_msg(value)`` makes a new message on the value's device)."""
    return _api.to_tensor_msg(_ADAPTER, msg_or_value, value, backend=backend, device=device)
