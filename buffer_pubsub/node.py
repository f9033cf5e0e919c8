"""``Node``: a Zenoh session, its discovery graph and its executor thread.

Shaped after ``rclpy.node.Node``. Callbacks of every subscription of a node run on the node's own
executor thread, one at a time, never on Zenoh's threads. Discovery is the ROS 2 graph carried by
``@ros2_lv`` liveliness tokens: peers appear on PUT and vanish on DELETE, which Zenoh also sends
when a peer process dies (SIGKILL included).
"""

from __future__ import annotations

import logging
import os
import queue
import re
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

import zenoh

from rosidl_buffer import BufferBackend, local_host_id
from rosidl_buffer.messages import Message, get_message_type, get_type_hash

from . import _process, wire
from ._zenoh import undeclare_quietly
from .config import resolve_domain_id
from .connectivity import open_session
from .errors import InvalidEndpointError, NodeClosedError, PubSubError
from .publisher import Publisher
from .subscription import Subscription

__all__ = ["Node"]

_log = logging.getLogger(__name__)
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


class Node:
    """A participant of the pub/sub graph.

    ``Node(name, config=None, namespace="", domain_id=None, *, router=None, backends=None)``:
    ``config`` is a ``zenoh.Config`` or the path of a Zenoh JSON5 file, ``router`` a Zenoh
    router endpoint (see :mod:`buffer_pubsub.config` for the defaults); ``domain_id`` defaults to
    env ``ROS_DOMAIN_ID`` or 0; ``backends`` overrides the buffer backends (by default every
    backend registered in :mod:`rosidl_buffer.registry`, loaded once per process).
    Use as a context manager or call :meth:`close`, which undeclares everything.
    """

    def __init__(
        self,
        name: str,
        config: zenoh.Config | str | os.PathLike[str] | None = None,
        namespace: str = "",
        domain_id: int | None = None,
        *,
        router: str | None = None,
        backends: Mapping[str, BufferBackend] | None = None,
    ) -> None:
        if not isinstance(name, str) or not _NAME.match(name):
            raise InvalidEndpointError(f"invalid node name {name!r}: use letters, digits and _")
        if namespace and not re.match(r"^/?[A-Za-z0-9_/]*$", namespace):
            raise InvalidEndpointError(f"invalid namespace {namespace!r}")
        self.name = name
        self.namespace = "/" + namespace.strip("/") if namespace.strip("/") else ""
        self.domain_id = resolve_domain_id(domain_id)
        self.backends: dict[str, BufferBackend] = (
            dict(backends) if backends is not None else _process.default_backends())
        self.locality = wire.Locality(local_host_id(), os.getpid(), os.getuid())
        self._closed = False
        self._lock = threading.RLock()
        self._graph_cond = threading.Condition(self._lock)
        self._graph: dict[bytes, wire.EndpointToken] = {}  # gid -> endpoint
        self._keys: dict[str, bytes] = {}  # liveliness key -> gid
        self._publishers: list[Publisher] = []
        self._subscriptions: list[Subscription] = []
        self._tasks: queue.SimpleQueue[Callable[[], None] | None] = queue.SimpleQueue()

        self.session = open_session(config, router)
        try:
            self.zid = str(self.session.zid())
            self.node_id = _process.next_id()
            self._executor = threading.Thread(
                target=self._run_executor, name=f"buffer_pubsub:{name}", daemon=True)
            self._executor.start()
            self._node_token = self.session.liveliness().declare_token(
                wire.NodeToken(self.domain_id, self.zid, self.node_id, self.namespace, name).key())
            self._graph_subscriber = self.session.liveliness().declare_subscriber(
                wire.liveliness_domain_selector(self.domain_id), self._on_liveliness, history=True)
        except BaseException:
            self._tasks.put(None)
            self.session.close()
            raise

    # -- context manager -----------------------------------------------------------------------
    def __enter__(self) -> Node:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Node({self.name!r}, namespace={self.namespace!r}, domain_id={self.domain_id})"

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Undeclare every endpoint and token, stop the executor and close the Zenoh session."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            endpoints: list[Publisher | Subscription] = [*self._publishers, *self._subscriptions]
            self._publishers.clear()
            self._subscriptions.clear()
            self._graph_cond.notify_all()
        for endpoint in endpoints:
            endpoint._undeclare()
        undeclare_quietly(self._graph_subscriber, self._node_token)
        self._tasks.put(None)
        if threading.current_thread() is not self._executor:
            self._executor.join(timeout=10)
        self.session.close()

    def _check_open(self) -> None:
        if self._closed:
            raise NodeClosedError(f"node {self.name!r} is closed")

    # -- endpoints -----------------------------------------------------------------------------
    def _resolve_type(self, msg_type: type[Message] | str) -> type[Message]:
        if isinstance(msg_type, str):
            return get_message_type(msg_type)
        if isinstance(msg_type, type) and issubclass(msg_type, Message):
            return msg_type
        raise InvalidEndpointError(f"msg_type must be a message class or name, got {msg_type!r}")

    def _endpoint_token(self, kind: str, topic: str, type_name: str, depth: int,
                        backends: dict[str, str]) -> wire.EndpointToken:
        return wire.EndpointToken(
            domain_id=self.domain_id, zid=self.zid, node_id=self.node_id,
            entity_id=_process.next_id(), kind=kind, namespace=self.namespace,
            node_name=self.name, topic=topic, type_name=type_name,
            type_hash=get_type_hash(type_name), qos=wire.qos_segment(depth), buffer_aware=True,
            locality=self.locality, backends=backends)

    @staticmethod
    def _check_depth(depth: int) -> int:
        if isinstance(depth, bool) or not isinstance(depth, int) or depth < 1:
            raise InvalidEndpointError(f"depth must be a positive int (keep-last), got {depth!r}")
        return depth

    def create_publisher(self, msg_type: type[Message] | str, topic: str,
                         depth: int = 10) -> Publisher:
        """A publisher of ``msg_type`` on ``topic`` (relative names resolve in the namespace)."""
        self._check_open()
        cls = self._resolve_type(msg_type)
        depth = self._check_depth(depth)
        fq_topic = wire.fully_qualified_topic(topic, self.namespace)
        token = self._endpoint_token(wire.PUBLISHER_KIND, fq_topic, cls.__msgtype__, depth, {})
        publisher = Publisher(self, cls, token, depth)
        with self._lock:
            self._publishers.append(publisher)
            peers = [t for t in self._graph.values() if publisher._matches(t)]
        for peer in peers:
            publisher._on_peer(peer, True)
        return publisher

    def create_subscription(
        self,
        msg_type: type[Message] | str,
        topic: str,
        callback: Callable[..., Any],
        depth: int = 10,
        acceptable_buffer_backends: str = "cpu",
        *,
        with_info: bool = False,
    ) -> Subscription:
        """A subscription calling ``callback(msg)`` (``callback(msg, info)`` with ``with_info``)
        on this node's executor thread for every message of ``topic``.

        ``acceptable_buffer_backends``: ``"cpu"``, ``"any"`` (every loaded backend) or a comma
        separated list of backend names; advertised to publishers through discovery.
        """
        self._check_open()
        if not callable(callback):
            raise InvalidEndpointError(f"callback must be callable, got {callback!r}")
        cls = self._resolve_type(msg_type)
        depth = self._check_depth(depth)
        fq_topic = wire.fully_qualified_topic(topic, self.namespace)
        from rosidl_buffer import parse_acceptable_backends

        try:
            accepted = parse_acceptable_backends(
                acceptable_buffer_backends, ["cpu", *self.backends])
        except ValueError as exc:
            raise InvalidEndpointError(str(exc)) from None
        advertised = {name: "" if name == "cpu" else self.backends[name].get_backend_metadata()
                      for name in accepted}
        token = self._endpoint_token(
            wire.SUBSCRIPTION_KIND, fq_topic, cls.__msgtype__, depth, advertised)
        subscription = Subscription(self, cls, token, callback, depth, accepted, with_info)
        with self._lock:
            self._subscriptions.append(subscription)
        return subscription

    def _forget(self, endpoint: Publisher | Subscription) -> None:
        with self._lock:
            for group in (self._publishers, self._subscriptions):
                if endpoint in group:
                    group.remove(endpoint)

    # -- discovery -----------------------------------------------------------------------------
    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            token = wire.parse_token(key)
        except PubSubError as exc:
            _log.debug("ignoring liveliness token %s: %s", key, exc)
            return
        if not isinstance(token, wire.EndpointToken):
            return
        with self._lock:
            if self._closed:
                return
            if sample.kind == zenoh.SampleKind.PUT:
                gid = token.gid
                self._keys[key] = gid
                self._graph[gid] = token
                appeared = True
            else:
                gid = self._keys.pop(key, None)
                if gid is None:
                    return
                token = self._graph.pop(gid, token)
                appeared = False
            publishers = [p for p in self._publishers if p._matches(token)]
            self._graph_cond.notify_all()
        for publisher in publishers:
            try:
                publisher._on_peer(token, appeared)
            except Exception:  # a failing backend hook must not break discovery
                _log.exception("negotiation with %s failed", token.key())

    def _count_matching(self, kind: str, topic: str, type_name: str, type_hash: str) -> int:
        with self._lock:
            return sum(1 for t in self._graph.values()
                       if t.kind == kind and t.topic == topic and t.type_name == type_name
                       and t.type_hash == type_hash)

    def _wait_matching(self, kind: str, topic: str, type_name: str, type_hash: str,
                       count: int, timeout: float | None) -> bool:
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._graph_cond:
            while True:
                if self._count_matching(kind, topic, type_name, type_hash) >= count:
                    return True
                if self._closed:
                    return False
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return False
                self._graph_cond.wait(left)

    def _publisher_token(self, gid: bytes, timeout: float) -> wire.EndpointToken | None:
        """The discovered publisher ``gid``, waiting up to ``timeout`` for its token to arrive."""
        deadline = time.monotonic() + timeout
        with self._graph_cond:
            while True:
                token = self._graph.get(gid)
                left = deadline - time.monotonic()
                if token is not None or left <= 0 or self._closed:
                    return token
                self._graph_cond.wait(left)

    def get_topic_names_and_types(self) -> list[tuple[str, list[str]]]:
        """Topics seen in the graph (this domain) with their type names, like rclpy."""
        topics: dict[str, set[str]] = {}
        with self._lock:
            for token in self._graph.values():
                topics.setdefault(token.topic, set()).add(token.type_name)
        return sorted((topic, sorted(types)) for topic, types in topics.items())

    # -- executor ------------------------------------------------------------------------------
    def _post(self, task: Callable[[], None]) -> None:
        self._tasks.put(task)

    def _run_executor(self) -> None:
        while True:
            task = self._tasks.get()
            if task is None:
                return
            try:
                task()
            except Exception:
                _log.exception("executor task failed on node %s", self.name)
