"""``Subscription``: receives on its channels, checks attachments, runs the callback on the
node's executor thread.

A subscription listens on ``<key>/_buf/<its gid>`` (payloads built for it) when it accepts some
backend besides CPU, else on ``<key>/_buf_cpu`` (the shared CPU stream), and on the base key,
where it accepts samples only from discovered publishers that know nothing of buffers (see
:mod:`.wire`). Samples
without a valid 33-byte attachment are dropped (``rejected``); a jump in a publisher's sequence
number counts as ``lost``; a keep-last queue of ``depth`` messages drops the oldest when the
callback falls behind (``dropped``); a message that cannot be deserialized (a typed
``RosidlBufferError``, e.g. a stale backend buffer, or any other exception a backend raises)
counts in ``errors`` and the subscription goes on.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import zenoh

from rosidl_buffer import RosidlBufferError
from rosidl_buffer.messages import Message, deserialize_message

from . import _process, wire
from ._zenoh import undeclare_quietly
from ._info import endpoint_info
from .errors import PubSubError

if TYPE_CHECKING:
    from .node import Node

__all__ = ["MessageInfo", "Subscription", "SubscriptionCounters"]

_log = logging.getLogger(__name__)

#: How long a sample from a not-yet-discovered publisher waits for its liveliness token.
PUBLISHER_DISCOVERY_WAIT_S = 1.0

ROUTE_INTRA = "intra"  # same process, message object shared (or CPU copy)
ROUTE_BUFFER = "buffer"  # <key>/_buf/<gid>: serialized for this subscription (descriptor or CPU)
ROUTE_CPU = "cpu"  # <key>/_buf_cpu: shared CPU stream
ROUTE_BASE = "base"  # base key, from a publisher that knows nothing of buffers


@dataclass(frozen=True)
class MessageInfo:
    """Passed as second callback argument when the subscription was made ``with_info=True``."""

    sequence_number: int
    source_timestamp_ns: int
    received_timestamp_ns: int
    publisher_gid: bytes
    route: str  # "intra", "buffer", "cpu" or "base"


@dataclass
class SubscriptionCounters:
    received: int = 0  # callbacks delivered
    lost: int = 0  # sequence gaps seen on arrival
    errors: int = 0  # messages that failed to deserialize
    dropped: int = 0  # overwritten in the keep-last queue before the callback ran
    rejected: int = 0  # samples without a valid attachment, or from an unexpected route
    callback_errors: int = 0  # exceptions raised by the user callback


class Subscription:
    """Created by :meth:`Node.create_subscription`."""

    def __init__(self, node: Node, msg_type: type[Message], token: wire.EndpointToken,
                 callback: Callable[..., Any], depth: int, accepted: list[str],
                 with_info: bool) -> None:
        self.node = node
        self.msg_type = msg_type
        self.topic_name = token.topic
        self.depth = depth
        self.accepted: tuple[str, ...] = tuple(accepted)
        self.gid = token.gid
        self.info = endpoint_info(token)
        self.counters = SubscriptionCounters()
        self.last_error: BaseException | None = None
        self._token = token
        self._callback = callback
        self._with_info = with_info
        self._lock = threading.Lock()
        self._queue: collections.deque[tuple[Any, ...]] = collections.deque(maxlen=depth)
        self._last_sequence: dict[bytes, int] = {}
        self._closed = False
        self.base_key = wire.data_key(node.domain_id, token.topic, msg_type.__msgtype__)
        for backend in node.backends.values():
            backend.on_creating_endpoint(self.info)
        session = node.session
        remote = zenoh.Locality.REMOTE
        if wire.accepts_backends(token.backends):
            channel = session.declare_subscriber(
                wire.buffer_channel_key(self.base_key, self.gid),
                lambda s: self._on_sample(s, ROUTE_BUFFER), allowed_origin=remote)
        else:
            channel = session.declare_subscriber(
                wire.cpu_channel_key(self.base_key),
                lambda s: self._on_sample(s, ROUTE_CPU), allowed_origin=remote)
        self._subscribers = [
            channel,
            session.declare_subscriber(
                self.base_key, lambda s: self._on_sample(s, ROUTE_BASE), allowed_origin=remote),
        ]
        _process.add_subscription(self.base_key, self)
        # Declared last: a publisher that discovers us finds our Zenoh subscribers in place.
        self._liveliness = session.liveliness().declare_token(token.key())

    def __repr__(self) -> str:
        return (f"Subscription({self.msg_type.__msgtype__}, {self.topic_name!r}, "
                f"accepts={list(self.accepted)})")

    # -- counters and matching -----------------------------------------------------------------
    @property
    def received(self) -> int:
        return self.counters.received

    @property
    def lost(self) -> int:
        return self.counters.lost

    @property
    def errors(self) -> int:
        return self.counters.errors

    def get_publisher_count(self) -> int:
        """Matched publishers (local and remote) currently known through discovery."""
        return self.node._count_matching(
            wire.PUBLISHER_KIND, self._token.topic, self._token.type_name, self._token.type_hash)

    def wait_for_publishers(self, count: int = 1, timeout: float | None = 10.0) -> bool:
        """Block until at least ``count`` publishers are matched; False on timeout."""
        return self.node._wait_matching(
            wire.PUBLISHER_KIND, self._token.topic, self._token.type_name,
            self._token.type_hash, count, timeout)

    # -- arrival (Zenoh threads, or the publisher's thread for intra-process) -------------------
    def _on_sample(self, sample: zenoh.Sample, route: str) -> None:
        received_ns = time.time_ns()
        raw = sample.attachment
        try:
            attachment = wire.Attachment.decode(None if raw is None else raw.to_bytes())
        except PubSubError:
            with self._lock:
                self.counters.rejected += 1
            return
        gid = attachment.publisher_gid
        if _process.is_local_publisher(gid):
            return  # delivered intra-process already
        if route == ROUTE_BASE:
            publisher = self.node._graph.get(gid)
            if publisher is None or publisher.buffer_aware:
                return  # buffer-aware publishers reach us on _buf_cpu or _buf/<gid>
        self._enqueue((sample.payload.to_bytes(), attachment, route, received_ns))

    def _deliver_intra(self, msg: Message, attachment: wire.Attachment) -> None:
        self._enqueue((msg, attachment, ROUTE_INTRA, time.time_ns()))

    def _enqueue(self, item: tuple[Any, ...]) -> None:
        attachment: wire.Attachment = item[1]
        gid = attachment.publisher_gid
        with self._lock:
            if self._closed:
                return
            last = self._last_sequence.get(gid)
            if last is not None and attachment.sequence_number > last + 1:
                self.counters.lost += attachment.sequence_number - last - 1
            if last is None or attachment.sequence_number > last:
                self._last_sequence[gid] = attachment.sequence_number
            if len(self._queue) == self._queue.maxlen:
                self.counters.dropped += 1
            self._queue.append(item)
        self.node._post(self._take)

    # -- executor thread -----------------------------------------------------------------------
    def _take(self) -> None:
        with self._lock:
            if self._closed or not self._queue:
                return
            payload, attachment, route, received_ns = self._queue.popleft()
        if route == ROUTE_INTRA:
            msg = payload
        else:
            try:
                msg = self._deserialize(payload, attachment, route)
            except Exception as exc:  # typed errors expected; a backend bug is counted too
                with self._lock:
                    self.counters.errors += 1
                self.last_error = exc
                _log.warning("%r: dropped a message from %s: %s", self,
                             attachment.publisher_gid.hex(), exc,
                             exc_info=not isinstance(exc, RosidlBufferError))
                return
        with self._lock:
            self.counters.received += 1
        try:
            if self._with_info:
                self._callback(msg, MessageInfo(
                    attachment.sequence_number, attachment.source_timestamp_ns, received_ns,
                    attachment.publisher_gid, route))
            else:
                self._callback(msg)
        except Exception as exc:
            with self._lock:
                self.counters.callback_errors += 1
            self.last_error = exc
            _log.exception("%r: callback raised", self)

    def _deserialize(self, payload: bytes, attachment: wire.Attachment, route: str) -> Message:
        # Only a payload built for us may hold descriptors, which need the publisher's info.
        wait = PUBLISHER_DISCOVERY_WAIT_S if route == ROUTE_BUFFER else 0.0
        token = self.node._publisher_token(attachment.publisher_gid, wait)
        if token is None:
            info = None  # CPU payloads need no publisher info; descriptors will be refused
        else:
            info = endpoint_info(token)
        return deserialize_message(payload, self.msg_type, backends=self.node.backends,
                                   endpoint_info=info)

    # -- teardown ------------------------------------------------------------------------------
    def destroy(self) -> None:
        """Undeclare this subscription (also done by :meth:`Node.close`)."""
        self.node._forget(self)
        self._undeclare()

    def _undeclare(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._queue.clear()
        _process.remove_subscription(self.base_key, self)
        undeclare_quietly(self._liveliness, *self._subscribers)
