"""What a node sees of the ROS 2 graph of its domain, in rclpy's shapes.

Every endpoint and node announced through ``@ros2_lv`` liveliness tokens is listed, ours and
those of any rmw_zenoh node (``rmw_zenoh_cpp`` 0.10.5+ advertises the buffer backends of
buffer-aware endpoints; older ones and other types advertise none). :class:`TopicEndpointInfo`
is rclpy's ``TopicEndpointInfo`` plus what this transport adds: the backends an endpoint
advertises (the "Buffer backends:" line of ``ros2 topic info -v``) and, for our own endpoints,
where they live.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

from . import wire

__all__ = ["EndpointKind", "NodeInfo", "TopicEndpointInfo"]


class EndpointKind(enum.Enum):
    """rclpy's ``TopicEndpointTypeEnum`` names."""

    PUBLISHER = "PUBLISHER"
    SUBSCRIPTION = "SUBSCRIPTION"


@dataclass(frozen=True)
class NodeInfo:
    """A node of the graph (``ros2 node list`` shows ``full_name``)."""

    name: str
    namespace: str  # "/" for the root namespace, as rclpy reports it
    enclave: str
    zid: str  # the Zenoh session of its process

    @property
    def full_name(self) -> str:
        return f"{self.namespace.rstrip('/')}/{self.name}"


@dataclass(frozen=True)
class TopicEndpointInfo:
    """One publisher or subscription of a topic, as its liveliness token announces it."""

    node_name: str
    node_namespace: str  # "/" for the root namespace, as rclpy reports it
    topic_name: str
    topic_type: str  # pkg/msg/Name
    topic_type_hash: str  # RIHS01_<hex>
    endpoint_type: EndpointKind
    endpoint_gid: bytes
    qos_profile: wire.QoSProfile
    #: The buffer backends it advertises, name -> metadata; None when it advertises none (a type
    #: without a top-level uint8[], a transient-local endpoint, a pre-0.10.5 rmw_zenoh node).
    backends: Mapping[str, str] | None = field(compare=False)
    #: Where it lives, for endpoints of warp-buffer (None for any other implementation).
    locality: wire.Locality | None = None
    zid: str = ""

    @property
    def is_ours(self) -> bool:
        """Declared by warp-buffer (any other ROS 2 implementation: False)."""
        return self.locality is not None

    @classmethod
    def from_token(cls, token: wire.EndpointToken) -> TopicEndpointInfo:
        return cls(
            node_name=token.node_name,
            node_namespace=token.namespace or "/",
            topic_name=token.topic,
            topic_type=token.type_name,
            topic_type_hash=token.type_hash,
            endpoint_type=(EndpointKind.PUBLISHER if token.is_publisher
                           else EndpointKind.SUBSCRIPTION),
            endpoint_gid=token.gid,
            qos_profile=token.qos,
            backends=None if token.backends is None else MappingProxyType(dict(token.backends)),
            locality=token.locality,
            zid=token.zid,
        )


def node_info(token: wire.NodeToken) -> NodeInfo:
    return NodeInfo(token.name, token.namespace or "/", token.enclave or "/", token.zid)
