"""``Publisher``: routes every message to each matched subscription by exactly one route.

The routes are rmw_zenoh 0.10.5's (``rmw_publisher_data.cpp``), judged once per subscription
when it is discovered (:func:`wire.subscription_channel`), not per message:

- subscriptions of this process get a snapshot of the message (intra-process: a message object
  of their own sharing its buffers and arrays, no serialization, no copy of the payload) when
  they accept every backend the message's buffers live in, else a snapshot of a CPU copy; they
  are never served through Zenoh as well;
- on a topic whose type has a top-level ``uint8[]`` (buffer-aware):

  - subscriptions that advertise exactly ``cpu`` share one CPU serialization on
    ``<key>/_buf_cpu``;
  - every other subscription gets its own stream ``<key>/_buf/<its gid>`` (over the same-host
    lane when it is ours, on this host and user, see :mod:`._lane_routes`; else on
    Zenoh): a payload serialized for it alone when a backend agreed to serve it
    (``on_discovering_endpoint``) and holds one of the message's buffers
    (``create_descriptor_with_endpoint`` per top-level buffer, CPU bytes where that returns
    None), else the shared CPU serialization;
  - nothing is published while no subscription is matched;
  - while a subscription that advertises no backends is matched (a pre-0.10.5 rmw_zenoh node, a
    transient-local subscription: they listen on the base key only), every message goes once on
    the base key, which every ROS 2 subscription of the topic listens on; only our own
    subscriptions that a backend serves keep their stream as well (they recognize the base copy
    by its source timestamp and drop it). rmw_zenoh itself never reaches such subscriptions
    (its list of discovered subscriptions is never pruned);
- on any other topic every message goes on the base key (classic rmw_zenoh).

Sequence numbers count per stream (base key, ``_buf_cpu``, each ``_buf/<gid>`` with its lane,
intra-process), so whoever receives one stream from us sees 1, 2, 3...; source timestamps are
strictly increasing per publisher (the key of duplicate detection, see :mod:`._streams`). The two
shared streams (base key, ``_buf_cpu``) number every message that left, also while nobody read
them: a subscription that Zenoh judged gone and that comes back when it was their only reader
counts what it missed (a ``_buf/<gid>`` stream does so through its peer's resume).
"""

from __future__ import annotations

import collections
import dataclasses
import itertools
import logging
import threading
import time
import weakref
from dataclasses import dataclass, field
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, NamedTuple

import zenoh
import zenoh.ext

from rosidl_buffer import Buffer, BufferImplBase, EndpointInfo
from rosidl_buffer.buffer import impl_of
from rosidl_buffer.messages import Message, deserialize_message, iter_buffers, serialize_message

from . import _lane_routes, _process, fast_lane, wire
from ._info import endpoint_gone, endpoint_info
from ._rate import RateLimit
from ._snapshot import copier as snapshot_copier, snapshot
from .graph import matching_wait
from .loan import Loan, LoanPool, flat_buffer_fields
from ._validation import validate_message, validator
from ._zenoh import undeclare_quietly
from .errors import (
    InvalidEndpointError,
    LoanError,
    NodeClosedError,
    PayloadTooLargeError,
    TransportError,
    WrongMessageTypeError,
)

if TYPE_CHECKING:
    from ._waker import Waker
    from .node import Node
    from .subscription import Subscription

__all__ = ["Publisher", "RouteInfo", "replay_history", "seal_and_list_backends"]

_log = logging.getLogger(__name__)
#: How long destroy() waits for a publish in flight on another thread before leaving the
#: Zenoh publishers to that publish to undeclare.
UNDECLARE_WAIT_S = 1.0
#: Streams of subscriptions that left remembered per publisher (see Publisher._left_streams).
MAX_LEFT_STREAMS = 1024
#: Heartbeat period (s) of a transient-local publisher, for subscribers to detect a missed last
#: sample and fetch it from the cache (rmw_zenoh's SAMPLE_MISS_DETECTION_HEARTBEAT_PERIOD).
MISS_DETECTION_HEARTBEAT_S = 0.5
#: Transient-local publishers of this process by base key: a new transient-local subscription
#: here gets their history in-process (see replay_history).
_TRANSIENT: dict[str, weakref.WeakSet[Publisher]] = {}
_transient_lock = threading.Lock()


def seal_and_list_backends(msg: Message, flat: tuple[str, ...] | None
                           ) -> tuple[frozenset[str], int, tuple[BufferImplBase, ...]]:
    """Seal every buffer of ``msg`` (once per publish, every route); return the backend names
    they live in, their total size in bytes and their impls (for ``end_publish``), in one
    walk."""
    if flat is not None:  # (one field: no comprehension, whose frame costs more than it)
        buffers: Any = (getattr(msg, flat[0]),) if len(flat) == 1 else [
            getattr(msg, name) for name in flat]
    else:
        buffers = list(iter_buffers(msg))
    if not buffers:
        return _NO_BACKENDS, 0, ()
    if len(buffers) == 1:  # the common case: one buffer, its backend's set made once
        impl = impl_of(buffers[0])  # perf: its impl's methods, without Buffer's forwarding
        name, nbytes = impl.seal_for_publish()
        backends = _ONE_BACKEND.get(name)
        if backends is None:
            backends = _ONE_BACKEND.setdefault(name, frozenset((name,)))
        # (an impl without an end_publish of its own is not called for it)
        return backends, nbytes, (impl,) if type(impl).end_publish is not _NO_END else ()
    nbytes = 0
    for buffer in buffers:
        buffer.seal()
        nbytes += len(buffer)
    return (frozenset(buffer.get_backend_type() for buffer in buffers), nbytes,
            tuple(buffer.get_impl() for buffer in buffers))


