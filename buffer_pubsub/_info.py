"""Endpoint info from liveliness tokens: what backends are told about a peer."""

from __future__ import annotations

import logging
from collections.abc import Iterable

from rosidl_buffer import BufferBackend, EndpointInfo, EndpointType

from . import wire

__all__ = ["endpoint_gone", "endpoint_info", "unknown_publisher_info"]

_log = logging.getLogger(__name__)


def endpoint_info(token: wire.EndpointToken) -> EndpointInfo:
    """What backends are told about an endpoint, from its liveliness token.

    Cached on the (frozen) token: subscriptions need the publisher's info for every message, and
    EndpointInfo is immutable, so one instance per token serves them all.
    """
    info = token.__dict__.get("_endpoint_info")
    if info is None:
        info = _build(token)
        object.__setattr__(token, "_endpoint_info", info)
    return info


def _build(token: wire.EndpointToken) -> EndpointInfo:
    # An endpoint that is not ours carries no locality: backends see an unknown host ("").
    locality = token.locality or _UNKNOWN
    return EndpointInfo(
        gid=token.gid,
        node_name=token.node_name,
        node_namespace=token.namespace or "/",
        topic_name=token.topic,
        topic_type=token.type_name,
        endpoint_type=EndpointType.PUBLISHER if token.is_publisher else EndpointType.SUBSCRIPTION,
        host_id=locality.host_id,
        process_id=locality.process_id,
        user_id=locality.user_id,
        supported_backends=token.backends or {},
    )


_UNKNOWN = wire.Locality()


def unknown_publisher_info(gid: bytes, topic: str, type_name: str) -> EndpointInfo:
    """What backends are told about a publisher known by its gid alone (a sample arrived before
    its token, or it has none): as rmw_zenoh's minimal endpoint info, the gid and the kind, no
    locality. A backend judges such a publisher by what its descriptor names."""
    return EndpointInfo(
        gid=gid, node_name="", node_namespace="", topic_name=topic, topic_type=type_name,
        endpoint_type=EndpointType.PUBLISHER, host_id="", process_id=0, user_id=-1)


def endpoint_gone(backends: Iterable[BufferBackend], info: EndpointInfo) -> None:
    """Tell each backend that an endpoint it was told about (created or discovered) is gone, so
    it can drop what it keeps for it; a failing hook is logged, never raised (teardown)."""
    for backend in backends:
        hook = getattr(backend, "on_endpoint_gone", None)  # older backends may lack it
        if hook is None:
            continue
        try:
            hook(info)
        except Exception:
            _log.exception("%s.on_endpoint_gone failed", type(backend).__name__)
