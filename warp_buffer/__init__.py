"""warp_buffer: the Warp memory domain of rosidl_buffer (backend type ``"warp"``).

A warp buffer is a :class:`rosidl_buffer.Buffer` whose bytes are a 1-D ``wp.array`` of uint8 on
a Warp device (``cuda:N`` where a GPU exists, ``cpu`` otherwise; the default follows Warp's):

- :func:`allocate_buffer` makes one from a size-classed pool (:mod:`warp_buffer.pool`);
- :func:`from_output_buffer` / :func:`from_input_buffer` give write / read handles, ordered by a
  CUDA event (cpu work is synchronous);
- :func:`to_buffer` copies any DLPack-capable source (wp.array, torch, NumPy) into a handle;
- :mod:`warp_buffer.ipc` exports a buffer to a same-host process with zero payload copies (one
  sealed memfd arena per process, CUDA IPC) and imports such exports;
- :mod:`warp_buffer.lease` is the lifetime of local memory: one owner per block, the
  transitions of its write and publish, readers' tokens, and when a block is written again.

Environment switches
--------------------
``WARP_BUFFER_DISABLE_IPC=1``
    No exports: the warp backend serves every peer by CPU fallback, and cpu blocks are private
    memory instead of arena ranges.
``WARP_BUFFER_TEST_HOST_ID`` / ``WARP_BUFFER_TEST_USER_ID`` (tests only)
    The backend pretends its own host id / user id is this value, so peers look foreign and the
    fallback paths can be tested on one machine. The kernel's credential checks keep the real uid.
``WARP_BUFFER_ARENA_GIB`` (default 64)
    Virtual size of a process's arena (address space only: pages exist once touched).
``WARP_BUFFER_EXIT_LINGER_S`` (default 2)
    A cleanly exiting publisher keeps serving its arena this long at most, and only to live peers
    it sent descriptors to that never attached to it (so their queued messages stay readable).
``WARP_BUFFER_POOL_IDLE_S`` (default 10)
    Free pool blocks unused this long are given back to the system.
``WARP_BUFFER_POOL_MAX_IDLE_BYTES`` (default 1 GiB)
    Free pool memory beyond this, per device, is given back at once.
"""

from __future__ import annotations

from . import cuda, errors, ipc, kernels, lease
from .api import (
    ReadHandle,
    WriteHandle,
    allocate_buffer,
    from_input_buffer,
    from_output_buffer,
    to_buffer,
)
from .buffer_impl import WARP_BACKEND, WarpBufferImpl
from .errors import (
    CudaDriverError,
    DescriptorError,
    DeviceMemoryError,
    DeviceUnavailableError,
    EmptyBufferError,
    ExportBoundsError,
    ExportError,
    ExportUnavailableError,
    ForeignExportError,
    HandleError,
    HandleReleasedError,
    InvalidDTypeError,
    InvalidSizeError,
    SizeMismatchError,
    SizeTypeError,
    RecycledBufferError,
    StaleBufferError,
    UnsupportedSourceError,
    WarpBufferError,
    WriteHandleError,
)
from .pool import pool_stats, trim_pools
from .startup import init_warp

__all__ = [
    "WARP_BACKEND",
    "CudaDriverError",
    "DescriptorError",
    "DeviceMemoryError",
    "DeviceUnavailableError",
    "EmptyBufferError",
    "ExportBoundsError",
    "ExportError",
    "ExportUnavailableError",
    "ForeignExportError",
    "HandleError",
    "HandleReleasedError",
    "InvalidDTypeError",
    "InvalidSizeError",
    "ReadHandle",
    "SizeMismatchError",
    "SizeTypeError",
    "RecycledBufferError",
    "StaleBufferError",
    "UnsupportedSourceError",
    "WarpBufferError",
    "WarpBufferImpl",
    "WriteHandle",
    "WriteHandleError",
    "allocate_buffer",
    "cuda",
    "errors",
    "from_input_buffer",
    "from_output_buffer",
    "ipc",
    "kernels",
    "lease",
    "pool_stats",
    "to_buffer",
    "trim_pools",
]

init_warp()  # at import: Warp's banner and CUDA-driver warning go to logging, not stdout
