"""``Publisher``: routes every message to each matched subscription by exactly one route.

Per publish:

- subscriptions of this process get the message object itself (intra-process, no serialization,
  no copy of the payload) when they accept every backend the message's buffers live in, else a
  CPU copy; they are never served through Zenoh as well;
- a remote subscription that advertises a backend besides CPU gets its own channel
  ``<key>/_buf/<its gid>`` (over the same-host iceoryx2 lane when its process is on this host
  and user and has the lane on, see :mod:`._lane_routes`; else on Zenoh): a payload
  serialized for it alone when a backend agreed to serve it (``on_discovering_endpoint``)
  and holds one of the message's buffers (``create_descriptor_with_endpoint`` per buffer,
  CPU bytes where that returns None), else the shared CPU serialization;
- subscriptions that accept only CPU share one CPU serialization on ``<key>/_buf_cpu``;
- subscriptions that know nothing of buffers (no extra segment) get CPU bytes on the base key.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import threading
import time
from dataclasses import dataclass, field
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import zenoh

from rosidl_buffer import Buffer, BufferImplBase, EndpointInfo
from rosidl_buffer.messages import Message, deserialize_message, iter_buffers, serialize_message

from . import _lane_routes, _process, fast_lane, wire
from ._info import endpoint_gone, endpoint_info
from ._snapshot import snapshot
from .loan import Loan, LoanPool, flat_buffer_fields
from ._validation import validate_message
from ._zenoh import undeclare_quietly
from .errors import (
    InvalidEndpointError,
    LoanError,
    NodeClosedError,
    PayloadTooLargeError,
    TransportError,
)

if TYPE_CHECKING:
    from .node import Node

__all__ = ["Publisher", "seal_and_list_backends"]

_log = logging.getLogger(__name__)
#: How long destroy() waits for a publish in flight on another thread before leaving the
#: Zenoh publishers to that publish to undeclare.
UNDECLARE_WAIT_S = 1.0

_BUFFER_AWARE_ENCODING = zenoh.Encoding.APPLICATION_CDR.with_schema(wire.BUFFER_AWARE_SCHEMA)


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
        impl = buffers[0].get_impl()  # perf: its impl's methods, without Buffer's forwarding
        impl.seal()
        name = impl.get_backend_type()
        backends = _ONE_BACKEND.get(name)
        if backends is None:
            backends = _ONE_BACKEND.setdefault(name, frozenset((name,)))
        return backends, impl.size(), (impl,)
    nbytes = 0
    for buffer in buffers:
        buffer.seal()
        nbytes += len(buffer)
    return (frozenset(buffer.get_backend_type() for buffer in buffers), nbytes,
            tuple(buffer.get_impl() for buffer in buffers))


_NO_BACKENDS: frozenset[str] = frozenset()
_ONE_BACKEND: dict[str, frozenset[str]] = {}


def cpu_copy(message: Message) -> Message:
    """A deep copy of ``message`` whose buffers all live in CPU memory."""
    return deserialize_message(serialize_message(message), type(message))


@dataclass
class _Peer:
    token: wire.EndpointToken
    info: EndpointInfo
    served: set[str] = field(default_factory=set)  # backends that agreed to serve this peer
    channel: Any = None  # zenoh.Publisher on <key>/_buf/<gid>, declared on first use
    lane: fast_lane.LaneWriter | None = None  # the same-host lane to it, opened at matching
    gone: bool = False  # vanished: its channel is (being) undeclared, puts are skipped
    ready: bool = False  # its route is settled (lane opened or not): wait_for_subscriptions
    # Serializes put and undeclare of the channel: a peer may vanish (discovery thread) while
    # publish() is putting to it, and a zenoh.Publisher must not be used from both at once.
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    # Served on its own channel: it advertises a backend besides CPU (see wire). Judged once
    # from its token (which never changes), not per publish.
    individual: bool = field(init=False)
    # What backends are told when descriptors are made for it: its info, plus the depth of
    # the lane's keep-last queue while the lane carries them (EndpointInfo.delivery_queue_depth).
    route_info: EndpointInfo = field(init=False)

    def __post_init__(self) -> None:
        self.individual = wire.accepts_backends(self.token.backends)
        self.route_info = self.info

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


def _close_route(channel: zenoh.Publisher | None, lane: fast_lane.LaneWriter | None) -> None:
    """Undeclare and close what :meth:`_Peer.take_route` took."""
    if channel is not None:
        undeclare_quietly(channel)
    if lane is not None:
        lane.close()


class Publisher:
    """Created by :meth:`Node.create_publisher`; publishes ``msg_type`` messages on a topic."""

    def __init__(self, node: Node, msg_type: type[Message], token: wire.EndpointToken,
                 depth: int, history: str = wire.KEEP_LAST) -> None:
        self.node = node
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
        self._sequences = itertools.count(1)
        self._sequence = 0  # the last one used
        self._closed = False
        # As rmw_zenoh: keep-last drops when Zenoh's queue to a peer is full (a frozen
        # subscriber never stalls publish()), keep-all blocks (no loss, publish() waits).
        self._congestion = (zenoh.CongestionControl.BLOCK if history == wire.KEEP_ALL
                            else zenoh.CongestionControl.DROP)
        # One CDR output buffer, reused while the serialized size stays the same: Zenoh copies
        # the bytes during put(), and a fresh buffer per message costs page faults (~10 ms at
        # 16 MiB). The lock keeps concurrent publish() calls from sharing it, and their
        # sequence numbers in the order they are sent.
        self._out: bytearray | None = None
        self._out_lock = threading.Lock()
        self._undeclare_after_send = False  # see _undeclare
        self._flat_buffers = flat_buffer_fields(msg_type)
        self._loans = LoanPool()
        self._remote: tuple[_Peer, ...] = ()  # peers in other processes, rebuilt on change
        self._backends = tuple(node.backends.values())
        for backend in self._backends:
            backend.on_creating_endpoint(self.info)
        self._base = self._declare_channel(self.base_key)
        self._cpu = self._declare_channel(wire.cpu_channel_key(self.base_key))
        _process.add_publisher(self.gid)
        self._liveliness = node.session.liveliness().declare_token(token.key())

    def __repr__(self) -> str:
        return f"Publisher({self.msg_type.__msgtype__}, {self.topic_name!r})"

    # -- matching ------------------------------------------------------------------------------
    def _matches(self, token: wire.EndpointToken) -> bool:
        return (not token.is_publisher and token.topic == self._token.topic
                and token.type_name == self._token.type_name
                and token.type_hash == self._token.type_hash)

    def _on_peer(self, token: wire.EndpointToken, appeared: bool) -> None:
        """A matching subscription appeared or vanished (called by the node's discovery)."""
        gid = token.gid
        if not appeared:
            with self._lock:
                peer = self._peers.pop(gid, None)
                self._update_remote()
                self._ready.notify_all()
            if peer is not None:
                peer.close()  # (backends hear of its departure from the node: see there)
            return
        info = endpoint_info(token)
        peer = _Peer(token, info)
        with self._lock:
            if self._closed or gid in self._peers:
                return
            existing = [p.info for p in self._peers.values()]
        if token.buffer_aware:
            for name, backend in self.node.backends.items():
                accepted, _groups = backend.on_discovering_endpoint(
                    info, existing, info.supported_backends)
                if accepted:
                    peer.served.add(name)
        # Negotiation ran unlocked; keep the peer only if it is still in the graph (checked
        # under the node's lock, which its DELETE takes before calling us), else a DELETE that
        # overtook us would leave a ghost peer pinning a block per publish.
        with self.node._lock:
            keep = self.node._still_in_graph(token)
            present = self.node._graph.get(gid) is token  # (whether or not our node closed)
            if keep:
                with self._lock:
                    keep = not self._closed and gid not in self._peers
                    if keep:
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

    def _open_lane(self, peer: _Peer) -> None:
        """Give a kept peer the same-host lane if it has one (~12 ms, once per match). Opened
        after the peer is kept, so publish() reaches it over Zenoh meanwhile."""
        node = self.node
        token = peer.token
        if node._lane is None or not _lane_routes.serves(
                node.locality, token, individual=peer.individual, served=bool(peer.served),
                keep_all=wire.KEEP_ALL in (self.history, wire.qos_history(token.qos))):
            return
        writer = _lane_routes.open_writer(self.base_key, token.gid)  # None: Zenoh serves it
        if writer is None:
            return
        with peer.lock:
            if not peer.gone:
                peer.use_lane(writer)
                writer = None
        if writer is not None:  # it vanished meanwhile
            writer.close()

    def _update_remote(self) -> None:
        """Rebuild the peers publish() serves through Zenoh; call with ``self._lock`` held.
        Subscriptions of this process are served in-process (they register there before their
        token is declared, so discovery already knows them as local)."""
        self._remote = tuple(peer for gid, peer in self._peers.items()
                             if not _process.is_local_subscription(gid))

    def get_subscription_count(self) -> int:
        """Matched subscriptions (local and remote) currently known through discovery."""
        return self.node._count_matching(
            wire.SUBSCRIPTION_KIND, self._token.topic, self._token.type_name,
            self._token.type_hash)

    def wait_for_subscriptions(self, count: int = 1, timeout: float | None = 10.0) -> bool:
        """Block until at least ``count`` subscriptions are matched and this publisher has
        settled the route to each (negotiated, same-host lane opened where one serves), so the
        next publish() takes the route it keeps; False on timeout."""
        deadline = None if timeout is None else time.monotonic() + timeout
        if not self.node._wait_matching(
                wire.SUBSCRIPTION_KIND, self._token.topic, self._token.type_name,
                self._token.type_hash, count, timeout):
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
        return Loan(self, factory, None if max_loans is None else max(1, int(max_loans)))

    def loan_stats(self) -> dict[str, int]:
        """Pooled messages ``created``, loans ``reused``, ``unpooled`` loans, ``pooled`` now."""
        return self._loans.stats()

    def publish(self, msg: Message) -> None:
        """Send ``msg`` to every matched subscription, each by exactly one route.

        Field values are checked first, whoever listens (SerializationError); a payload larger
        than the transport carries raises PayloadTooLargeError before anything is sent.
        """
        if type(msg) is not self.msg_type and not isinstance(msg, self.msg_type):
            raise InvalidEndpointError(
                f"publisher of {self.msg_type.__msgtype__} got {type(msg).__name__}")
        validate_message(msg)
        backends, nbytes, impls = seal_and_list_backends(msg, self._flat_buffers)  # write ends
        try:
            # perf: the flag and the peer tuple are read without the publisher's lock (each read
            # is atomic, and a destroy() racing this publish is no different from one that comes
            # right after the check).
            if self._closed:
                raise NodeClosedError(f"publisher on {self.topic_name!r} is closed")
            remote = self._remote
            # Numbered and sent under one lock: concurrent publish() calls leave in the order of
            # their sequence numbers (else subscribers count the overtaken ones as lost).
            with self._out_lock:
                if self._closed:  # destroyed while this publish waited for the lock
                    raise NodeClosedError(f"publisher on {self.topic_name!r} is closed")
                self._sequence = sequence = next(self._sequences)
                attachment = wire.Attachment(sequence, time.time_ns(), self.gid)
                if not remote:
                    self._publish_intra(msg, backends, attachment)
                    return
                try:
                    self._publish_remote(msg, backends, nbytes, attachment, remote)
                finally:
                    if self._undeclare_after_send:  # destroyed during this publish (see there)
                        undeclare_quietly(self._base, self._cpu)
        finally:
            for impl in impls:  # after the sends: readers are on their way meanwhile
                impl.end_publish()

    def _publish_remote(self, msg: Message, backends: frozenset[str], nbytes: int,
                        attachment: wire.Attachment, peers: tuple[_Peer, ...]) -> None:
        # Everything is serialized (and size-checked) before anything leaves, so a message too
        # large for the transport reaches nobody rather than some.
        cpu_payload: bytearray | None = None
        individual: list[tuple[_Peer, bytearray | None]] = []
        need_cpu_channel = need_base = need_cpu = False
        for peer in peers:
            if not peer.token.buffer_aware:
                need_base = True
            elif not peer.individual:
                need_cpu_channel = True
            elif peer.served & backends:
                individual.append((peer, self._checked(self._serialize_for(peer, msg))))
            else:
                individual.append((peer, None))  # the shared CPU serialization
                need_cpu = True
        if need_cpu_channel or need_base or need_cpu:
            if nbytes > self.node.max_message_size:
                self._checked(None, nbytes)  # hopeless: raise before copying a huge payload
            cpu_payload = self._out = self._checked(serialize_message(msg, out=self._out))
        self._publish_intra(msg, backends, attachment)
        encoded = attachment.encode()
        try:
            for peer, payload in individual:
                self._put_individual(peer, cpu_payload if payload is None else payload, encoded)
            if need_cpu_channel:
                self._cpu.put(cpu_payload, attachment=encoded)
            if need_base:
                self._base.put(cpu_payload, attachment=encoded, encoding=_BUFFER_AWARE_ENCODING)
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

    def _publish_intra(self, msg: Message, backends: frozenset[str],
                       attachment: wire.Attachment) -> None:
        subscriptions = _process.local_subscriptions(self._intra_key)
        if not subscriptions:
            return
        copy: Message | None = None
        domain_id = self.node.domain_id
        for subscription in subscriptions:
            if subscription.node.domain_id != domain_id:
                continue
            if not backends or backends.issubset(subscription.accepted):
                # the values as published, in an object of its own (see _snapshot)
                subscription._deliver_intra(snapshot(msg), attachment)
            else:
                if copy is None:
                    copy = cpu_copy(msg)
                subscription._deliver_intra(snapshot(copy), attachment)

    def _serialize_for(self, peer: _Peer, msg: Message) -> bytearray:
        backends = self.node.backends

        def route(buffer: Buffer) -> tuple[str, Any] | None:
            name = buffer.get_backend_type()
            if name not in peer.served:
                return None
            descriptor = backends[name].create_descriptor_with_endpoint(
                buffer.get_impl(), peer.route_info)
            return None if descriptor is None else (name, descriptor)

        return serialize_message(msg, route=route)

    def _put_individual(self, peer: _Peer, payload: bytearray, attachment: bytes) -> None:
        with peer.lock:
            if peer.gone:
                return  # the subscription vanished while we were publishing: nobody to send to
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
                # False: iceoryx2 reached no reader (it died before its DELETE came), so the
                # Zenoh put below cannot duplicate the message.
            if peer.channel is None:
                peer.channel = self._declare_channel(
                    wire.buffer_channel_key(self.base_key, peer.token.gid))
            peer.channel.put(payload, attachment=attachment)
            if peer.gone:  # closed while this put was blocked (see _Peer.close)
                _close_route(*peer.take_route())

    def _declare_channel(self, key: str) -> zenoh.Publisher:
        # Zenoh's same-session delivery is skipped: local subscriptions are served in-process.
        return self.node.session.declare_publisher(
            key, allowed_destination=zenoh.Locality.REMOTE, congestion_control=self._congestion)

    # -- teardown ------------------------------------------------------------------------------
    def destroy(self) -> None:
        """Undeclare this publisher (also done by :meth:`Node.close`)."""
        self.node._forget(self)
        self._undeclare()

    def _undeclare(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            peers = list(self._peers.values())
            self._peers.clear()
            self._remote = ()
            self._ready.notify_all()
        _process.remove_publisher(self.gid)
        self._loans.clear()
        undeclare_quietly(self._liveliness)
        for peer in peers:  # their routes; not their state in the backends: they live on, and
            peer.close()  # may import frames of ours still in flight (a lane's queue)
        # After a publish in flight on another thread: zenoh-python cannot undeclare a publisher
        # while a put uses it ("Already borrowed"). One that outlasts the wait (a keep-all put
        # blocked by a frozen peer) undeclares them itself when its sends return.
        self._undeclare_after_send = True  # before the wait: a publish ending meanwhile sees it
        if self._out_lock.acquire(timeout=UNDECLARE_WAIT_S):
            try:
                undeclare_quietly(self._base, self._cpu)  # (a second undeclare is harmless)
            finally:
                self._out_lock.release()
        endpoint_gone(self._backends, self.info)
