"""A test-only rosidl_buffer backend named ``fake``, registered by a static dist-info directory.

Put ``tests/fake_backend`` on ``sys.path`` (or ``PYTHONPATH``) and call
``rosidl_buffer.registry.refresh()``. The buffer lives in a private NumPy array; the descriptor
carries the bytes inline, so it only serves payloads under the 4096-byte descriptor limit. It
refuses peers on another host, and peers whose advertised metadata differs from its own; a buffer
made with ``stale=True`` yields a descriptor that the reader rejects with a typed error.
"""

from __future__ import annotations

import os

import numpy as np

from rosidl_buffer import BackendError, BufferBackend, BufferImplBase, CpuBufferImpl, local_host_id
from rosidl_buffer.messages import get_message_type

NAME = "fake"
MAGIC = 0x46414B45
METADATA = "fake-v1"


class FakeBufferImpl(BufferImplBase):
    def __init__(self, data: np.ndarray, stale: bool = False) -> None:
        self.array = np.ascontiguousarray(data, dtype=np.uint8).reshape(-1)
        self.stale = stale

    def get_backend_type(self) -> str:
        return NAME

    def size(self) -> int:
        return int(self.array.shape[0])

    def to_cpu(self) -> CpuBufferImpl:
        return CpuBufferImpl.wrap(self.array.copy())

    def clone(self) -> FakeBufferImpl:
        return FakeBufferImpl(self.array.copy(), self.stale)


class FakeBufferBackend(BufferBackend):
    def __init__(self) -> None:
        self.created: list = []  # endpoints announced through on_creating_endpoint
        self.discovered: list = []
        self.gone: list = []  # endpoints reported gone through on_endpoint_gone

    def get_backend_type(self) -> str:
        return NAME

    def get_backend_metadata(self) -> str:
        return METADATA

    def get_descriptor_type(self) -> type:
        return get_message_type("fake_buffer_backend_msgs/msg/FakeBufferDescriptor")

    def on_creating_endpoint(self, endpoint_info) -> None:
        self.created.append(endpoint_info)

    def on_discovering_endpoint(self, endpoint_info, existing_endpoints, endpoint_supported_backends):
        self.discovered.append(endpoint_info)
        return endpoint_supported_backends.get(NAME) == METADATA, []

    def on_endpoint_gone(self, endpoint_info) -> None:
        self.gone.append(endpoint_info)

    def create_descriptor_with_endpoint(self, impl, endpoint_info):
        if not isinstance(impl, FakeBufferImpl) or endpoint_info.host_id != local_host_id():
            return None
        return self.get_descriptor_type()(
            magic=0 if impl.stale else MAGIC, origin_pid=os.getpid(), data=impl.array)

    def from_descriptor_with_endpoint(self, descriptor, endpoint_info) -> FakeBufferImpl:
        if descriptor.magic != MAGIC:
            raise BackendError(f"stale fake descriptor (magic {descriptor.magic:#x})")
        return FakeBufferImpl(np.array(descriptor.data, dtype=np.uint8))
