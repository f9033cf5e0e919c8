"""How a node reaches its peers: the Zenoh configuration.

Choices, first match wins:

1. ``Node(config=...)``: a ``zenoh.Config``, or the path of a Zenoh JSON5 configuration file.
2. ``Node(router="tcp/host:7447")`` or env ``WARP_BUFFER_ZENOH_ROUTER``: Zenoh *client* mode
   connected to that router (``warp-buffer router``, or any Zenoh router such as rmw_zenoh's
   ``rmw_zenohd``), multicast scouting off: for use across hosts. Client, not peer, mode: Zenoh
   1.10's routers no longer broker data between peers of their own region (the old
   ``peers_failover_brokering`` is gone), so two peers that cannot open a link to each other (on
   hosts that cannot reach each other's listening addresses, or in separate network namespaces)
   exchanged nothing through a router; a client sends everything through its router. A node
   waits up to ``WARP_BUFFER_ZENOH_CONNECT_TIMEOUT_S`` (default 10 s) for the router, warning
   after a few seconds, then raises :class:`TransportConfigError`.
3. env ``ZENOH_SESSION_CONFIG_URI`` (as rmw_zenoh): the path of a Zenoh JSON5 configuration file.
4. The embedded default: peer mode, multicast scouting only on the loopback interface ``lo``,
   listening on ``tcp/127.0.0.1:0``. Processes of one host find each other in about 0.1 s with no
   router and no set-up, and no traffic leaves the host. Like rmw_zenoh's default session, it
   also connects to a router on this host (``tcp/localhost:7447``: ``rmw_zenohd``, or ``warp-buffer
   router``) when one runs, retrying in the background when none does: a node joins the ROS 2
   graph of its host with nothing set.

Then env ``ZENOH_CONFIG_OVERRIDE`` (as rmw_zenoh: ``key=value`` pairs separated by ``;``, each
key a ``/`` path into the configuration, each value JSON5, e.g.
``'mode="client";connect/endpoints=["tcp/192.168.1.3:7447"]'``) changes any of 2.-4. and the
router's configuration; an invalid pair raises :class:`TransportConfigError` naming it.

Configuration files (``config=``, ``ZENOH_SESSION_CONFIG_URI``) are read here, and an error names
the file. :data:`ROUTER_DEFAULTS` is the configuration of ``warp-buffer router``: the defaults of
rmw_zenoh's router (``DEFAULT_RMW_ZENOH_ROUTER_CONFIG.json5``).

The domain id (``Node(domain_id=...)`` or env ``ROS_DOMAIN_ID``, default 0) is the first key
segment of everything a node publishes or advertises, so nodes of different domains never see each
other even when their Zenoh sessions are connected.
"""

from __future__ import annotations

import json
import os
import re
from typing import Any

import zenoh

from .errors import TransportConfigError

__all__ = ["CONFIG_URI_ENV", "CONNECT_TIMEOUT_ENV", "DEFAULT_CONFIG", "DROP_FRAGMENTS_WAIT_US",
           "LOCAL_ROUTER", "NO_SHARED_MEMORY", "OVERRIDE_ENV", "ROUTER_DEFAULTS", "ROUTER_ENV",
           "apply_overrides", "connect_timeout_s", "make_config",
           "make_router_config", "resolve_domain_id", "zenoh_error_text"]

ROUTER_ENV = "WARP_BUFFER_ZENOH_ROUTER"
CONFIG_URI_ENV = "ZENOH_SESSION_CONFIG_URI"
OVERRIDE_ENV = "ZENOH_CONFIG_OVERRIDE"
#: Where rmw_zenoh's sessions look for their router (its DEFAULT_RMW_ZENOH_SESSION_CONFIG).
LOCAL_ROUTER = "tcp/localhost:7447"
CONNECT_TIMEOUT_ENV = "WARP_BUFFER_ZENOH_CONNECT_TIMEOUT_S"
DOMAIN_ENV = "ROS_DOMAIN_ID"
DEFAULT_CONNECT_TIMEOUT_S = 10.0

#: How long (us) a keep-last message may take to queue its fragments (see DEFAULT_CONFIG).
DROP_FRAGMENTS_WAIT_US = 500_000
#: Zenoh's queue of data batches per link (see DEFAULT_CONFIG).
DATA_QUEUE_BATCHES = 8

#: Zenoh's SHM transport off, in every configuration we make: it made CPU-fallback samples
#: slower here (its buffers have no Python buffer protocol, so Python copies in and out), and
#: it names segments in /dev/shm (``<id>.zenoh``) that a killed process leaves behind.
#: Same-host zero copy is the backends' job.
NO_SHARED_MEMORY: dict[str, Any] = {"enabled": False}

