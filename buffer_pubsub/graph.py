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
import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

from . import wire
from ._executor import wait_seconds
from .errors import InvalidEndpointError

__all__ = ["EndpointKind", "Graph", "NodeInfo", "TopicEndpointInfo", "matching_wait"]

_log = logging.getLogger(__name__)


class EndpointKind(enum.Enum):
    """rclpy's ``TopicEndpointTypeEnum`` names."""

    PUBLISHER = "PUBLISHER"
    SUBSCRIPTION = "SUBSCRIPTION"


def matching_wait(count: Any, timeout: Any) -> tuple[int, float | None]:
    """The arguments of a wait for matched endpoints, checked: ``count`` a whole number >= 0
    (else :class:`InvalidEndpointError`), ``timeout`` in seconds as rclpy reads it (None,
    negative or infinite: no limit; NaN or not a number: :class:`InvalidTimeoutError`)."""
    if type(count) is bool or not isinstance(count, int) or count < 0:
        raise InvalidEndpointError(f"count must be a whole number >= 0, not {count!r}")
    return count, wait_seconds(timeout)


@dataclass(frozen=True)
class NodeInfo:
    """A node of the graph (``ros2 node list`` shows ``full_name``)."""

    name: str
    namespace: str  # "/" for the root namespace, as rclpy reports it
    enclave: str
    zid: str  # the Zenoh session of its process

    @property
    def full_name(self) -> str:
        """The node's namespace and name joined by one slash (``/ns/camera``, ``/camera``)."""
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


#: Publishers that left, kept so their last samples still find their info.
RECENTLY_GONE = 256

Event = tuple[wire.EndpointToken, bool]  # an endpoint, and whether it appeared (else vanished)


class Graph:
    """The endpoints and nodes of a domain as one node discovers them, from liveliness PUTs and
    DELETEs (which Zenoh also sends when a peer process dies, SIGKILL included).

    A gid claimed by several keys (a forged twin, a foreign implementation) is the first key's
    while it lives, then the next one's. ``lock`` guards it (the node shares it); ``changed`` is
    notified on every change. Readers on the hot path (:meth:`publisher`) take no lock.
    """

    def __init__(self, lock: threading.RLock) -> None:
        self.lock = lock
        self.changed = threading.Condition(lock)
        self.closed = False
        self._live: dict[bytes, wire.EndpointToken] = {}  # gid -> endpoint
        self._gone: OrderedDict[bytes, wire.EndpointToken] = OrderedDict()  # recently left
        self._keys: dict[str, wire.EndpointToken] = {}  # liveliness key -> its endpoint
        self._gid_keys: dict[bytes, list[str]] = {}
        self._nodes: dict[str, wire.NodeToken] = {}  # liveliness key -> node
        self._services: dict[str, wire.EndpointToken] = {}  # liveliness key -> server, client

    # -- changes (the node's discovery, with ``lock`` held) ----------------------------------
    def put(self, key: str, token: wire.EndpointToken | wire.NodeToken) -> list[Event]:
        """Record ``key``'s endpoint, node or service; the endpoints that appeared. A gid another
        live key already claims keeps that endpoint: a twin never replaces it."""
        if isinstance(token, wire.NodeToken):
            self._nodes[key] = token
            return []
        if token.is_service:  # (kept apart: nothing routes to a service here)
            self._services[key] = token
            return []
        gid = token.gid
        if key in self._keys:
            return []  # a repeated PUT
        self._keys[key] = token
        keys = self._gid_keys.setdefault(gid, [])
        keys.append(key)
        if len(keys) > 1:
            _log.debug("liveliness key %s repeats the gid of %s: kept aside", key, keys[0])
            return []
        self._live[gid] = token
        self._gone.pop(gid, None)
        return [(token, True)]

    def delete(self, key: str) -> list[Event]:
        """Forget ``key``'s endpoint, node or service; the endpoints that vanished and those
        that took their gid over."""
        if (self._nodes.pop(key, None) is not None
                or self._services.pop(key, None) is not None):
            return []
        token = self._keys.pop(key, None)
        if token is None:
            return []
        gid = token.gid
        keys = self._gid_keys.get(gid, [])
        if key in keys:
            keys.remove(key)
        if self._live.get(gid) is not token:
            return []  # a twin kept aside went away
        if keys:  # another live key claims the gid: its endpoint is the one now
            successor = self._live[gid] = self._keys[keys[0]]
            return [(token, False), (successor, True)]
        del self._live[gid]
        self._gid_keys.pop(gid, None)
        if token.is_publisher:
            self._gone[gid] = token
            while len(self._gone) > RECENTLY_GONE:
                self._gone.popitem(last=False)
        return [(token, False)]

    def close(self) -> None:
        """The node closed: waiters return, nothing is held any more."""
        with self.lock:
            self.closed = True
            self.changed.notify_all()

    # -- questions ---------------------------------------------------------------------------
    def holds(self, token: wire.EndpointToken) -> bool:
        """Is ``token`` (still) the discovered endpoint of its gid? Call with ``lock`` held."""
        return self._live.get(token.gid) is token and not self.closed

    def current(self, gid: bytes) -> wire.EndpointToken | None:
        """The live endpoint of ``gid``."""
        return self._live.get(gid)

    def publisher(self, gid: bytes) -> wire.EndpointToken | None:
        """The publisher ``gid`` if discovered (or gone a moment ago); never waits."""
        token = self._live.get(gid)  # a dict read is atomic; no lock on the hot path
        return token if token is not None else self._gone.get(gid)

    def endpoints(self, kind: str | None = None, topic: str | None = None
                  ) -> list[wire.EndpointToken]:
        """The live endpoints (of ``kind`` and ``topic`` where given)."""
        with self.lock:
            return [t for t in self._live.values()
                    if (kind is None or t.kind == kind) and (topic is None or t.topic == topic)]

    def nodes(self) -> list[wire.NodeToken]:
        with self.lock:
            return list(self._nodes.values())

    def services(self) -> list[wire.EndpointToken]:
        """The service servers and clients of other nodes."""
        with self.lock:
            return list(self._services.values())

    def count(self, kind: str, topic: str, type_name: str, type_hash: str) -> int:
        """Live endpoints of ``kind`` on ``topic`` with this type and hash."""
        with self.lock:
            return sum(1 for t in self._live.values()
                       if t.kind == kind and t.topic == topic and t.type_name == type_name
                       and t.type_hash == type_hash)

    def wait(self, kind: str, topic: str, type_name: str, type_hash: str, count: int,
             timeout: float | None, gone: Callable[[], bool] = lambda: False) -> bool:
        """Until :meth:`count` reaches ``count`` (False on timeout, on close, or once ``gone()``
        says the waiting endpoint was destroyed: :meth:`wake` makes it look); ``count`` and
        ``timeout`` as :func:`matching_wait` returns them (None: no limit)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self.changed:
            while True:
                if self.count(kind, topic, type_name, type_hash) >= count:
                    return True
                if self.closed or gone():
                    return False
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return False
                self.changed.wait(left)

    def wake(self) -> None:
        """Make every :meth:`wait` look again (an endpoint it waits for was destroyed)."""
        with self.changed:
            self.changed.notify_all()
