"""How a node reaches its peers: the Zenoh configuration.

Choices, first match wins:

1. ``Node(config=...)``: a ``zenoh.Config``, or the path of a Zenoh JSON5 configuration file.
2. ``Node(router="tcp/host:7447")`` or env ``WARP_BUFFER_ZENOH_ROUTER``: peer mode connected to
   that Zenoh router (``zenohd``), multicast scouting off, gossip on: rmw_zenoh's default layout,
   for use across hosts.
3. env ``ZENOH_SESSION_CONFIG_URI`` (as rmw_zenoh): the path of a Zenoh JSON5 configuration file.
4. The embedded default: peer mode, multicast scouting only on the loopback interface ``lo``,
   listening on ``tcp/127.0.0.1:0``. Processes of one host find each other in about 0.1 s with no
   router and no set-up, and no traffic leaves the host.

The domain id (``Node(domain_id=...)`` or env ``ROS_DOMAIN_ID``, default 0) is the first key
segment of everything a node publishes or advertises, so nodes of different domains never see each
other even when their Zenoh sessions are connected.
"""

from __future__ import annotations

import json
import os
from typing import Any

import zenoh

from .errors import TransportConfigError

__all__ = ["DEFAULT_CONFIG", "ROUTER_ENV", "CONFIG_URI_ENV", "make_config", "resolve_domain_id"]

ROUTER_ENV = "WARP_BUFFER_ZENOH_ROUTER"
CONFIG_URI_ENV = "ZENOH_SESSION_CONFIG_URI"
DOMAIN_ENV = "ROS_DOMAIN_ID"

#: The embedded default (no router): loopback-only peer discovery by multicast scouting.
DEFAULT_CONFIG: dict[str, Any] = {
    "mode": "peer",
    "listen": {"endpoints": ["tcp/127.0.0.1:0"]},
    "scouting": {"multicast": {"enabled": True, "interface": "lo"}, "gossip": {"enabled": True}},
    # Zenoh's SHM transport made CPU-fallback samples slower here (its buffers have no Python
    # buffer protocol, so Python copies in and out); same-host zero copy is the backends' job.
    "transport": {"shared_memory": {"enabled": False}},
}


def _router_config(endpoint: str) -> dict[str, Any]:
    return {
        "mode": "peer",
        "connect": {"endpoints": [endpoint]},
        "listen": {"endpoints": ["tcp/localhost:0"]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": True}},
    }


def make_config(config: zenoh.Config | str | os.PathLike[str] | None = None,
                router: str | None = None) -> zenoh.Config:
    """Build the ``zenoh.Config`` of a node from the choices listed in the module docstring."""
    if isinstance(config, zenoh.Config):
        return config
    try:
        if config is not None:
            return zenoh.Config.from_file(os.fspath(config))
        router = router or os.environ.get(ROUTER_ENV)
        if router:
            return zenoh.Config.from_json5(json.dumps(_router_config(router)))
        uri = os.environ.get(CONFIG_URI_ENV)
        if uri:
            return zenoh.Config.from_file(uri)
        return zenoh.Config.from_json5(json.dumps(DEFAULT_CONFIG))
    except zenoh.ZError as exc:
        raise TransportConfigError(f"invalid Zenoh configuration: {exc}") from exc
    except OSError as exc:
        raise TransportConfigError(f"cannot read Zenoh configuration {config!r}: {exc}") from exc


def resolve_domain_id(domain_id: int | None) -> int:
    """``domain_id``, else env ``ROS_DOMAIN_ID``, else 0; must be a non-negative integer."""
    if domain_id is None:
        text = os.environ.get(DOMAIN_ENV, "").strip()
        try:
            domain_id = int(text) if text else 0
        except ValueError:
            raise TransportConfigError(f"{DOMAIN_ENV}={text!r} is not an integer") from None
    if isinstance(domain_id, bool) or not isinstance(domain_id, int) or domain_id < 0:
        raise TransportConfigError(f"domain id must be a non-negative int, got {domain_id!r}")
    return domain_id