#: The embedded default (no router): loopback-only peer discovery by multicast scouting.
DEFAULT_CONFIG: dict[str, Any] = {
    "mode": "peer",
    "listen": {"endpoints": ["tcp/127.0.0.1:0"]},
    # rmw_zenoh's: a router of this host when there is one; a peer never fails for its absence
    # and retries in the background (1 s, doubling to 4 s).
    "connect": {"endpoints": [LOCAL_ROUTER], "timeout_ms": {"router": -1, "peer": -1,
                                                            "client": 0},
                "exit_on_failure": {"router": False, "peer": False, "client": True},
                "retry": {"period_init_ms": 1000, "period_max_ms": 4000,
                          "period_increase_factor": 2}},
    "scouting": {"multicast": {"enabled": True, "interface": "lo"}, "gossip": {"enabled": True}},
    "transport": {
        "shared_memory": NO_SHARED_MEMORY,
        # A keep-last (DROP) message that needs many fragments may take this long to queue them
        # all before the rest is dropped (Zenoh's default, 50 ms, lost every CPU message over
        # ~40 MiB on loopback here, ~6 MB on 1 GbE, even with no congestion). A peer already
        # frozen still costs 1 ms a message (wait_before_drop): only the message in flight
        # when it froze waits up to this.
        "link": {"tx": {"queue": {
            "congestion_control": {
                "drop": {"max_wait_before_drop_fragments": DROP_FRAGMENTS_WAIT_US}},
            # Zenoh's default, 2 batches of 64 KiB, holds less than one 300 KB frame: a
            # keep-last frame was dropped whenever the reader stalled for one frame period
            # (a loaded host's hiccup). 8 batches ride out a few frames' worth.
            "size": {"data": DATA_QUEUE_BATCHES}}}},
    },
}


#: ``warp-buffer router``: rmw_zenoh's router defaults (listen on every address at port 7447,
#: multicast scouting off, gossip on, peers told only of the router, timestamps on), Zenoh's
#: SHM transport off (see NO_SHARED_MEMORY).
ROUTER_DEFAULTS: dict[str, Any] = {
    "mode": "router",
    "listen": {"endpoints": ["tcp/[::]:7447"]},
    "connect": {"endpoints": []},
    "scouting": {
        "multicast": {"enabled": False},
        "gossip": {"enabled": True, "multihop": False,
                   "target": {"router": ["router", "peer"], "peer": ["router"]},
                   "autoconnect": {"router": [], "peer": ["router", "peer"]}},
    },
    "timestamping": {"enabled": {"router": True, "peer": True, "client": True}},
    "queries_default_timeout": 600000,
    "transport": {"shared_memory": NO_SHARED_MEMORY},
}


def connect_timeout_s() -> float:
    """How long a node waits for its router: env ``WARP_BUFFER_ZENOH_CONNECT_TIMEOUT_S``."""
    text = os.environ.get(CONNECT_TIMEOUT_ENV, "").strip()
    try:
        value = float(text) if text else DEFAULT_CONNECT_TIMEOUT_S
    except ValueError:
        raise TransportConfigError(f"{CONNECT_TIMEOUT_ENV}={text!r} is not a number") from None
    if not value > 0:
        raise TransportConfigError(f"{CONNECT_TIMEOUT_ENV} must be > 0, got {text!r}")
    return value


def _client_config(endpoint: str) -> dict[str, Any]:
    return {
        "mode": "client",
        "connect": {"endpoints": [endpoint], "timeout_ms": int(connect_timeout_s() * 1000)},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"shared_memory": NO_SHARED_MEMORY,
                      "link": {"tx": {"queue": {"size": {"data": DATA_QUEUE_BATCHES}}}}},
    }


def _from_json(data: dict[str, Any], what: str) -> zenoh.Config:
    try:
        return zenoh.Config.from_json5(json.dumps(data))
    except zenoh.ZError as exc:
        raise TransportConfigError(f"invalid Zenoh configuration ({what}): {zenoh_error_text(exc)}") from exc


def _from_file(path: str, source: str) -> zenoh.Config:
    """Read a Zenoh JSON5 file; errors name the file and where its name came from."""
    if not os.path.isfile(path):
        raise TransportConfigError(f"Zenoh configuration file {path!r} ({source}) does not exist"
                                   if not os.path.exists(path) else
                                   f"Zenoh configuration {path!r} ({source}) is not a file")
    try:
        return zenoh.Config.from_file(path)
    except zenoh.ZError as exc:
        raise TransportConfigError(
            f"invalid Zenoh configuration file {path!r} ({source}): {zenoh_error_text(exc)}") from exc


def zenoh_error_text(exc: BaseException) -> str:
    """Zenoh's message without the Rust source location it appends (``at .../lib.rs:1486.``)."""
    return re.sub(r"\s+at \S+\.rs:\d+\.?", "", str(exc)).strip()


