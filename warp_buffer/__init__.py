"""warp_buffer: the Warp memory domain of rosidl_buffer (backend type ``"warp"``).

A warp buffer is a :class:`rosidl_buffer.Buffer` whose bytes are a 1-D ``wp.array`` of uint8 on
a Warp device (``cuda:N`` where a GPU exists, ``cpu`` otherwise; the default follows Warp's):

- :func:`allocate_buffer` makes one from a size-classed pool (:mod:`warp_buffer.pool`);
- :func:`from_output_buffer` / :func:`from_input_buffer` give write / read handles, ordered by a
  CUDA event or, on cpu, a generation stamp written by a Warp kernel after the write;
- :func:`to_buffer` copies any DLPack-capable source (wp.array, torch, NumPy) into a handle;
- :mod:`warp_buffer.ipc` exports a buffer to a same-host process with zero payload copies
  (shared memory, CUDA IPC) and imports such exports.

Environment switches
--------------------
``WARP_BUFFER_DISABLE_IPC=1``
    No exports: the warp backend serves every peer by CPU fallback, and cpu blocks are private
    memory instead of /dev/shm files.
``WARP_BUFFER_TEST_HOST_ID`` / ``WARP_BUFFER_TEST_USER_ID`` (tests only)
    The backend pretends its own host id / user id is this value, so peers look foreign and the
    fallback paths can be tested on one machine. File ownership checks keep using the real uid.
``WARP_BUFFER_POOL_IDLE_S`` (default 10)
    Free pool blocks unused this long are given back to the system.
``WARP_BUFFER_POOL_MAX_IDLE_BYTES`` (default 1 GiB)
    Free pool memory beyond this, per device, is given back at once.
``WARP_BUFFER_INFLIGHT_GRACE_S`` (default 2)
    An exported block whose descriptors were not all imported (a peer dropped the message) may
    be recycled this long after the last one was issued. Blocks a reader holds are never
    recycled, whatever the time.
``WARP_BUFFER_SYNC_TIMEOUT_S`` (default 2)
    How long an importer waits for the writer's completion stamp.
"""

from __future__ import annotations

from . import errors, ipc, kernels
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
    DescriptorError,
    DeviceUnavailableError,
    EmptyBufferError,
    ExportBoundsError,
    ExportError,
    ExportUnavailableError,
    ForeignExportError,
    HandleError,
    HandleReleasedError,
    InvalidSizeError,
    SizeMismatchError,
    StaleBufferError,
    SyncTimeoutError,
    WarpBufferError,
    WriteHandleError,
)
from .pool import pool_stats, trim_pools
from .startup import init_warp

__all__ = [
    "WARP_BACKEND",
    "DescriptorError",
    "DeviceUnavailableError",
    "EmptyBufferError",
    "ExportBoundsError",
    "ExportError",
    "ExportUnavailableError",
    "ForeignExportError",
    "HandleError",
    "HandleReleasedError",
    "InvalidSizeError",
    "ReadHandle",
    "SizeMismatchError",
    "StaleBufferError",
    "SyncTimeoutError",
    "WarpBufferError",
    "WarpBufferImpl",
    "WriteHandle",
    "WriteHandleError",
    "allocate_buffer",
    "errors",
    "from_input_buffer",
    "from_output_buffer",
    "ipc",
    "kernels",
    "pool_stats",
    "to_buffer",
    "trim_pools",
]

init_warp()  # at import: Warp's banner and CUDA-driver warning go to logging, not stdout
