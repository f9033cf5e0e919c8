"""Endpoint info from liveliness tokens: what backends are told about a peer."""

from __future__ import annotations

from rosidl_buffer import EndpointInfo, EndpointType

from . import wire

__all__ = ["endpoint_info"]


def endpoint_info(token: wire.EndpointToken) -> EndpointInfo:
    """What backends are told about an endpoint, from its liveliness token."""
    return EndpointInfo(
        gid=token.gid,
        node_name=token.node_name,
        node_namespace=token.namespace or "/",
        topic_name=token.topic,
        topic_type=token.type_name,
        endpoint_type=EndpointType.PUBLISHER if token.is_publisher else EndpointType.SUBSCRIPTION,
        host_id=token.locality.host_id,
        process_id=token.locality.process_id,
        user_id=token.locality.user_id,
        supported_backends=token.backends,
    )
