"""Endpoint info from liveliness tokens: what backends are told about a peer."""

from __future__ import annotations

import logging
from collections.abc import Iterable

from rosidl_buffer import BufferBackend, EndpointInfo, EndpointType

from . import wire

__all__ = ["endpoint_gone", "endpoint_info"]

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
