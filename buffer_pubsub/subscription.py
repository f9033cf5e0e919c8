"""``Subscription``: receives on its channels, checks attachments, runs the callback on the
node's executor (or, when nothing waits before it, on the thread the message arrived on: the
executor's own waiting thread for a lane message, Zenoh's for a sample whose subscription's
callbacks proved short, see :mod:`._inline`; one callback of the node at a time either way).

A subscription listens on ``<key>/_buf/<its gid>`` (payloads built for it) when it accepts some
backend besides CPU, else on ``<key>/_buf_cpu`` (the shared CPU stream), and on the base key (see
:mod:`.wire`). As rmw_zenoh, it accepts every sample with a valid 33-byte attachment from any
publisher, whatever its gid: other ROS 2 implementations derive gids their own way. What it
refuses is counted by reason in ``counters.refused``:

- ``attachment``: no valid attachment;
- ``duplicate``: a base-key copy written by a buffer-aware publisher (that publisher reaches us
  on ``_buf_cpu`` / ``_buf/<gid>``);
- ``unknown_publisher``: a payload built for us (it may hold backend descriptors, which need the
  publisher's endpoint info) whose publisher's liveliness token did not arrive within
  ``PUBLISHER_DISCOVERY_WAIT_S``. Such samples wait *parked* in this subscription only (at most
  ``depth`` of them); no thread ever waits on discovery, and other subscriptions are unaffected.

A jump in a publisher's sequence number counts as ``lost`` when within ``LOST_WINDOW`` (a larger
jump, spoofed or a restarted counter, only resynchronizes and counts in ``sequence_jumps``). A
keep-last queue of ``depth`` messages drops the oldest when the callback falls behind
(``dropped``); keep-all keeps every message. A message that cannot be deserialized (a typed
``RosidlBufferError``, e.g. a stale backend buffer, or any other exception a backend raises)
counts in ``errors`` and the subscription goes on.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import zenoh

from rosidl_buffer import RosidlBufferError
from rosidl_buffer.messages import Message, deserialize_message, release_buffers

from . import _lane_routes, _process, fast_lane, wire
from ._info import endpoint_gone, endpoint_info
from ._executor import spinning_here
from ._inline import InlinePolicy
from ._zenoh import undeclare_quietly
from .errors import NodeClosedError, PubSubError

if TYPE_CHECKING:
    from .callback_groups import CallbackGroup
    from .node import Node

__all__ = ["MessageInfo", "Subscription", "SubscriptionCounters"]

_log = logging.getLogger(__name__)

#: How long a sample built for us waits (parked, nobody blocked) for its publisher's token.
PUBLISHER_DISCOVERY_WAIT_S = 1.0
#: Largest sequence gap counted as lost; a larger jump only resynchronizes.
LOST_WINDOW = 1 << 16
#: Publishers whose last sequence number a subscription remembers (oldest forgotten first).
MAX_TRACKED_PUBLISHERS = 1024

ROUTE_INTRA = "intra"  # same process, message object shared (or CPU copy)
ROUTE_BUFFER = "buffer"  # <key>/_buf/<gid>: serialized for this subscription (descriptor or CPU)
ROUTE_CPU = "cpu"  # <key>/_buf_cpu: shared CPU stream
ROUTE_BASE = "base"  # base key: plain ROS 2 publishers (rmw_zenoh or others)
ROUTE_LANE = "lane"  # the same-host iceoryx2 lane: what _buf/<gid> carries, off Zenoh
#: Routes whose payload was built for this subscription and may carry descriptors: decoded on
#: arrival, so a backend's hold is taken when a message arrives and dropped with it.
_DESCRIPTOR_ROUTES = (ROUTE_BUFFER, ROUTE_LANE)

REFUSED_ATTACHMENT = "attachment"
REFUSED_DUPLICATE = "duplicate"
REFUSED_LATE = "late"  # older than a message already delivered from its publisher (keep-last)
REFUSED_UNKNOWN_PUBLISHER = "unknown_publisher"

_BUFFER_AWARE_ENCODING = zenoh.Encoding.APPLICATION_CDR.with_schema(wire.BUFFER_AWARE_SCHEMA)


@dataclass(frozen=True)
class MessageInfo:
    """Passed as second callback argument when the subscription was made ``with_info=True``."""

    sequence_number: int
    source_timestamp_ns: int
    received_timestamp_ns: int
    publisher_gid: bytes
    route: str  # "intra", "buffer", "lane", "cpu" or "base"


@dataclass
class SubscriptionCounters:
    received: int = 0  # callbacks delivered
    lost: int = 0  # sequence gaps (within LOST_WINDOW) seen on arrival (on the lane, also
    # iceoryx2's keep-last overwrite when the executor falls more than depth messages behind)
    errors: int = 0  # messages that failed to deserialize (on arrival for descriptor routes)
    dropped: int = 0  # overwritten in the keep-last queue before the callback ran
    rejected: int = 0  # samples refused for a reason other than "duplicate" (see refused)
    callback_errors: int = 0  # exceptions raised by the user callback
    sequence_jumps: int = 0  # sequence jumps beyond LOST_WINDOW (resynchronized, not counted)
    refused: dict[str, int] = field(default_factory=dict)  # reason -> samples not delivered


class Subscription:
    """Created by :meth:`Node.create_subscription`."""

    def __init__(self, node: Node, msg_type: type[Message], token: wire.EndpointToken,
                 callback: Callable[..., Any], depth: int, accepted: list[str],
                 with_info: bool, history: str = wire.KEEP_LAST,
                 callback_group: CallbackGroup | None = None) -> None:
        self.node = node
        #: Which callbacks may run beside this one on a multi-threaded executor.
        self.callback_group = (node.default_callback_group if callback_group is None
                               else callback_group)
        self.msg_type = msg_type
        self.topic_name = token.topic
        self.depth = depth
        self.history = history
        self.accepted: tuple[str, ...] = tuple(accepted)
        self.gid = token.gid
        self.info = endpoint_info(token)
        self.counters = SubscriptionCounters()
        self.last_error: BaseException | None = None
        self._token = token
        self._callback = callback
        self._with_info = with_info
        self._lock = threading.Lock()
        self._queue: collections.deque[tuple[Any, ...]] = collections.deque(
            maxlen=depth if history == wire.KEEP_LAST else None)
        self._scheduled = False  # in the executor's ready set (at most once)
        self._parked: collections.deque[tuple[float, tuple[Any, ...]]] = collections.deque()
        self._last_sequence: dict[bytes, int] = {}
        self._closed = False
        # Zenoh arrivals may run their callback on Zenoh's thread (see _inline) only when the
        # node runs its own executor thread: with executor="manual" callbacks run in spin().
        self._gate = node._gate
        self._inline_arrivals = node._inline_callbacks
        self._policy = InlinePolicy()
        self.base_key = wire.data_key(node.domain_id, token.topic, msg_type.__msgtype__)
        self._backends = tuple(node.backends.values())
        for backend in self._backends:
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
        # The lane reader exists before the token: a publisher that discovers us finds the
        # service, so its writer decides the route at once. The Zenoh channel stays for
        # publishers that cannot open the lane (other host or user, lane off, older peers).
        self._lane_reader = None
        lane = node._lane
        # (Keep-all stays on Zenoh: iceoryx2's keep-last queue would drop; so do queues
        # deeper than the lane preallocates, see fast_lane.MAX_DEPTH.)
        if (lane is not None and history == wire.KEEP_LAST and depth <= fast_lane.MAX_DEPTH
                and wire.accepts_backends(token.backends)):
            self._lane_reader = _lane_routes.open_reader(self.base_key, self.gid, depth)
            if self._lane_reader is not None:
                lane.attach(self._lane_reader, self._on_lane)
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

    def _matches(self, token: wire.EndpointToken) -> bool:
        return (token.is_publisher and token.topic == self._token.topic
                and token.type_name == self._token.type_name)

    def _refuse(self, reason: str, count: int = 1) -> None:
        """Count ``count`` samples refused for ``reason``; call with ``self._lock`` held."""
        refused = self.counters.refused
        refused[reason] = refused.get(reason, 0) + count
        if reason != REFUSED_DUPLICATE:
            self.counters.rejected += count

    # -- arrival (Zenoh threads, or the publisher's thread for intra-process) -------------------
    def _on_sample(self, sample: zenoh.Sample, route: str) -> None:
        received_ns = time.time_ns()
        raw = sample.attachment
        try:
            attachment = wire.Attachment.decode(None if raw is None else raw.to_bytes())
        except PubSubError:
            with self._lock:
                self._refuse(REFUSED_ATTACHMENT)
            return
        gid = attachment.publisher_gid
        if _process.is_local_publisher(gid):
            return  # delivered intra-process already
        node = self.node
        if route == ROUTE_BASE:
            publisher = node._publisher_token(gid)
            if (publisher is not None and publisher.buffer_aware) or \
                    sample.encoding == _BUFFER_AWARE_ENCODING:
                with self._lock:
                    self._refuse(REFUSED_DUPLICATE)
                return
        # ZBytes has no buffer protocol in zenoh 1.10: to_bytes() is the one copy out of Zenoh
        # (deserialization then aliases these bytes).
        self._arrived((sample.payload.to_bytes(), attachment, route, received_ns, False),
                      self._inline_arrivals)

    def _on_lane(self, data: bytes) -> None:
        """A lane message, on the waiting thread (the executor's, or the user's in spin()),
        inside the waker's wait: when nothing waits before it, its callback runs right here
        (no queue, no second pass through the executor)."""
        received_ns = time.time_ns()
        try:
            attachment, payload = _lane_routes.split_frame(data)
        except PubSubError:
            with self._lock:
                self._refuse(REFUSED_ATTACHMENT)
            return
        gid = attachment.publisher_gid
        if _process.is_local_publisher(gid):
            return  # delivered intra-process already (never sent here; a forged frame)
        self._arrived((payload, attachment, ROUTE_LANE, received_ns, False), inline=True)

    def _arrived(self, item: tuple[Any, ...], inline: bool = False) -> None:
        """A sample built for us waits (parked) for its publisher's token, which its
        descriptors need; anything else is accepted at once (``inline``: see _enqueue)."""
        publisher = None
        if item[2] in _DESCRIPTOR_ROUTES:
            gid = item[1].publisher_gid
            publisher = self.node._publisher_token(gid)
            # Behind its publisher's parked samples while they wait to resume: accepted first,
            # it would make them late (and refused)
            if publisher is None or (self._parked and self._has_parked(gid)):
                self._park(item)
                return
        self._accept(item, publisher, inline)

    def _accept(self, item: tuple[Any, ...], publisher: wire.EndpointToken | None = None,
                inline: bool = False) -> None:
        """Queue an arrived sample; one built for us is deserialized now (descriptors imported,
        holds taken) and queued as the message, released if it is dropped before delivery.
        ``inline``: deliver at once if nothing waits (see :meth:`_enqueue`)."""
        payload, attachment, route, received_ns, _ = item
        if route in _DESCRIPTOR_ROUTES:
            try:
                msg = self._deserialize(payload, attachment, route, publisher)
            except Exception as exc:  # typed errors expected; a backend bug is counted too
                self._count_error(exc, attachment, arrived=True)
                return
            item = (msg, attachment, route, received_ns, True)
        self._enqueue(item, inline)

    def _count_error(self, exc: BaseException, attachment: wire.Attachment,
                     arrived: bool = False) -> None:
        """Count a message that failed to deserialize (``arrived``: on arrival, before the
        queue saw its sequence number, so it is an error and not also a gap)."""
        with self._lock:
            if arrived:
                self._track_sequence(attachment)
            self.counters.errors += 1
        self.last_error = exc
        _log.warning("%r: dropped a message from %s: %s", self,
                     attachment.publisher_gid.hex(), exc,
                     exc_info=not isinstance(exc, RosidlBufferError))

    def _deliver_intra(self, msg: Message, attachment: wire.Attachment) -> None:
        self._enqueue((msg, attachment, ROUTE_INTRA, time.time_ns(), False))

    def _track_sequence(self, attachment: wire.Attachment) -> bool:
        """Count gaps in the publisher's sequence; whether this message is older than one
        already seen from it (call with ``self._lock`` held)."""
        gid = attachment.publisher_gid
        sequence = attachment.sequence_number
        last_seen = self._last_sequence
        last = last_seen.get(gid)
        if last is None:
            if len(last_seen) >= MAX_TRACKED_PUBLISHERS:
                del last_seen[next(iter(last_seen))]
            last_seen[gid] = sequence
            return False
        gap = sequence - last - 1
        if gap < 0 and last - sequence < LOST_WINDOW:
            return True  # late or repeated: neither new nor a gap
        if 0 < gap <= LOST_WINDOW:
            self.counters.lost += gap
        elif gap != 0:
            self.counters.sequence_jumps += 1
        last_seen[gid] = sequence
        return False

    def _enqueue(self, item: tuple[Any, ...], inline: bool = False) -> None:
        """Queue ``(payload or message, attachment, route, received_ns, owned)``; ``owned``:
        a message decoded for us alone, whose buffers are released if it is dropped.

        ``inline``: the arrival thread may run the callback itself when nothing waits before
        it (this queue and the executor's ready set empty) and no other callback of the node
        runs (the gate): the same order and one callback at a time, one thread hop less. A
        lane message arrives on the executor's own waiting thread; a Zenoh sample on Zenoh's
        thread, which only callbacks proved short may hold (:mod:`._inline`)."""
        evicted = None
        run_now = False
        gate = self._gate
        with self._lock:
            if self._closed:
                closed = True
            elif self._track_sequence(item[1]) and self.history == wire.KEEP_LAST:
                # Older than one already delivered: a route switch (Zenoh to the lane) let a
                # later message overtake it. A keep-last reader gets each publisher's messages
                # in order (its gap was counted as lost when the later one came).
                closed = True  # (not queued: released below, as a closed one is)
                refused = self.counters.refused
                refused[REFUSED_LATE] = refused.get(REFUSED_LATE, 0) + 1
            else:
                closed = False
                queue = self._queue
                lane = item[2] == ROUTE_LANE
                if (inline and not queue and not self.node._executor.has_ready()
                        and (lane or self._policy.trusted)
                        and (gate is None or gate.acquire(blocking=False))):
                    run_now = lane or self._policy.arrived_inline()
                    if not run_now:
                        gate.release()  # type: ignore[union-attr]  # Zenoh arrivals have one
                if not run_now:
                    if len(queue) == queue.maxlen:
                        self.counters.dropped += 1
                        evicted = queue[0]
                    queue.append(item)
                    schedule = not self._scheduled
                    self._scheduled = True
        if run_now:
            try:
                ran = self._run_item(item, inline=True)
            finally:
                if gate is not None:
                    gate.release()
            if lane and ran:
                self.node._executor.ran_inline()
            return
        if closed:
            evicted = item
        elif schedule:
            self.node._executor.schedule(self)
        # Only an owned message holds anything: serialized bytes hold nothing, an intra-process
        # message shares the publisher's buffers (not ours to release).
        if evicted is not None and evicted[4]:
            release_buffers(evicted[0])

    # -- samples waiting for their publisher's token -------------------------------------------
    def _has_parked(self, gid: bytes) -> bool:
        with self._lock:  # (a deque another thread changes cannot be iterated unlocked)
            return any(entry[1][1].publisher_gid == gid for entry in self._parked)

    def _park(self, item: tuple[Any, ...]) -> None:
        deadline = time.monotonic() + PUBLISHER_DISCOVERY_WAIT_S
        with self._lock:
            if self._closed:
                return
            self._parked.append((deadline, item))
            if len(self._parked) > self.depth:
                self._parked.popleft()
                self._refuse(REFUSED_UNKNOWN_PUBLISHER)
        # The token may have arrived between the lookup and the append: resume at once.
        if self.node._publisher_token(item[1].publisher_gid) is not None:
            self._resume(item[1].publisher_gid)

    def _on_publisher(self, token: wire.EndpointToken, appeared: bool) -> None:
        """A matching publisher appeared (resume its parked samples) or left."""
        if appeared:
            if self._parked:
                self._resume(token.gid)
        else:
            with self._lock:
                self._last_sequence.pop(token.gid, None)

    def _resume(self, gid: bytes) -> None:
        with self._lock:
            ready = [item for _, item in self._parked if item[1].publisher_gid == gid]
            if not ready:
                return
            self._parked = collections.deque(
                entry for entry in self._parked if entry[1][1].publisher_gid != gid)
        for item in ready:
            self._accept(item)

    def _expire_parked(self, now: float) -> None:
        """Drop (and count) parked samples whose publisher never appeared in time."""
        if not self._parked:
            return
        with self._lock:
            parked = self._parked
            expired = 0
            while parked and parked[0][0] <= now:
                parked.popleft()
                expired += 1
            if expired:
                self._refuse(REFUSED_UNKNOWN_PUBLISHER, expired)

    # -- executor ------------------------------------------------------------------------------
    def _run_one(self) -> bool:
        """Deliver the next queued message; whether its callback ran."""
        with self._lock:
            if self._closed or not self._queue:
                self._scheduled = False
                return False
            item = self._queue.popleft()
            again = bool(self._queue)
            self._scheduled = again
        if again:  # others wait: take turns with the node's other subscriptions
            self.node._executor.schedule(self)
        return self._run_item(item)

    def _run_item(self, item: tuple[Any, ...], inline: bool = False) -> bool:
        """Deserialize a queued payload if it still is one, then run the callback; whether it
        ran (not for a message that failed to decode or arrived after close)."""
        payload, attachment, route, received_ns, owned = item
        if owned or route == ROUTE_INTRA:
            msg = payload
        else:
            try:
                msg = self._deserialize(payload, attachment, route)
            except Exception as exc:  # typed errors expected; a backend bug is counted too
                self._count_error(exc, attachment)
                return False
        node = self.node
        if self._closed or node._closed:  # a closing node starts no callback
            if owned:
                release_buffers(msg)  # imported for us alone, and nobody will read it
            return False
        with self._lock:
            self.counters.received += 1
        in_flight = node._in_flight  # what close() waits for
        thread = in_flight.enter()
        start = time.perf_counter()
        try:
            if self._with_info:
                self._callback(msg, MessageInfo(
                    attachment.sequence_number, attachment.source_timestamp_ns, received_ns,
                    attachment.publisher_gid, route))
            else:
                self._callback(msg)
        except Exception as exc:
            self._callback_failed(exc)
        except BaseException as exc:  # SystemExit, say: the user's own thread gets it (rclpy)
            if spinning_here():
                raise
            # On the library's threads it would end the executor thread silently (and with it
            # every later delivery) or unwind Zenoh's: counted and logged, delivery goes on.
            self._callback_failed(exc)
        finally:
            in_flight.leave(thread)
        self._policy.ran(time.perf_counter() - start, inline)
        return True

    def _callback_failed(self, exc: BaseException) -> None:
        with self._lock:
            self.counters.callback_errors += 1
        self.last_error = exc
        if isinstance(exc, NodeClosedError) and self.node._closed:
            # A callback that outlived close()'s wait published on its closed node: the end of
            # the program (Ctrl-C), not an error to show.
            _log.debug("%r: callback ran past its node's close: %s", self, exc)
            return
        _log.error("%r: callback raised %s", self, type(exc).__name__,
                   exc_info=(type(exc), exc, exc.__traceback__))

    def _deserialize(self, payload: bytes, attachment: wire.Attachment, route: str,
                     publisher: wire.EndpointToken | None = None) -> Message:
        # Only a payload built for us may hold descriptors, which need the publisher's info; it
        # was parked until the token arrived. CPU payloads need no publisher info.
        info = None
        if route in _DESCRIPTOR_ROUTES:
            token = publisher or self.node._publisher_token(attachment.publisher_gid)
            info = None if token is None else endpoint_info(token)
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
            owned = [item[0] for item in self._queue if item[4]]
            self._queue.clear()  # the rest: serialized bytes or shared intra messages
            self._parked.clear()
        for msg in owned:
            release_buffers(msg)
        _process.remove_subscription(self.base_key, self)
        undeclare_quietly(self._liveliness, *self._subscribers)
        if self._lane_reader is not None:  # the waker closes it once detached
            self.node._lane.detach(self._lane_reader, close=True)
        endpoint_gone(self._backends, self.info)