_NO_BACKENDS: frozenset[str] = frozenset()
_NO_END = BufferImplBase.end_publish  # the default: nothing to do
_ONE_BACKEND: dict[str, frozenset[str]] = {}


def cpu_copy(message: Message) -> Message:
    """A deep copy of ``message`` whose buffers all live in CPU memory."""
    return deserialize_message(serialize_message(message), type(message))


@dataclass
class _Peer:
    token: wire.EndpointToken
    info: EndpointInfo
    # Which stream serves it (wire.SubscriptionChannel), judged once from its token (which never
    # changes), not per publish.
    stream: str
    served: set[str] = field(default_factory=set)  # backends that agreed to serve this peer
    channel: Any = None  # zenoh.Publisher on <key>/_buf/<gid>, declared on first use
    lane: fast_lane.LaneWriter | None = None  # the same-host lane to it, opened at matching
    gone: bool = False  # vanished: its channel is (being) undeclared, puts are skipped
    ready: bool = False  # its route is settled (lane opened or not): wait_for_subscriptions
    # Serializes put and undeclare of the channel: a peer may vanish (discovery thread) while
    # publish() is putting to it, and a zenoh.Publisher must not be used from both at once.
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    # The last number of its own stream (Zenoh channel and lane alike: one stream), advanced
    # under ``lock``; one that left and came back continues it (see Publisher._left_streams).
    sequence: int = 0
    # The publisher's publish count when this stream last numbered a message (or began).
    numbered_at: int = 0
    # A subscription that came back: (its last number, numbered_at) when it left. Its first
    # put skips one number per message published in between (see Publisher._continue_stream).
    resume: tuple[int, int] | None = None
    # What backends are told when descriptors are made for it: its info, plus the depth of
    # the lane's keep-last queue while the lane carries them (EndpointInfo.delivery_queue_depth).
    route_info: EndpointInfo = field(init=False)
    # A subscription of ours that asked for at most max_rate_hz messages a second: served on
    # its own stream at that rate (None: every message). Used by the publishing thread alone.
    rate: RateLimit | None = field(init=False)
    # It advertises only CPU and is on its own stream for its rate alone (see _update_remote).
    cpu_only: bool = False

    def __post_init__(self) -> None:
        self.route_info = self.info
        limited = self.token.is_ours and self.token.max_rate_hz
        self.rate = RateLimit(self.token.max_rate_hz) if limited else None

    @property
    def individual(self) -> bool:
        """Served on a stream of its own."""
        return self.stream == wire.SubscriptionChannel.OWN

    def use_lane(self, lane: fast_lane.LaneWriter | None) -> None:
        """Route to it by ``lane`` (None: by Zenoh); call with ``self.lock`` held."""
        self.lane = lane
        self.route_info = self.info if lane is None else dataclasses.replace(
            self.info, delivery_queue_depth=_lane_routes.queue_depth(self.token))

    def close(self) -> None:
        self.gone = True  # first: a put ending while we wait below sees it and closes the route
        if not self.lock.acquire(timeout=UNDECLARE_WAIT_S):
            # A put to this peer is blocked (keep-all, the peer frozen): it closes the route
            # itself when it returns (see Publisher._put_individual).
            return
        try:
            route = self.take_route()
        finally:
            self.lock.release()
        _close_route(*route)

    def take_route(self) -> tuple[zenoh.Publisher | None, fast_lane.LaneWriter | None]:
        """The channel and lane of this peer, which it has no more (call with ``lock`` held)."""
        channel, self.channel = self.channel, None
        lane, self.lane = self.lane, None
        return channel, lane


ROUTE_INTRA = "intra"
ROUTE_DESCRIPTOR = "descriptor"
ROUTE_CPU = "cpu"


@dataclass(frozen=True)
class RouteInfo:
    """How a publisher serves one subscription now (see :meth:`Publisher.routes`)."""

    subscription_gid: bytes
    route: str  # "intra", "descriptor" (zero-copy where a backend serves it) or "cpu" (bytes)
    via: str  # in process, the same-host lane, or the Zenoh key
    reason: str


class _Routing(NamedTuple):
    """The Zenoh streams one publish takes: the peers served on their own stream, whether the
    shared ``_buf_cpu`` stream and whether the base key are written."""

    own: tuple[_Peer, ...]
    cpu: bool
    base: bool


_NOBODY = _Routing((), False, False)


def _close_route(channel: zenoh.Publisher | None, lane: fast_lane.LaneWriter | None) -> None:
    """Undeclare and close what :meth:`_Peer.take_route` took."""
    if channel is not None:
        undeclare_quietly(channel)
    if lane is not None:
        lane.close()