def make_config(config: zenoh.Config | str | os.PathLike[str] | None = None,
                router: str | None = None) -> zenoh.Config:
    """Build the ``zenoh.Config`` of a node from the choices listed in the module docstring.

    Raises:
        TransportConfigError: a missing or invalid file (named), or an invalid router endpoint.
    """
    if isinstance(config, zenoh.Config):
        return config
    if config is not None:
        return _from_file(os.fspath(config), "Node(config=...)")
    router = router or os.environ.get(ROUTER_ENV)
    if router:
        return apply_overrides(_from_json(_client_config(router), f"router {router!r}"))
    uri = os.environ.get(CONFIG_URI_ENV)
    if uri:
        return apply_overrides(_from_file(uri, f"env {CONFIG_URI_ENV}"))
    return apply_overrides(_from_json(DEFAULT_CONFIG, "embedded default"))


def apply_overrides(config: zenoh.Config) -> zenoh.Config:
    """``config`` with env ``ZENOH_CONFIG_OVERRIDE``'s pairs inserted (see the module doc),
    split as rmw_zenoh splits them: at each ``;``, then at a pair's first ``=``.

    Raises:
        TransportConfigError: a pair without ``=``, or one Zenoh refuses (named).
    """
    for pair in os.environ.get(OVERRIDE_ENV, "").split(";"):
        if not pair.strip():
            continue
        key, sep, value = pair.partition("=")
        if not sep or not key.strip():
            raise TransportConfigError(f"{OVERRIDE_ENV}: {pair!r} is not key=value (pairs are "
                                       "separated by ';', e.g. mode=\"client\")")
        try:
            config.insert_json5(key.strip(), value)
        except zenoh.ZError as exc:
            raise TransportConfigError(
                f"{OVERRIDE_ENV}: {pair!r}: {zenoh_error_text(exc)}") from exc
    return config


def make_router_config(listen: list[str] | None = None, connect: list[str] | None = None,
                       config: str | os.PathLike[str] | None = None) -> zenoh.Config:
    """The configuration of ``warp-buffer router``: ``config`` (a JSON5 file) or
    :data:`ROUTER_DEFAULTS`, with ``listen`` / ``connect`` endpoints replacing the file's."""
    if config is not None:
        result = _from_file(os.fspath(config), "warp-buffer router --config")
    else:
        result = _from_json(ROUTER_DEFAULTS, "router defaults")
    apply_overrides(result)  # (the endpoints given on the command line win)
    for key, endpoints in (("listen/endpoints", listen), ("connect/endpoints", connect)):
        if endpoints:
            try:
                result.insert_json5(key, json.dumps(list(endpoints)))
            except zenoh.ZError as exc:
                raise TransportConfigError(
                    f"invalid router endpoint in {endpoints!r}: {zenoh_error_text(exc)}") from exc
    return result


# ROS_DOMAIN_ID as rcl reads it (strtoul, base 0): decimal, 0x hexadecimal or 0 octal, ASCII
# digits only, at most an unsigned 64-bit long.
_DOMAIN_TEXT = re.compile(
    r"\+?(?:0[xX](?P<hex>[0-9a-fA-F]+)|0(?P<octal>[0-7]*)|(?P<dec>[1-9][0-9]*))", re.ASCII)
_ULONG_MAX = (1 << 64) - 1


def _parse_domain_env(text: str) -> int:
    """The domain ``ROS_DOMAIN_ID``'s ``text`` names; :class:`TransportConfigError` if none."""
    match = _DOMAIN_TEXT.fullmatch(text)
    if match is None:
        raise TransportConfigError(f"{DOMAIN_ENV}={text!r} is not an integer")
    if match["hex"] is not None:
        value = int(match["hex"], 16)
    elif match["octal"] is not None:
        value = int(match["octal"] or "0", 8)
    else:
        value = int(match["dec"])
    if value > _ULONG_MAX:
        raise TransportConfigError(f"{DOMAIN_ENV}={text!r} is out of range")
    return value


def resolve_domain_id(domain_id: int | None) -> int:
    """``domain_id``, else env ``ROS_DOMAIN_ID``, else 0; must be a non-negative integer."""
    where = ""
    if domain_id is None:
        text = os.environ.get(DOMAIN_ENV, "").strip()
        where = f" ({DOMAIN_ENV}={text!r})"
        domain_id = _parse_domain_env(text) if text else 0
    if isinstance(domain_id, bool) or not isinstance(domain_id, int) or domain_id < 0:
        raise TransportConfigError(f"domain id{where} must be a non-negative int, got "
                                   f"{domain_id!r}")
    return domain_id
