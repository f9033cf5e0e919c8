"""``BufferBackend``: the plugin interface a memory domain implements (the six methods).

Mirrors ``rosidl::BufferBackend``. A transport calls :meth:`on_creating_endpoint` for each local
endpoint, :meth:`on_discovering_endpoint` for each peer, :meth:`on_endpoint_gone` when either
goes away, and then, per publish and peer,
:meth:`create_descriptor_with_endpoint` on the publisher side and
:meth:`from_descriptor_with_endpoint` on the subscriber side.
"""

from __future__ import annotations

import abc
from collections.abc import Mapping, Sequence
from typing import Any

from .buffer_impl import BufferImplBase
from .endpoint import EndpointInfo

__all__ = ["BufferBackend", "MAX_BUFFER_DESCRIPTOR_SIZE", "EndpointGroups"]

#: Upper bound on a serialized descriptor, in bytes (``rosidl::kMaxBufferDescriptorSize``).
MAX_BUFFER_DESCRIPTOR_SIZE = 4096

#: Groups of endpoints a backend may serve together (indices into ``existing_endpoints``).
EndpointGroups = list[set[int]]


class BufferBackend(abc.ABC):
    """A buffer backend plugin. Registered under the entry point group ``rosidl_buffer.backends``
    with the same name that :meth:`get_backend_type` returns."""

    # -- identity ------------------------------------------------------------------------------
    @abc.abstractmethod
    def get_backend_type(self) -> str:
        """Short name, e.g. ``"warp"``; what subscribers put in acceptable_buffer_backends."""

    def get_backend_metadata(self) -> str:
        """What a peer needs to judge compatibility, advertised in discovery. Default empty."""
        return ""

    # -- descriptors ---------------------------------------------------------------------------
    @abc.abstractmethod
    def get_descriptor_type(self) -> type:
        """The message class of this backend's descriptor (a generated message type)."""

    def create_empty_descriptor(self) -> Any:
        """A default-constructed descriptor, to be filled by deserialization."""
        return self.get_descriptor_type()()

    @abc.abstractmethod
    def create_descriptor_with_endpoint(
        self, impl: BufferImplBase, endpoint_info: EndpointInfo
    ) -> Any | None:
        """Describe ``impl`` for the peer ``endpoint_info``, or return None to serve it by CPU."""

    @abc.abstractmethod
    def from_descriptor_with_endpoint(
        self, descriptor: Any, endpoint_info: EndpointInfo
    ) -> BufferImplBase:
        """Rebuild the buffer a publisher (``endpoint_info``) described. Owns the result."""

    # -- discovery hooks -----------------------------------------------------------------------
    def on_creating_endpoint(self, endpoint_info: EndpointInfo) -> None:
        """A local publisher or subscription was created. Default: nothing."""

    def on_discovering_endpoint(
        self,
        endpoint_info: EndpointInfo,
        existing_endpoints: Sequence[EndpointInfo],
        endpoint_supported_backends: Mapping[str, str],
    ) -> tuple[bool, EndpointGroups]:
        """May this backend serve the peer? Default: yes if the peer advertises this backend.

        ``False`` routes the peer to CPU serialization for good. The groups are for backends that
        serve several endpoints with one export; most return an empty list.
        """
        return self.get_backend_type() in endpoint_supported_backends, []

    def on_endpoint_gone(self, endpoint_info: EndpointInfo) -> None:
        """An endpoint this backend was told about (through :meth:`on_creating_endpoint` or
        :meth:`on_discovering_endpoint`) is gone: drop what is kept for it. Not in the C++
        interface (which never forgets a peer); the transport calls it when discovery reports
        the endpoint's departure. Default: nothing."""
