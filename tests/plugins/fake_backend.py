"""A fake non-CPU backend ("fake") for tests, plus deliberately broken plugin objects.

``FakeBufferImpl`` keeps its bytes in a private NumPy array that ``Buffer`` cannot see, so every
CPU-only operation must refuse it. ``FakeBackend`` describes a buffer by a handle into a
process-local "device memory" table, which ``from_descriptor_with_endpoint`` looks up again.
"""

from __future__ import annotations

import itertools

import numpy as np

from rosidl_buffer import (
    BackendError,
    BufferBackend,
    BufferImplBase,
    CpuBufferImpl,
    EndpointInfo,
)
from rosidl_buffer.messages import get_message_type, register_message_definitions

FAKE_BACKEND = "fake"
DESCRIPTOR_TYPE = "warp_buffer_test_msgs/msg/FakeDescriptor"

register_message_definitions({
    DESCRIPTOR_TYPE: "uint64 handle\nuint32 size\nstring note\n",
})


class FakeBufferImpl(BufferImplBase):
    """Bytes (or any dtype) held where Buffer's CPU paths cannot reach them."""

    def __init__(self, data, dtype=np.uint8) -> None:
        self.dtype = np.dtype(dtype)
        if isinstance(data, (bytes, bytearray)):
            data = np.frombuffer(data, np.uint8)
        self.device_array = np.array(data, dtype=self.dtype).reshape(-1)

    def get_backend_type(self) -> str:
        return FAKE_BACKEND

    def size(self) -> int:
        return self.device_array.shape[0]

    def to_cpu(self) -> CpuBufferImpl:
        return CpuBufferImpl(self.device_array.copy(), self.dtype)

    def clone(self) -> FakeBufferImpl:
        return FakeBufferImpl(self.device_array.copy(), self.dtype)


#: handle -> contents, standing in for memory another process could map.
DEVICE_MEMORY: dict[int, np.ndarray] = {}
_handles = itertools.count(1)


class FakeBackend(BufferBackend):
    """A well-behaved plugin. ``note`` pads the descriptor (to test the size limit)."""

    def __init__(self, note: str = "") -> None:
        self.note = note
        self.rebuilt_from: list[EndpointInfo] = []

    def get_backend_type(self) -> str:
        return FAKE_BACKEND

    def get_backend_metadata(self) -> str:
        return "fake-metadata-v1"

    def get_descriptor_type(self) -> type:
        return get_message_type(DESCRIPTOR_TYPE)

    def create_descriptor_with_endpoint(self, impl, endpoint_info):
        handle = next(_handles)
        DEVICE_MEMORY[handle] = impl.device_array.copy()
        return self.get_descriptor_type()(handle=handle, size=impl.size(), note=self.note)

    def from_descriptor_with_endpoint(self, descriptor, endpoint_info):
        self.rebuilt_from.append(endpoint_info)
        memory = DEVICE_MEMORY.get(descriptor.handle)
        if memory is None or descriptor.size > memory.shape[0]:
            raise BackendError(f"no fake allocation {descriptor.handle} of {descriptor.size} bytes")
        return FakeBufferImpl(memory[: descriptor.size])


class PluginBackend(FakeBackend):
    """The fake backend under a name that no other test distribution registers."""

    NAME = "rosidl_buffer_test_fake"

    def get_backend_type(self) -> str:
        return self.NAME


class RaisingBackend(FakeBackend):
    """Registered fine, but its constructor fails."""

    def __init__(self) -> None:
        raise RuntimeError("cannot open the fake device")


def not_a_backend() -> object:
    """A factory that returns something that is not a BufferBackend."""
    return object()
