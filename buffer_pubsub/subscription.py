"""``Subscription``: receives on its channels, checks attachments, runs the callback on the
node's executor (or, when nothing waits before it, on the thread the message arrived on: the
executor's own waiting thread for a lane message, Zenoh's for a sample whose subscription's
callbacks proved short, see :mod:`._inline`; one callback of the node at a time either way).

As rmw_zenoh 0.10.5 (``rmw_subscription_data.cpp``), a subscription listens on the base key and,
on a buffer-aware topic, on one more key: ``<key>/_buf_cpu`` when it accepts only CPU, else
``<key>/_buf/<its gid>`` (payloads built for it, possibly with backend descriptors; also over
the same-host lane). It accepts every sample with a valid 33-byte attachment from any publisher,
whatever its gid, known or not: a sample built for us by a publisher whose token has not arrived
is decoded at once with what the gid alone says (rmw_zenoh's minimal endpoint info). What it
refuses is counted by reason in ``counters.refused``:

- ``attachment``: no valid attachment;
- ``duplicate``: a second copy of a message (same publisher and source timestamp), which one of
  our publishers sends while it also serves a subscription without backends on the base key;
- ``late``: older than a message already delivered from its publisher on the same stream
  (keep-last only; a route switch from Zenoh to the lane may let a later message overtake).

Losses are judged per stream (see :mod:`._streams`): a gap on Zenoh counts in ``lost``; a
gap on the lane is the lane's keep-last queue overwriting what the executor had not taken yet,
the subscription's own backlog, and counts in ``dropped`` with the overflow of its own keep-last
queue; so does, for a keep-last subscription, a message whose backend memory its publisher
reused before the import (``BufferOverwrittenError``: the reader fell more than its queue
behind). Any other message that cannot be deserialized (a typed ``RosidlBufferError``, e.g. a
backend buffer whose publisher is gone, or any other exception a backend raises) counts in
``errors`` and the subscription goes on.
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
import zenoh.ext

from rosidl_buffer import BufferOverwrittenError, RosidlBufferError
from rosidl_buffer.messages import (
    Message,
    buffer_fields,
    deserialize_message,
    release_buffers,
    serialize_message,
)

from . import _lane_routes, _process, fast_lane, wire
from ._info import endpoint_gone, endpoint_info, unknown_publisher_info
from ._executor import log_callback_error, spinning_here
from .graph import matching_wait
from ._inline import InlinePolicy
from ._rate import RateLimit
from ._streams import Streams
from ._zenoh import undeclare_quietly
from .errors import NodeClosedError, PubSubError

if TYPE_CHECKING:
    from ._waker import Waker
    from .callback_groups import CallbackGroup
    from .node import Node

__all__ = ["MessageInfo", "Subscription", "SubscriptionCounters"]

_log = logging.getLogger(__name__)

ROUTE_INTRA = "intra"  # same process, message object shared (or CPU copy)
ROUTE_BUFFER = "buffer"  # <key>/_buf/<gid>: serialized for this subscription (descriptor or CPU)
ROUTE_CPU = "cpu"  # <key>/_buf_cpu: shared CPU stream
ROUTE_BASE = "base"  # base key: plain ROS 2 publishers (rmw_zenoh or others)
ROUTE_LANE = "lane"  # the same-host lane: what _buf/<gid> carries, off Zenoh
#: Routes whose payload was built for this subscription and may carry descriptors: decoded on
#: arrival, so a backend's hold is taken when a message arrives and dropped with it.
_DESCRIPTOR_ROUTES = (ROUTE_BUFFER, ROUTE_LANE)

REFUSED_ATTACHMENT = "attachment"
REFUSED_DUPLICATE = "duplicate"
REFUSED_LATE = "late"  # older than a message already delivered on its stream (keep-last)
#: The stream (for sequence numbers) of each route: the lane carries what _buf/<gid> carries.
_OWN = "own"  # this subscription's own stream (the _buf/<gid> key and the lane carry it)
_STREAM = {ROUTE_INTRA: "intra", ROUTE_BUFFER: _OWN, ROUTE_LANE: _OWN, ROUTE_CPU: "cpu",
           ROUTE_BASE: "base"}
#: Our publishers number the base key and ``_buf_cpu`` with one counter (see publisher): from
#: them, what a CPU reader gets on either key is one stream.
_SHARED = "shared"
_SHARED_ROUTES = frozenset({ROUTE_CPU, ROUTE_BASE})


#: A publisher not looked up yet (None is a publisher not discovered).
_UNRESOLVED: Any = object()
#: Streams every publisher numbers on its own (see _judging); only our publishers
#: write the lane.
_EXACT_ROUTES = frozenset({ROUTE_INTRA, ROUTE_BASE, ROUTE_LANE})


def _judging(route: str, publisher: wire.EndpointToken | None) -> tuple[str, bool, bool]:
    """How a message's number is judged, ``(stream, exact, restarts)`` (one call per message):

    - ``stream``: its route's, except that the base key and ``_buf_cpu`` are one stream from
      our publishers (and from one not discovered yet, which may be ours): they number both
      with one counter;
    - ``exact``: the publisher numbers the stream on its own (every step exact). Ours do, in
      process or not (the lane is ours alone, discovered or not); on the base key every
      publisher does (a buffer-aware one writes it alone when it writes it at all), and so does
      one that advertises no backends. On the buffer streams, rmw_zenoh's publishers and
      publishers not discovered yet are judged by the stride of their steps (see
      :mod:`._streams`);
    - ``restarts``: a step back is the publisher's counter starting again. Another
      implementation's numbers go back only when it restarted (rmw_zenoh drops nothing for
      it); ours also when a route switch let a later message overtake (then it is late).
    """
    foreign = publisher is not None and publisher.locality is None
    stream = _SHARED if route in _SHARED_ROUTES and not foreign else _STREAM[route]
    exact = route in _EXACT_ROUTES or publisher is not None and (
        not foreign or publisher.backends is None)
    return stream, exact, foreign and route != ROUTE_INTRA


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
    lost: int = 0  # messages that never arrived: gaps in a stream's numbers on Zenoh
    errors: int = 0  # messages that failed to deserialize (on arrival for descriptor routes)
    # Overwritten in a keep-last queue before the callback ran: this subscription's own queue,
    # or the lane's (which holds as many), or its payload reused by the publisher before the
    # import: the subscriber's backlog, not transport loss.
    dropped: int = 0
    # Samples refused as malformed (see refused; a duplicate or late copy is no fault of input).
    rejected: int = 0
    callback_errors: int = 0  # exceptions raised by the user callback
    # Messages left out by the subscription's max_rate (here; a publisher of ours that honours
    # the rate does not send them at all, and they count nowhere).
    decimated: int = 0
    sequence_jumps: int = 0  # jumps beyond _streams.LOST_WINDOW (resynchronized, not counted)
    refused: dict[str, int] = field(default_factory=dict)  # reason -> samples not delivered


class Subscription:
    """Created by :meth:`Node.create_subscription`."""

    def __init__(self, node: Node, msg_type: type[Message], token: wire.EndpointToken,
                 callback: Callable[..., Any], depth: int, accepted: list[str],
                 with_info: bool, history: str = wire.KEEP_LAST,
                 callback_group: CallbackGroup | None = None, *, raw: bool = False,
                 on_destroy: Callable[[Subscription], None] = lambda subscription: None) -> None:
        self.node = node
        self._on_destroy = on_destroy  # the node forgets it
        #: Which callbacks may run beside this one on a multi-threaded executor.
        self.callback_group = (node.default_callback_group if callback_group is None
                               else callback_group)
        self.msg_type = msg_type
        self.raw = raw  # callbacks get the serialized CDR bytes (rclpy's raw=True)
        # At most max_rate_hz messages a second from each publisher (0: all). Our publishers
        # honour it on this subscription's own stream; what comes otherwise (a shared stream,
        # another implementation) is thinned here, before it is decoded or copied.
        self.max_rate_hz = token.max_rate_hz
        self._rates: dict[bytes, RateLimit] = {}  # per publisher
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
        self._streams = Streams()  # sequence numbers and second copies, judged in C
        self._closed = False
        # Zenoh arrivals may run their callback on Zenoh's thread (see _inline) only when the
        # node runs its own executor thread: with executor="manual" callbacks run in spin().
        self._gate = node.scheduler.gate
        self._inline_arrivals = node.inline_callbacks
        self._policy = InlinePolicy()
        self.base_key = wire.data_key(node.domain_id, token.topic, msg_type.__msgtype__)
        self._backends = tuple(node.backends.values())
        for backend in self._backends:
            backend.on_creating_endpoint(self.info)
        # What __init__ declares, undeclared by _undeclare() if a later step fails: the
        # session is shared with other nodes and outlives this node (see _sessions).
        self._subscribers: list[Any] = []
        self._lane_reader = None
        self._liveliness: Any = None
        try:
            session = node.session
            remote = zenoh.Locality.REMOTE
            on_base = lambda s: self._on_sample(s, ROUTE_BASE)  # noqa: E731
            if token.qos.transient_local:  # rmw_zenoh's: history from publishers' caches first,
                # and (reliable) the misses their heartbeats reveal
                self._subscribers = [zenoh.ext.declare_advanced_subscriber(
                    session, self.base_key, on_base, allowed_origin=remote,
                    history=zenoh.ext.HistoryConfig(detect_late_publishers=True,
                                                    max_samples=depth),
                    recovery=None if token.qos.best_effort else zenoh.ext.RecoveryConfig(
                        heartbeat=True), subscriber_detection=True)]
            else:
                self._subscribers = [session.declare_subscriber(self.base_key, on_base,
                                                                allowed_origin=remote)]
            # A buffer-aware subscription (its type has a top-level uint8[]) listens on one more
            # key: the shared CPU stream when it advertises exactly cpu, else its own.
            # A rate-limited CPU-only one listens on its own stream too: our publishers serve it
            # there, at its rate (see max_rate below).
            own_stream = False
            if buffer_fields(msg_type) and token.backends is not None:  # (transient-local: none)
                cpu_only = wire.subscription_channel(token) == wire.SubscriptionChannel.CPU
                if cpu_only:
                    self._subscribers.append(session.declare_subscriber(
                        wire.cpu_channel_key(self.base_key),
                        lambda s: self._on_sample(s, ROUTE_CPU), allowed_origin=remote))
                if not cpu_only or token.max_rate_hz:
                    own_stream = not cpu_only
                    self._subscribers.append(session.declare_subscriber(
                        wire.buffer_channel_key(self.base_key, self.gid),
                        lambda s: self._on_sample(s, ROUTE_BUFFER), allowed_origin=remote))
            # The lane reader exists before the token: a publisher that discovers us finds the
            # service, so its writer decides the route at once. The Zenoh channel stays for
            # publishers that cannot open the lane (other host or user, lane off, older peers).
            lane = node.lane
            # (Keep-all stays on Zenoh: the lane's keep-last ring would drop; so do queues
            # deeper than the lane's deepest ring, see fast_lane.MAX_DEPTH.)
            if (lane is not None and history == wire.KEEP_LAST and depth <= fast_lane.MAX_DEPTH
                    and own_stream):
                self._lane_reader = _lane_routes.open_reader(self.base_key, self.gid, depth)
                if self._lane_reader is not None:
                    lane.attach(self._lane_reader, self._on_lane)
            _process.add_subscription(self.base_key, self)
            # Declared last: a publisher that discovers us finds our Zenoh subscribers in place.
            self._liveliness = session.liveliness().declare_token(token.key())
        except BaseException:
            self._undeclare()
            raise

    def __repr__(self) -> str:
        return (f"Subscription({self.msg_type.__msgtype__}, {self.topic_name!r}, "
                f"accepts={list(self.accepted)})")

    # -- counters and matching -----------------------------------------------------------------
    @property
    def received(self) -> int:
        """Messages delivered to the callback so far (``counters.received``)."""
        return self.counters.received

    @property
    def lost(self) -> int:
        """Messages lost in transit (``counters.lost``): gaps in a publisher's sequence numbers
        on Zenoh; what a keep-last queue overwrote counts in ``counters.dropped`` instead."""
        return self.counters.lost

    @property
    def errors(self) -> int:
        """Messages that arrived but could not be deserialized (``counters.errors``)."""
        return self.counters.errors

    def get_publisher_count(self) -> int:
        """Matched publishers (local and remote) currently known through discovery."""
        return self.node.graph.count(
            wire.PUBLISHER_KIND, self._token.topic, self._token.type_name, self._token.type_hash)

    def wait_for_publishers(self, count: int = 1, timeout: float | None = 10.0) -> bool:
        """Block until at least ``count`` publishers are matched; False on timeout, or when the
        subscription is destroyed meanwhile (a destroyed one raises :class:`NodeClosedError`).
        ``timeout`` as rclpy reads it: None, negative or infinite waits without limit."""
        count, timeout = matching_wait(count, timeout)
        if self._closed:
            raise NodeClosedError(f"subscription on {self.topic_name!r} is closed")
        return self.node.graph.wait(
            wire.PUBLISHER_KIND, self._token.topic, self._token.type_name,
            self._token.type_hash, count, timeout, gone=lambda: self._closed)

    def matches(self, token: wire.EndpointToken) -> bool:
        """Is ``token`` a publisher of this topic and type? (The node's discovery asks.)"""
        return (token.is_publisher and token.topic == self._token.topic
                and token.type_name == self._token.type_name)

    def _refuse(self, reason: str, count: int = 1) -> None:
        """Count ``count`` samples refused for ``reason``; call with ``self._lock`` held."""
        refused = self.counters.refused
        refused[reason] = refused.get(reason, 0) + count
        if reason not in (REFUSED_DUPLICATE, REFUSED_LATE):
            self.counters.rejected += count

    # -- arrival (Zenoh threads, or the publisher's thread for intra-process) -------------------
    def _on_sample(self, sample: zenoh.Sample, route: str) -> None:
        received_ns = time.time_ns()
        raw = sample.attachment
        try:
            attachment = wire.parse_attachment(None if raw is None else raw.to_bytes())
        except PubSubError:
            with self._lock:
                self._refuse(REFUSED_ATTACHMENT)
            return
        if attachment.publisher_gid in _process.PUBLISHER_GIDS:
            return  # delivered intra-process already
        if self.max_rate_hz and not self._due(attachment, route):
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
            attachment, payload = wire.split_frame(data)
        except PubSubError:
            with self._lock:
                self._refuse(REFUSED_ATTACHMENT)
            return
        if attachment.publisher_gid in _process.PUBLISHER_GIDS:
            return  # delivered intra-process already (never sent here; a forged frame)
        if self.max_rate_hz and not self._due(attachment, ROUTE_LANE):
            return
        self._arrived((payload, attachment, ROUTE_LANE, received_ns, False), inline=True)

    def _due(self, attachment: wire.Attachment, route: str) -> bool:
        """Whether a message passes ``max_rate_hz`` (the first after each interval, per
        publisher); one that does not is counted in ``decimated``, its number still judged."""
        gid = attachment.publisher_gid
        if route in _DESCRIPTOR_ROUTES and self._from_ours(gid, route):
            return True  # our publisher sends this stream at our rate already
        now = time.monotonic()
        with self._lock:
            rate = self._rates.get(gid)
            if rate is None:
                rate = self._rates[gid] = RateLimit(self.max_rate_hz)
            if rate.admit(now):
                return True
            self._judge(attachment, route, self.node.graph.publisher(gid))
            self.counters.decimated += 1
            return False

    def _arrived(self, item: tuple[Any, ...], inline: bool = False) -> None:
        """Queue an arrived sample (``inline``: deliver at once if nothing waits, see
        :meth:`_enqueue`). One built for us is deserialized now (descriptors imported, holds
        taken: released if it is dropped before delivery), with its publisher's info, or with
        the gid alone when its token has not arrived (rmw_zenoh does not wait either)."""
        payload, attachment, route, received_ns, _ = item
        publisher = self.node.graph.publisher(attachment.publisher_gid)  # once per message
        if route in _DESCRIPTOR_ROUTES:
            try:
                msg = self._deserialize(payload, attachment, route, publisher)
            except Exception as exc:  # typed errors expected; a backend bug is counted too
                self._count_error(exc, attachment, route, publisher)
                return
            item = (msg, attachment, route, received_ns, True)
        self._enqueue(item, inline, publisher)

    def _count_error(self, exc: BaseException, attachment: wire.Attachment,
                     arrived_on: str | None = None,
                     publisher: wire.EndpointToken | None = None) -> None:
        """Count a message that failed to deserialize (``arrived_on``: its route, when it failed
        on arrival, before the queue saw its number: an error, not also a gap). One whose
        backend memory its publisher reused before the import is no fault of its bytes: under
        keep-last the reader fell more than its queue behind, what keep-last drops (counted in
        ``dropped``); under keep-all the publisher judged this subscription gone (Zenoh closed
        its link while it was stalled) and took its memory back: lost in transit (``lost``)."""
        overwritten = isinstance(exc, BufferOverwrittenError)
        with self._lock:
            if arrived_on is not None:
                self._judge(attachment, arrived_on, publisher)
            if not overwritten:
                self.counters.errors += 1
            elif self.history == wire.KEEP_LAST:
                self.counters.dropped += 1
            else:
                self.counters.lost += 1
        if overwritten:
            _log.debug("%r: dropped a message from %s, overwritten before its import: %s",
                       self, attachment.publisher_gid.hex(), exc)
            return
        self.last_error = exc
        _log.warning("%r: dropped a message from %s: %s", self,
                     attachment.publisher_gid.hex(), exc,
                     exc_info=not isinstance(exc, RosidlBufferError))

    def deliver_intra(self, msg: Message, attachment: wire.Attachment) -> Waker | None:
        """A message from a publisher of this process (its snapshot), on the publisher's
        thread: queued, never run here. Returns the waker of the executor that runs it, for
        the publisher to notify once its publish has sent everything (None: nothing to wake).

        The intra-process case of :meth:`_enqueue`, without its other routes' branches (it runs
        for every in-process message): the stream is numbered exactly by its publisher, no
        duplicate can come, nothing runs inline and nothing is owned."""
        if self.max_rate_hz and not self._due(attachment, ROUTE_INTRA):
            return None
        item = (msg, attachment, ROUTE_INTRA, time.time_ns(), False)
        with self._lock:
            if self._closed:
                return None
            # (_judge for the intra stream, one C call: its publisher numbers it exactly)
            verdict = self._streams.track(_STREAM[ROUTE_INTRA], attachment.publisher_gid,
                                          attachment.sequence_number, True)
            if (verdict is not None and self._count_verdict(verdict, ROUTE_INTRA)
                    and self.history == wire.KEEP_LAST):
                self._refuse(REFUSED_LATE)  # (as _enqueue)
                return None
            evicted, schedule = self._queue_item(item)
        if evicted is not None and evicted[4]:  # an owned message (a lane's) leaves the queue
            release_buffers(evicted[0])
        return self.node.scheduler.make_ready(self) if schedule else None

    def _queue_item(self, item: tuple[Any, ...]) -> tuple[tuple[Any, ...] | None, bool]:
        """Append ``item`` to the keep-last queue (call with ``self._lock`` held); returns the
        item it pushed out (counted in ``dropped``), if any, and whether the subscription must
        be made ready (it was not)."""
        queue = self._queue
        evicted = None
        if len(queue) == queue.maxlen:
            self.counters.dropped += 1
            evicted = queue[0]
        queue.append(item)
        schedule = not self._scheduled
        self._scheduled = True
        return evicted, schedule

    def _judge(self, attachment: wire.Attachment, route: str,
               publisher: wire.EndpointToken | None) -> bool:
        """Count what ``attachment`` says of its stream (gaps, jumps); whether the message is
        late, older than one already seen there (call with ``self._lock`` held)."""
        stream, exact, restarts = _judging(route, publisher)
        verdict = self._streams.track(stream, attachment.publisher_gid,
                                      attachment.sequence_number, exact, stream == _OWN, restarts)
        return verdict is not None and self._count_verdict(verdict, route)

    def _count_verdict(self, verdict: tuple[bool, int, bool, bool], route: str) -> bool:
        """Count what a verdict of :class:`._streams.Streams` says (``(duplicate, lost, late,
        jump)``, the second copies counted by the caller); whether the message is late (call
        with ``self._lock`` held)."""
        _, lost, late, jump = verdict
        if lost:
            if route == ROUTE_LANE:
                self.counters.dropped += lost  # the lane's keep-last queue overwrote
            else:
                self.counters.lost += lost
        elif jump:
            self.counters.sequence_jumps += 1
        return late

    def _from_ours(self, gid: bytes, route: str) -> bool:
        """Is ``gid`` one of our publishers in another process? (See :meth:`_enqueue`.)"""
        if route == ROUTE_INTRA:
            return False
        token = self.node.graph.publisher(gid)
        return token is not None and token.locality is not None

    def _enqueue(self, item: tuple[Any, ...], inline: bool = False,
                 publisher: Any = _UNRESOLVED) -> None:
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
        route = item[2]
        attachment = item[1]
        if route == ROUTE_INTRA:
            publisher = None
            ours = False
        else:
            if publisher is _UNRESOLVED:
                publisher = self.node.graph.publisher(attachment.publisher_gid)
            # Only our publishers in other processes may send a message twice (see _streams),
            # and only their stamps are known to be unique: another implementation may stamp
            # alike. One not discovered yet may be ours (its first messages can come before
            # its token): its copies are recognized too, trusting its stamps meanwhile.
            ours = publisher is None or publisher.locality is not None
        stream, exact, restarts = _judging(route, publisher)
        with self._lock:
            # One C call judges the number and, for ours, the stamp (a second copy's stream
            # still advances); None: a new message, in order.
            verdict = None if self._closed else self._streams.admit(
                stream, attachment.publisher_gid, attachment.sequence_number,
                attachment.source_timestamp_ns if ours else None, exact, stream == _OWN, restarts)
            if self._closed:
                closed = True
            elif verdict is not None and verdict[0]:  # a second copy (see _streams)
                self._count_verdict(verdict, route)
                closed = True  # (not queued: released below, as a closed one is)
                self._refuse(REFUSED_DUPLICATE)
            elif (verdict is not None and self._count_verdict(verdict, route)
                  and self.history == wire.KEEP_LAST):
                # Older than one already delivered on its stream: a route switch (Zenoh to the
                # lane) let a later message overtake it. A keep-last reader gets each
                # publisher's messages in order (its gap was counted when the later one came).
                closed = True  # (not queued: released below, as a closed one is)
                self._refuse(REFUSED_LATE)
            else:
                closed = False
                queue = self._queue
                lane = route == ROUTE_LANE
                if (inline and not queue and not self.node.scheduler.has_ready()
                        and (lane or self._policy.trusted)
                        and (gate is None or gate.acquire(blocking=False))):
                    run_now = lane or self._policy.arrived_inline()
                    if not run_now:
                        gate.release()  # type: ignore[union-attr]  # Zenoh arrivals have one
                if not run_now:
                    evicted, schedule = self._queue_item(item)
        if run_now:
            try:
                ran = self._run_item(item, inline=True)
            finally:
                if gate is not None:
                    gate.release()
            if lane and ran:
                self.node.scheduler.ran_inline()
            return
        if closed:
            evicted = item
        elif schedule:
            self.node.scheduler.schedule(self)
        # Only an owned message holds anything: serialized bytes hold nothing, an intra-process
        # message's shares of the publisher's buffers end when it is collected.
        if evicted is not None and evicted[4]:
            release_buffers(evicted[0])

    def last_sequence(self, stream: str, gid: bytes) -> int | None:
        """The last number judged on ``stream`` from publisher ``gid`` (None: none yet)."""
        with self._lock:
            return self._streams.last(stream, gid)

    # -- discovery --------------------------------------------------------------------------
    def on_publisher(self, token: wire.EndpointToken, appeared: bool) -> None:
        """A matching publisher appeared or left. Its streams' numbers are kept (the tracker
        forgets the oldest by itself): a publisher whose token leaves and comes back is the
        same one after a reconnect (a gid names one endpoint of one session), for instance
        when Zenoh closed the link to this process after it stalled a keep-all put for
        ``wait_before_close``, and what it sent meanwhile is lost, and counted."""
        if not appeared:
            with self._lock:
                self._streams.forget(token.gid)
                self._rates.pop(token.gid, None)

    # -- executor ------------------------------------------------------------------------------
    def run_one(self) -> bool:
        """Deliver the next queued message; whether its callback ran."""
        with self._lock:
            if self._closed or not self._queue:
                self._scheduled = False
                return False
            item = self._queue.popleft()
            again = bool(self._queue)
            self._scheduled = again
        if again:  # others wait: take turns with the node's other subscriptions
            self.node.scheduler.schedule(self)
        return self._run_item(item)

    def _run_item(self, item: tuple[Any, ...], inline: bool = False) -> bool:
        """Deserialize a queued payload if it still is one, then run the callback; whether it
        ran (not for a message that failed to decode or arrived after close)."""
        payload, attachment, route, received_ns, owned = item
        if self.raw:  # the bytes as they came (CPU routes only); an intra message serialized
            msg = bytes(serialize_message(payload)) if route == ROUTE_INTRA else bytes(payload)
        elif owned or route == ROUTE_INTRA:
            msg = payload
        else:
            try:
                msg = self._deserialize(payload, attachment, route)
            except Exception as exc:  # typed errors expected; a backend bug is counted too
                self._count_error(exc, attachment)
                return False
        node = self.node
        if self._closed or node.closed:  # a closing node starts no callback
            if owned:
                release_buffers(msg)  # imported for us alone, and nobody will read it
            return False
        with self._lock:
            self.counters.received += 1
        in_flight = node.scheduler.in_flight  # what close() waits for
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
        log_callback_error(_log, self, exc)

    def _deserialize(self, payload: bytes, attachment: wire.Attachment, route: str,
                     publisher: Any = _UNRESOLVED) -> Message:
        # Only a payload built for us may hold descriptors, which need the publisher's info
        # (the gid alone when it is not discovered yet). CPU payloads need none.
        info = None
        if route in _DESCRIPTOR_ROUTES:
            gid = attachment.publisher_gid
            if publisher is _UNRESOLVED:
                publisher = self.node.graph.publisher(gid)
            info = (endpoint_info(publisher) if publisher is not None else
                    unknown_publisher_info(gid, self.topic_name, self.msg_type.__msgtype__))
        return deserialize_message(payload, self.msg_type, backends=self.node.backends,
                                   endpoint_info=info)

    # -- teardown ------------------------------------------------------------------------------
    def destroy(self) -> None:
        """Undeclare this subscription (also done by :meth:`Node.close`)."""
        self._on_destroy(self)
        self._undeclare()

    def _undeclare(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            owned = [item[0] for item in self._queue if item[4]]
            self._queue.clear()  # the rest: serialized bytes or shared intra messages
        self.node.graph.wake()  # a wait_for_publishers on another thread returns now
        for msg in owned:
            release_buffers(msg)
        _process.remove_subscription(self.base_key, self)
        undeclare_quietly(self._liveliness, *self._subscribers)
        # Let go of them here, in the close the exit waits for: a zenoh entity dropped later on a
        # daemon thread, while the interpreter finalizes, aborts the process (its Rust drop
        # cannot take the GIL back).
        self._liveliness, self._subscribers = None, []
        if self._lane_reader is not None:  # the waker closes it once detached
            self.node.lane.detach(self._lane_reader, close=True)
        endpoint_gone(self._backends, self.info)

