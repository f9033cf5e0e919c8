"""Test helpers: per-framework dtype tables and bit-exact comparison of tensors.

Used by this project's tests and useful to downstream tests; needs torch, NumPy and Warp.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
import warp as wp

from . import numpy as tc_numpy
from . import torch as tc_torch
from . import warp as tc_warp
from .dlpack import import_warp
from .dtypes import SUPPORTED_DTYPES

MODULES = {"torch": tc_torch, "numpy": tc_numpy, "warp": tc_warp}

#: dtypes each framework module supports (checked against the package in the tests).
FRAMEWORK_DTYPES = {
    "torch": list(SUPPORTED_DTYPES),
    "numpy": [n for n in SUPPORTED_DTYPES if n != "bfloat16"],
    "warp": [n for n in SUPPORTED_DTYPES if not n.startswith("complex")],
}
SHARED_DTYPES = [n for n in FRAMEWORK_DTYPES["torch"]
                 if all(n in FRAMEWORK_DTYPES[f] for f in MODULES)]



def framework_dtype(framework: str, name: str) -> Any:
    if framework == "torch":
        return getattr(torch, name)
    if framework == "numpy":
        return np.dtype(name)
    return getattr(wp, name)


def itemsize(name: str) -> int:
    return SUPPORTED_DTYPES[name].itemsize


def random_bits(name: str, shape: tuple[int, ...], seed: int = 0) -> np.ndarray:
    """Random raw bytes of ``shape`` elements of ``name`` (bool: only 0/1), shape (*shape, size)."""
    rng = np.random.default_rng(seed)
    size = itemsize(name)
    raw = rng.integers(0, 256, size=(*shape, size), dtype=np.uint8)
    if name == "bool":
        raw &= 1
    return raw


def make_value(framework: str, name: str, raw: np.ndarray) -> Any:
    """A framework value whose element bytes are ``raw`` (shape (*shape, itemsize))."""
    shape = raw.shape[:-1]
    flat = torch.from_numpy(np.ascontiguousarray(raw).reshape(-1).copy())
    t = flat.view(getattr(torch, name)).reshape(shape) if flat.numel() else torch.empty(
        shape, dtype=getattr(torch, name))
    if framework == "torch":
        return t
    if framework == "numpy":
        return t.numpy().copy()
    import_warp()
    return wp.clone(wp.from_dlpack(t.reshape(shape or (1,))))


def to_raw(value: Any) -> np.ndarray:
    """The element bytes of any framework value, shape (*shape, itemsize), independent copy."""
    shape = tuple(value.shape)
    if isinstance(value, np.ndarray):
        array = np.ascontiguousarray(value).reshape(-1)
        return array.view(np.uint8).reshape(*shape, value.dtype.itemsize).copy()
    t = value if isinstance(value, torch.Tensor) else torch.from_dlpack(value)
    # a copy: a read-only input view refuses .numpy()
    flat = t.clone(memory_format=torch.contiguous_format).reshape(-1)
    size = flat.element_size()
    if flat.dtype.is_complex:
        flat = torch.view_as_real(flat).reshape(-1)
    return flat.view(torch.uint8).numpy().reshape(*shape, size).copy()