class Publisher:
    """Created by :meth:`Node.create_publisher`; publishes ``msg_type`` messages on a topic."""

    def __init__(self, node: Node, msg_type: type[Message], token: wire.EndpointToken,
                 depth: int, history: str = wire.KEEP_LAST, *,
                 on_destroy: Callable[[Publisher], None] = lambda publisher: None) -> None:
        self.node = node
        self._on_destroy = on_destroy  # the node forgets it
        self.msg_type = msg_type
        self.topic_name = token.topic
        self.depth = depth
        self.history = history
        self._token = token
        self.gid = token.gid
        self.info = endpoint_info(token)
        self.base_key = wire.data_key(node.domain_id, token.topic, msg_type.__msgtype__)
        self._intra_key = self.base_key
        self._lock = threading.Lock()
        self._ready = threading.Condition(self._lock)  # a peer's route settled, or it left
        self._peers: dict[bytes, _Peer] = {}
        # Buffer-aware (it advertises backends): the _buf_cpu / _buf/<gid> routes apply.
        self._aware = token.backends is not None
        # One numbering per stream (see the module doc); source stamps strictly increase. The
        # shared streams count every message that left (read or not): one counter serves both.
        self._shared_sequences = itertools.count(1)
        self._intra_sequences = itertools.count(1)
        self._last_stamp = 0
        self._published = 0  # publish() calls, for the streams of subscriptions that came back
        # The streams of subscriptions that left, by gid: one whose token comes back is the same
        # subscription after a reconnect (Zenoh closed its link when it stalled, SIGSTOP say),
        # and continues its numbers: its reader keeps judging them (restarted from 1 they would
        # all look late), and what was published while it was away counts as lost there.
        self._left_streams: collections.OrderedDict[bytes, tuple[int, int]] = \
            collections.OrderedDict()
        self._closed = False
        # As rmw_zenoh: keep-last drops when Zenoh's queue to a peer is full (a frozen
        # subscriber never stalls publish()), keep-all blocks (no loss, publish() waits);
        # best-effort always drops, and Zenoh does not retransmit its samples.
        best_effort = token.qos.best_effort
        self._congestion = (zenoh.CongestionControl.BLOCK
                            if history == wire.KEEP_ALL and not best_effort
                            else zenoh.CongestionControl.DROP)
        self._reliability = (zenoh.Reliability.BEST_EFFORT if best_effort
                             else zenoh.Reliability.RELIABLE)
        # One CDR output buffer, reused while the serialized size stays the same: Zenoh copies
        # the bytes during put(), and a fresh buffer per message costs page faults (~10 ms at
        # 16 MiB). The lock keeps concurrent publish() calls from sharing it, and their
        # sequence numbers in the order they are sent.
        self._out: bytearray | None = None
        self._out_lock = threading.Lock()
        self._undeclare_after_send = False  # see _undeclare
        self._flat_buffers = flat_buffer_fields(msg_type)
        # Compiled once for the type: the publish path calls them, not their dispatchers.
        self._validate = validator(msg_type)
        self._snapshot = snapshot_copier(msg_type)  # what each in-process subscription gets
        self._loans = LoanPool(msg_type=self.msg_type)
        # Peers in other processes and the streams that serve them, rebuilt on change.
        self._remote: _Routing = _NOBODY
        self._backends = tuple(node.backends.values())
        for backend in self._backends:
            backend.on_creating_endpoint(self.info)
        # Transient-local, as rmw_zenoh's: an advanced publisher whose cache keeps the last
        # ``depth`` samples for late subscribers, detectable, with sample-miss heartbeats; it
        # advertises no backends, so everything goes on the base key. In-process late joiners
        # get the same from _history (see replay_history).
        self._transient = token.qos.transient_local
        self._history: collections.deque[tuple[Message, wire.Attachment, frozenset[str]]] | \
            None = collections.deque(maxlen=depth) if self._transient else None
        # What __init__ declares, undeclared by _undeclare() if a later step fails: the
        # session is shared with other nodes and outlives this node (see _sessions).
        self._base = self._cpu = self._base_matching = self._liveliness = None
        try:
            self._base = (self._declare_transient(self.base_key, depth) if self._transient
                          else self._declare_channel(self.base_key))
            self._cpu = (self._declare_channel(wire.cpu_channel_key(self.base_key))
                         if self._aware else None)
            # A type without buffer fields is put on the base key whenever Zenoh routes that key
            # to a subscriber in another session, as rmw_zenoh's publishers put it always: a ROS
            # 2 subscription declares its Zenoh subscriber before its token, and what is
            # published in between reaches it (and a plain Zenoh listener, which has no token,
            # gets it).
            self._base_matched = self._transient  # (its cache takes every message)
            self._base_matching = (None if self._aware or self._transient else
                                   self._base.declare_matching_listener(self._on_base_matching))
            if self._transient:
                self._remote = _Routing((), False, True)  # from the first publish, into its cache
                with _transient_lock:
                    _TRANSIENT.setdefault(self._intra_key, weakref.WeakSet()).add(self)
            _process.add_publisher(self.gid)
            self._liveliness = node.session.liveliness().declare_token(token.key())
        except BaseException:
            self._undeclare()
            raise

    def __repr__(self) -> str:
        return f"Publisher({self.msg_type.__msgtype__}, {self.topic_name!r})"

    # -- matching ------------------------------------------------------------------------------
    def matches(self, token: wire.EndpointToken) -> bool:
        """Is ``token`` a subscription of this topic, type and hash? (The node's discovery
        asks.)"""
        return (not token.is_publisher and token.topic == self._token.topic
                and token.type_name == self._token.type_name
                and token.type_hash == self._token.type_hash)

    def on_subscription(self, token: wire.EndpointToken, appeared: bool) -> None:
        """A matching subscription appeared or vanished (called by the node's discovery)."""
        gid = token.gid
        if not appeared:
            with self._lock:
                peer = self._peers.pop(gid, None)
                self._update_remote()
                self._ready.notify_all()
            if peer is not None:
                peer.close()  # (backends hear of its departure from the node: see there)
                self._remember_stream(peer)
            return
        info = endpoint_info(token)
        stream = (wire.subscription_channel(token) if self._aware
                  else wire.SubscriptionChannel.BASE)
        if token.is_ours and (stream == wire.SubscriptionChannel.BASE and self._aware
                              or stream == wire.SubscriptionChannel.CPU and token.max_rate_hz):
            # Ours listen on their own stream too: one that advertises no backend ("any" with
            # none installed) always, a CPU-only one that asked for a rate to get it there.
            stream = wire.SubscriptionChannel.OWN
        peer = _Peer(token, info, stream)
        peer.cpu_only = (stream == wire.SubscriptionChannel.OWN and self._aware
                         and wire.subscription_channel(token) == wire.SubscriptionChannel.CPU)
        with self._lock:
            if self._closed or gid in self._peers:
                return
            # the publisher first, then its peers (as rmw_zenoh passes existing_endpoints)
            existing = [self.info, *(p.info for p in self._peers.values())]
        if peer.individual:  # as rmw_zenoh: backends negotiate with subscriptions of own streams
            for name, backend in self.node.backends.items():
                accepted, _groups = backend.on_discovering_endpoint(
                    info, existing, info.supported_backends)
                if accepted:
                    peer.served.add(name)
        # Negotiation ran unlocked; keep the peer only if it is still in the graph (checked
        # under the node's lock, which its DELETE takes before calling us), else a DELETE that
        # overtook us would leave a ghost peer pinning a block per publish.
        graph = self.node.graph
        with graph.lock:
            keep = graph.holds(token)
            present = graph.current(gid) is token  # (whether or not our node closed)
            if keep:
                with self._lock:
                    keep = not self._closed and gid not in self._peers
                    if keep:
                        self._continue_stream(peer)
                        self._peers[gid] = peer
                        self._update_remote()
        if not keep:
            if not present:  # its DELETE (and the node's report of it) came before the
                endpoint_gone(self._backends, info)  # negotiation above registered it again
            return
        try:
            self._open_lane(peer)
        finally:
            with self._lock:
                peer.ready = True
                self._ready.notify_all()

    def _remember_stream(self, peer: _Peer) -> None:
        """Keep where ``peer``'s stream stands (see ``_left_streams``; bounded: the oldest
        goes first). Read after :meth:`_Peer.close`: no put numbers it any more."""
        if not peer.individual:
            return
        with self._lock:
            left = self._left_streams
            left[peer.token.gid] = (peer.resume if peer.resume is not None
                                    else (peer.sequence, peer.numbered_at))
            if len(left) > MAX_LEFT_STREAMS:
                left.popitem(last=False)

    def _continue_stream(self, peer: _Peer) -> None:
        """Number ``peer``'s stream on from where it stood when it left, skipping one number
        per message published meanwhile, which it missed (call with ``self._lock`` held). The
        skip is counted at its first put (:meth:`_put_individual`, under the publishing lock):
        a publish that began before the peer was kept neither reaches it nor escapes the
        count. A rate-limited stream skips none: its reader takes every number it is sent."""
        peer.numbered_at = self._published
        peer.resume = self._left_streams.pop(peer.token.gid, None)

    def _open_lane(self, peer: _Peer) -> None:
        """Give a kept peer the same-host lane if it has one (~12 ms, once per match). Opened
        after the peer is kept, so publish() reaches it over Zenoh meanwhile."""
        node = self.node
        token = peer.token
        if node.lane is None or not _lane_routes.serves(
                node.locality, token, individual=peer.individual, served=bool(peer.served),
                keep_all=self.history == wire.KEEP_ALL or token.qos.keep_all):
            return
        writer = _lane_routes.open_writer(self.base_key, token.gid,  # None: Zenoh serves it
                                          _lane_routes.queue_depth(token))
        if writer is None:
            return
        with peer.lock:
            if not peer.gone:
                peer.use_lane(writer)
                writer = None
        if writer is not None:  # it vanished meanwhile
            writer.close()

    def _on_base_matching(self, status: zenoh.MatchingStatus) -> None:
        with self._lock:
            if not self._closed:
                self._base_matched = status.matching
                self._update_remote()

    def _update_remote(self) -> None:
        """Rebuild the routes publish() takes through Zenoh (see the module doc); call with
        ``self._lock`` held. Subscriptions of this process are served in-process (they register
        there before their token is declared, so discovery already knows them as local)."""
        peers = [peer for gid, peer in self._peers.items()
                 if not _process.is_local_subscription(gid)]
        if not self._aware:  # (a transient-local publisher is never aware, always matched)
            self._remote = _Routing((), False, True) if peers or self._base_matched else _NOBODY
        elif not peers:
            self._remote = _NOBODY
        elif any(peer.stream == wire.SubscriptionChannel.BASE for peer in peers):
            # Base key for everyone; our own subscriptions a backend serves keep their stream
            # (for descriptors, see publish) and drop the base copy.
            self._remote = _Routing(tuple(peer for peer in peers if peer.individual
                                          and peer.token.is_ours and peer.served), False, True)
        else:
            own = tuple(peer for peer in peers if peer.individual)
            cpu = len(own) < len(peers)
            if cpu:
                # A rate-limited CPU-only subscription of ours also listens on _buf_cpu, which
                # carries every message while another CPU-only one is matched: it takes (and
                # thins) that stream, and its own is not written as well (twice its rate).
                own = tuple(peer for peer in own if not peer.cpu_only)
            self._remote = _Routing(own, cpu, False)

    def routes(self) -> list[RouteInfo]:
        """How each matched subscription is served now, with the reason (what ``warp-buffer
        topic info -v`` shows): in process, over the same-host lane, on its own Zenoh stream
        (descriptors where a backend serves it and holds the message's buffers, CPU bytes
        otherwise), on the shared CPU stream, or on the base key."""
        with self._lock:
            routing, peers = self._remote, list(self._peers.values())
        routes = []
        local = {s.gid for s in _process.local_subscriptions(self._intra_key)
                 if s.node.domain_id == self.node.domain_id}
        for gid in sorted(local):
            routes.append(RouteInfo(gid, ROUTE_INTRA, "in process",
                                    "same process: a snapshot of the message sharing its "
                                    "buffers, no copy (of a CPU copy for a subscription that "
                                    "does not accept its backend)"))
        own = {id(peer) for peer in routing.own}
        for peer in peers:
            gid = peer.token.gid
            if gid in local:
                continue
            rate = (f"; at most {peer.token.max_rate_hz:g} messages a second (its max_rate)"
                    if peer.rate is not None else "")
            if not self._aware:
                routes.append(RouteInfo(gid, ROUTE_CPU, "base key",
                                        "the type has no top-level uint8[]: classic rmw_zenoh"))
            elif id(peer) in own:
                via = ("same-host lane" if peer.lane is not None
                       else "own stream (_buf/<gid>)" + self._no_lane(peer))
                if peer.served:
                    why = "served by " + ", ".join(sorted(peer.served)) + self._why(peer, True)
                    routes.append(RouteInfo(gid, ROUTE_DESCRIPTOR, via, why + (
                        "; CPU bytes for a message whose buffers live elsewhere") + rate))
                else:
                    routes.append(RouteInfo(gid, ROUTE_CPU, via, "no backend serves it"
                                            + self._why(peer, False) + rate))
            elif routing.base:
                routes.append(RouteInfo(gid, ROUTE_CPU, "base key",
                                        "a subscription that advertises no backends is matched "
                                        "(it listens on the base key only): every subscription "
                                        "takes the base key"))
            else:
                routes.append(RouteInfo(gid, ROUTE_CPU, "shared CPU stream (_buf_cpu)",
                                        "it accepts only CPU" + (
                                            rate + ", thinning this stream itself" if rate
                                            else "")))
        return routes

    def _no_lane(self, peer: _Peer) -> str:
        """Why a subscription ``_lane_routes.serves`` picks for the lane (ours, on this host
        and user, in another process, served by a backend) takes Zenoh instead ("" for others)."""
        token = peer.token
        if not _lane_routes.serves(self.node.locality, token, individual=peer.individual,
                                   served=bool(peer.served)):
            return ""
        if self.node.lane is None:
            return ": the same-host lane is off in the publisher's process"
        if self.history == wire.KEEP_ALL or token.qos.keep_all:
            return ": keep-all endpoints take Zenoh, whose congestion control blocks"
        if token.qos.depth > fast_lane.MAX_DEPTH:
            return (f": its queue ({token.qos.depth}) is deeper than the same-host lane's "
                    f"{fast_lane.MAX_DEPTH} frames")
        if not peer.ready:
            return ": the same-host lane is being opened"
        return ": the same-host lane could not be opened (the subscriber's lane is off?)"

    def _why(self, peer: _Peer, served: bool) -> str:
        """The backends' own reasons about ``peer``, where they give one (``peer_decision``)."""
        reasons = []
        for name, backend in self.node.backends.items():
            decide = getattr(backend, "peer_decision", None)
            if decide is None or (name in peer.served) != served:
                continue
            try:
                reasons.append(f"{name}: {decide(peer.info).reason}")
            except Exception:  # an explanation must never break introspection
                continue
        return f" ({'; '.join(reasons)})" if reasons else ""

    def get_subscription_count(self) -> int:
        """Matched subscriptions (local and remote) currently known through discovery."""
        return self.node.graph.count(
            wire.SUBSCRIPTION_KIND, self._token.topic, self._token.type_name,
            self._token.type_hash)

    def wait_for_subscriptions(self, count: int = 1, timeout: float | None = 10.0) -> bool:
        """Block until at least ``count`` subscriptions are matched and this publisher has
        settled the route to each (negotiated, same-host lane opened where one serves), so the
        next publish() takes the route it keeps; False on timeout, or when the publisher is
        destroyed meanwhile (a closed one raises :class:`NodeClosedError`, as publish does).
        ``timeout`` as rclpy reads it: None, negative or infinite waits without limit."""
        count, timeout = matching_wait(count, timeout)
        if self._closed:
            raise NodeClosedError(f"publisher on {self.topic_name!r} is closed")
        deadline = None if timeout is None else time.monotonic() + timeout
        if not self.node.graph.wait(
                wire.SUBSCRIPTION_KIND, self._token.topic, self._token.type_name,
                self._token.type_hash, count, timeout, gone=lambda: self._closed):
            return False
        with self._ready:
            while sum(peer.ready for peer in self._peers.values()) < count:
                left = None if deadline is None else deadline - time.monotonic()
                if self._closed or (left is not None and left <= 0):
                    return False
                self._ready.wait(left)
        return True

    # -- publishing ----------------------------------------------------------------------------
    def loan(self, factory: Callable[[], Message], *, max_loans: int | None = None) -> Loan:
        """Loan a message whose buffers this publisher reuses: ``with pub.loan(f) as msg:``
        fill ``msg`` in place; it is published when the block ends (an exception publishes
        nothing and returns the loan). See :mod:`buffer_pubsub.loan`.

        ``factory`` makes a message when no pooled one is free (tensor_conversions' loan specs
        are factories). The loan ends at publish: do not write through views taken during the
        loan afterwards. On Warp's cpu device such a write faults (the pages are read-only
        until the next loan of the block); elsewhere it would change what zero-copy readers
        see. ``max_loans`` (default 16) bounds the pooled messages per factory key.
        """
        if self._closed:
            raise NodeClosedError(f"publisher on {self.topic_name!r} is closed")
        if not callable(factory):
            raise LoanError(f"a loan needs a factory that makes a message, got {factory!r}")
        return Loan(self._loans, self.publish, factory,
                    None if max_loans is None else max(1, int(max_loans)))

    def loan_stats(self) -> dict[str, int]:
        """Pooled messages ``created``, loans ``reused``, ``unpooled`` loans, ``pooled`` now."""
        return self._loans.stats()

    def publish(self, msg: Message) -> None:
        """Send ``msg`` to every matched subscription, each by exactly one route.

        Field values are checked first, whoever listens (SerializationError); a payload larger
        than the transport carries raises PayloadTooLargeError before anything is sent.
        """
        if self._loans.in_blocks and id(msg) in self._loans.in_blocks:
            raise LoanError("this message is on loan in a `with publisher.loan(...)` block, "
                            "which publishes it when the block ends: do not publish it inside")
        if type(msg) is self.msg_type:
            self._validate(msg)
        elif isinstance(msg, self.msg_type):  # a user's subclass
            validate_message(msg)
        else:
            raise WrongMessageTypeError(
                f"publisher of {self.msg_type.__msgtype__} got {type(msg).__name__}")
        backends, nbytes, impls = seal_and_list_backends(msg, self._flat_buffers)  # write ends
        # The executors of in-process subscriptions served: woken when publish() ends, also when
        # a later route fails.
        wakers: list[Waker] = []
        try:
            # perf: the flag and the peer tuple are read without the publisher's lock (each read
            # is atomic, and a destroy() racing this publish is no different from one that comes
            # right after the check).
            if self._closed:
                raise NodeClosedError(f"publisher on {self.topic_name!r} is closed")
            remote = self._remote
            # Stamped and sent under one lock: concurrent publish() calls leave in the order of
            # their numbers (else subscribers count the overtaken ones as lost).
            with self._out_lock:
                if self._closed:  # destroyed while this publish waited for the lock
                    raise NodeClosedError(f"publisher on {self.topic_name!r} is closed")
                stamp = self._last_stamp = max(time.time_ns(), self._last_stamp + 1)
                self._published += 1
                intra = None if self._history is None else self._remember(msg, stamp, backends)
                if remote is _NOBODY:
                    next(self._shared_sequences)  # (left, read on neither shared stream)
                    self._publish_intra(msg, backends, stamp, wakers, intra)
                    return
                try:
                    self._publish_remote(msg, backends, nbytes, stamp, remote, wakers, intra)
                finally:
                    if self._undeclare_after_send:  # destroyed during this publish (see there)
                        undeclare_quietly(self._base, self._cpu)
        finally:
            for impl in impls:  # after the sends: readers are on their way meanwhile
                impl.end_publish()
            for waker in wakers:  # last: a woken executor finds the GIL free soon
                waker.notify()

    def _publish_remote(self, msg: Message, backends: frozenset[str], nbytes: int, stamp: int,
                        routing: _Routing, wakers: list[Waker],
                        intra: wire.Attachment | None = None) -> None:
        """Send to every route (``wakers``, ``intra``: see :meth:`_publish_intra`)."""
        # Everything is serialized (and size-checked) before anything leaves, so a message too
        # large for the transport reaches nobody rather than some.
        need_base = routing.base
        need_cpu = routing.cpu or need_base
        individual: list[tuple[_Peer, bytearray | None]] = []
        now = time.monotonic()
        for peer in routing.own:
            if peer.rate is not None and not peer.rate.admit(now):
                continue  # at its max_rate: nothing serialized, nothing sent
            if peer.served & backends:
                individual.append((peer, self._checked(self._serialize_for(peer, msg))))
            elif not need_base:
                individual.append((peer, None))  # the shared CPU serialization
                need_cpu = True
            # (else the base copy serves it)
        cpu_payload: bytearray | None = None
        if need_cpu:
            if nbytes > self.node.max_message_size:
                self._checked(None, nbytes)  # hopeless: raise before copying a huge payload
            cpu_payload = self._out = self._checked(serialize_message(msg, out=self._out))
        if self._intra_key in _process.SUBSCRIPTIONS:
            self._publish_intra(msg, backends, stamp, wakers, intra)
        try:
            for peer, payload in individual:
                self._put_individual(peer, cpu_payload if payload is None else payload, stamp)
            # Numbered here: a message too large, or a send that failed before, took no number.
            shared = next(self._shared_sequences)
            if routing.cpu or need_base:
                attachment = wire.pack_attachment(shared, stamp, self.gid)
                if routing.cpu:
                    self._cpu.put(cpu_payload, attachment=attachment)  # type: ignore[union-attr]
                if need_base:
                    self._base.put(cpu_payload, attachment=attachment)
        except zenoh.ZError as exc:
            raise TransportError(f"publish on {self.topic_name}: {exc}") from exc

    def _checked(self, payload: bytearray | None, nbytes: int = 0) -> bytearray:
        """``payload`` if Zenoh carries it, else PayloadTooLargeError (None: always raise, for
        a message whose buffers alone, ``nbytes``, exceed the limit)."""
        limit = self.node.max_message_size
        if payload is None or len(payload) > limit:
            size = (f"{len(payload)} bytes" if payload is not None else
                    f"more than its {nbytes} buffer bytes")
            raise PayloadTooLargeError(
                f"a {self.msg_type.__msgtype__} message serializes to {size}, over the "
                f"{limit}-byte limit of the transport (Zenoh carries at most 1 GiB per message; "
                "see transport/link/rx/max_message_size); split it, or use a buffer backend")
        return payload

    def _publish_intra(self, msg: Message, backends: frozenset[str], stamp: int,
                       wakers: list[Waker], attachment: wire.Attachment | None = None) -> None:
        """Queue a snapshot of ``msg`` for each subscription of this process; adds the wakers
        of their executors to ``wakers`` (once each), which publish() notifies last.
        ``attachment``: the one its history keeps (a transient-local publisher's), else new."""
        subscriptions = _process.SUBSCRIPTIONS.get(self._intra_key)
        if not subscriptions:
            return
        if attachment is None:
            attachment = wire.new_attachment((next(self._intra_sequences), stamp, self.gid))
        copy: Message | None = None
        domain_id = self.node.domain_id
        make_snapshot = self._snapshot if type(msg) is self.msg_type else snapshot
        for subscription in subscriptions:
            if subscription.node.domain_id != domain_id:
                continue
            if not backends or backends.issubset(subscription.accepted):
                # the values as published, in an object of its own (see _snapshot)
                waker = subscription.deliver_intra(make_snapshot(msg), attachment)
            else:
                if copy is None:
                    copy = cpu_copy(msg)
                waker = subscription.deliver_intra(snapshot(copy), attachment)
            if waker is not None and waker not in wakers:
                wakers.append(waker)

    def _remember(self, msg: Message, stamp: int, backends: frozenset[str]) -> wire.Attachment:
        """Keep ``msg`` (a snapshot) in a transient-local publisher's history; its in-process
        attachment, numbered for every publish (call with ``_out_lock`` held)."""
        attachment = wire.new_attachment((next(self._intra_sequences), stamp, self.gid))
        self._history.append((snapshot(msg), attachment, backends))  # type: ignore[union-attr]
        return attachment

    def _replay(self, subscription: Subscription) -> None:
        """Deliver this transient-local publisher's history to ``subscription`` in process
        (see :func:`replay_history`), as :meth:`_publish_intra` delivers a message."""
        wakers: list[Waker] = []
        with self._out_lock:  # no publish interleaves
            seen = subscription.last_sequence("intra", self.gid)
            for msg, attachment, backends in tuple(self._history or ()):  # (destroy clears it)
                if seen is not None and attachment.sequence_number <= seen:
                    continue  # it reached the subscription live already
                copy = snapshot(msg if not backends or backends.issubset(subscription.accepted)
                                else cpu_copy(msg))
                waker = subscription.deliver_intra(copy, attachment)
                if waker is not None and waker not in wakers:
                    wakers.append(waker)
        for waker in wakers:
            waker.notify()

    def _serialize_for(self, peer: _Peer, msg: Message) -> bytearray:
        backends = self.node.backends

        def route(buffer: Buffer) -> tuple[str, Any] | None:
            impl = impl_of(buffer)
            name = impl.get_backend_type()
            if name not in peer.served:
                return None
            descriptor = backends[name].create_descriptor_with_endpoint(impl, peer.route_info)
            return None if descriptor is None else (name, descriptor)

        return serialize_message(msg, route=route)

    def _put_individual(self, peer: _Peer, payload: bytearray, stamp: int) -> None:
        with peer.lock:
            if peer.gone:
                return  # the subscription vanished while we were publishing: nobody to send to
            if peer.resume is not None:  # back: what was published while it was away is lost
                sequence, numbered_at = peer.resume
                peer.resume = None
                skipped = self._published - 1 - numbered_at  # (this message is the next)
                peer.sequence = sequence + (skipped if peer.rate is None else 0)
            peer.sequence = number = peer.sequence + 1
            peer.numbered_at = self._published
            attachment = wire.pack_attachment(number, stamp, self.gid)
            lane = peer.lane
            if lane is not None and lane.fits(len(attachment) + len(payload)):
                try:
                    if lane.write(attachment, payload):
                        return  # one route per message: the lane reached it
                except fast_lane.LaneError as exc:  # Zenoh carries this one; logged once
                    peer.use_lane(None)
                    lane.close()
                    _log.warning("lane to %s failed, Zenoh carries it: %s",
                                 peer.token.gid.hex(), exc)
                # False: the lane reached no reader (it died before its DELETE came), so the
                # Zenoh put below cannot duplicate the message.
            if peer.channel is None:
                peer.channel = self._declare_channel(
                    wire.buffer_channel_key(self.base_key, peer.token.gid))
            peer.channel.put(payload, attachment=attachment)
            if peer.gone:  # closed while this put was blocked (see _Peer.close)
                _close_route(*peer.take_route())

    def _declare_transient(self, key: str, depth: int) -> Any:
        # Misses are detected (sporadic heartbeats) and recovered from the cache by reliable
        # subscriptions. rmw_zenoh leaves detection off for best-effort, which then needs
        # Zenoh's timestamping (our default configuration has it off): it stays on, and
        # best-effort subscriptions do not recover, so what a peer sees is rmw_zenoh's.
        return zenoh.ext.declare_advanced_publisher(
            self.node.session, key, allowed_destination=zenoh.Locality.REMOTE,
            congestion_control=self._congestion, reliability=self._reliability,
            cache=zenoh.ext.CacheConfig(max_samples=depth), publisher_detection=True,
            sample_miss_detection=zenoh.ext.MissDetectionConfig(
                sporadic_heartbeat=MISS_DETECTION_HEARTBEAT_S))

    def _declare_channel(self, key: str) -> zenoh.Publisher:
        # Zenoh's same-session delivery is skipped: local subscriptions are served in-process.
        return self.node.session.declare_publisher(
            key, allowed_destination=zenoh.Locality.REMOTE, congestion_control=self._congestion,
            reliability=self._reliability)

    # -- teardown ------------------------------------------------------------------------------
    def destroy(self) -> None:
        """Undeclare this publisher (also done by :meth:`Node.close`)."""
        self._on_destroy(self)
        self._undeclare()

    def _undeclare(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            peers = list(self._peers.values())
            self._peers.clear()
            self._remote = _NOBODY
            self._ready.notify_all()
        self.node.graph.wake()  # a wait_for_subscriptions on another thread returns now
        _process.remove_publisher(self.gid)
        if self._transient:
            with _transient_lock:
                others = _TRANSIENT.get(self._intra_key)
                if others is not None:
                    others.discard(self)
                    if not others:
                        del _TRANSIENT[self._intra_key]
            self._history.clear()  # type: ignore[union-attr]
        self._loans.clear()
        undeclare_quietly(self._liveliness, self._base_matching)
        self._liveliness = self._base_matching = None  # (dropped here: see Subscription)
        for peer in peers:  # their routes; not their state in the backends: they live on, and
            peer.close()  # may import frames of ours still in flight (a lane's queue)
        # After a publish in flight on another thread: zenoh-python cannot undeclare a publisher
        # while a put uses it ("Already borrowed"). One that outlasts the wait (a keep-all put
        # blocked by a frozen peer) undeclares them itself when its sends return.
        self._undeclare_after_send = True  # before the wait: a publish ending meanwhile sees it
        if self._out_lock.acquire(timeout=UNDECLARE_WAIT_S):
            try:
                undeclare_quietly(self._base, self._cpu)  # (a second undeclare is harmless)
                self._base = self._cpu = None  # type: ignore[assignment]  # dropped here too
            finally:
                self._out_lock.release()
        endpoint_gone(self._backends, self.info)


def replay_history(subscription: Subscription) -> None:
    """Deliver to ``subscription``, a new transient-local one, what this process's
    transient-local publishers on its key keep (their last ``depth`` messages, oldest first),
    in-process as any of their messages (Zenoh serves other processes from the publishers'
    caches). A message published since the subscription registered reached it already, as do
    those before it in that publisher's history: they are skipped, never delivered twice."""
    with _transient_lock:
        publishers = list(_TRANSIENT.get(subscription.base_key, ()))
    for publisher in publishers:
        publisher._replay(subscription)
