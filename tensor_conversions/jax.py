"""ExperimentalTensor <-> ``jax.Array``, through ``jax.dlpack.from_dlpack``.

Install with ``pip install warp-buffer[jax]``. JAX imports only compact tensors: a contiguous
payload converts zero-copy (``clone=False``; on the CPU JAX also needs suitably aligned memory,
else it copies), a strided one needs ``clone=True``. JAX arrays are immutable, so there is no
writable view: :func:`from_output_tensor_msg` raises, fill messages with :func:`to_tensor_msg`.
CUDA storage needs a CUDA build of jaxlib; JAX orders its own streams when it imports.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

try:
    import jax
    import jax.dlpack
except ImportError as _error:  # an optional extra: say which
    raise ImportError(f"tensor_conversions.jax needs JAX: "
                      f"pip install 'warp-buffer[jax]' ({_error})") from _error

from . import _api
from .errors import UnsupportedBackendError

__all__ = ["allocate_tensor_msg", "from_input_tensor_msg", "from_output_tensor_msg",
           "to_tensor_msg"]


class _JaxAdapter(_api.DLPackAdapter[jax.Array]):
    name = "jax"
    value_type = jax.Array

    def consume(self, producer: Any) -> jax.Array:
        return jax.dlpack.from_dlpack(producer)


_ADAPTER = _JaxAdapter()


def from_output_tensor_msg(msg: Any) -> jax.Array:
    """Not available: JAX arrays are immutable. Raises :class:`UnsupportedBackendError`."""
    raise UnsupportedBackendError(
        "JAX arrays are immutable and cannot be filled in place; compute the array, then "
        "tensor_conversions.jax.to_tensor_msg(msg, array)")


def allocate_tensor_msg(shape: Sequence[int] | int, dtype: Any, backend: str = "cpu",
                        device: Any = None) -> Any:
    """A new ExperimentalTensor for ``shape``/``dtype`` (a NumPy/JAX dtype), storage as in
    :func:`tensor_conversions.torch.allocate_tensor_msg`."""
    return _api.allocate_tensor_msg(_ADAPTER, shape, dtype, backend, device)


def from_input_tensor_msg(msg: Any, clone: bool = True) -> jax.Array:
    """The tensor of ``msg``: an independent copy (default) or, with ``clone=False``, a
    zero-copy alias of a contiguous payload (treat as read-only)."""
    return _api.from_input_tensor_msg(_ADAPTER, msg, clone)


def to_tensor_msg(msg_or_value: Any, value: Any = None, *, backend: str | None = None,
                  device: Any = None) -> Any:
    """Copy a jax.Array value into a message (``to_tensor_msg(msg, value)`` fills preallocated
    storage, ``to_tensor_msg(value)`` makes a new message on the value's device)."""
    return _api.to_tensor_msg(_ADAPTER, msg_or_value, value, backend=backend, device=device)
