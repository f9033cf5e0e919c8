"""rosidl_buffer: the backend-neutral layer of warp-buffer (``rosidl::Buffer`` in Python).

Nothing here imports Warp or any backend: backends plug in through :mod:`rosidl_buffer.registry`.
"""

from .backend import MAX_BUFFER_DESCRIPTOR_SIZE, BufferBackend, EndpointGroups
from .buffer import Buffer
from .buffer_impl import CPU_BACKEND, BufferImplBase, CpuBufferImpl
from .endpoint import EndpointInfo, EndpointType, local_host_id, parse_acceptable_backends
from .errors import (
    BackendError,
    BackendLoadError,
    BufferOverwrittenError,
    BufferReleasedError,
    CpuBackendRequiredError,
    DescriptorTooLargeError,
    DeserializationError,
    RosidlBufferError,
    SerializationError,
    UnknownBackendError,
    UnknownMessageTypeError,
)

__all__ = [
    "CPU_BACKEND",
    "MAX_BUFFER_DESCRIPTOR_SIZE",
    "BackendError",
    "BackendLoadError",
    "BufferOverwrittenError",
    "BufferReleasedError",
    "Buffer",
    "BufferBackend",
    "BufferImplBase",
    "CpuBackendRequiredError",
    "CpuBufferImpl",
    "DescriptorTooLargeError",
    "DeserializationError",
    "EndpointGroups",
    "EndpointInfo",
    "EndpointType",
    "RosidlBufferError",
    "SerializationError",
    "UnknownBackendError",
    "UnknownMessageTypeError",
    "local_host_id",
    "parse_acceptable_backends",
]
