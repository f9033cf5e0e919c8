"""``Node``: its share of a Zenoh session, its discovery graph and its executor.

Shaped after ``rclpy.node.Node``. Callbacks of every subscription and timer of a node run one
at a time: on the node's own executor thread (``Node(executor="thread")``, the default), or on
the user's thread inside :meth:`Node.spin` / :meth:`Node.spin_once` (``Node(executor="manual")``,
as rclpy's ``rclpy.spin(node)``), so an application busy in Python pays no GIL hand-off to a
library thread. Either way the executor waits on one waker (:mod:`._waker`), no longer than
the nearest timer deadline (:mod:`.timer`), and runs each ready subscription's next message and
each due timer; a subscription is queued at most once, whatever the number of messages in its
keep-last queue. A node added to a user's executor (:mod:`buffer_pubsub.executors`) has its
callbacks run there instead, in parallel as their callback groups allow
(:mod:`buffer_pubsub.callback_groups`).

Discovery is the ROS 2 graph carried by ``@ros2_lv`` liveliness tokens: peers appear on PUT and
vanish on DELETE, which Zenoh also sends when a peer process dies (SIGKILL included).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import math
import operator
import os
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from typing import TYPE_CHECKING, Any

import zenoh

from rosidl_buffer import BufferBackend, RosidlBufferError, local_host_id
from rosidl_buffer.messages import Message, buffer_fields, get_message_type, get_type_hash

from . import _process, _sessions, fast_lane as _fast_lane, wire
from ._executor import NodeExecutor, user_spin, wait_seconds
from ._info import endpoint_gone, endpoint_info
from ._waker import Waker
from ._zenoh import inherited, run_bounded, typed_zenoh_errors, undeclare_quietly
from .callback_groups import CallbackGroup, MutuallyExclusiveCallbackGroup
from .config import make_config, resolve_domain_id
from .graph import Graph, NodeInfo, TopicEndpointInfo, node_info
from .errors import (
    ExecutorModeError,
    InvalidEndpointError,
    NodeClosedError,
)
from .node_logger import NodeLogger
from .names import expand_topic_name, validate_namespace, validate_node_name
from .publisher import Publisher, replay_history
from .qos import DEFAULT_DEPTH, QoSProfile, resolve_qos
from .subscription import Subscription
from .timer import Timer, TimerSet, period_ns

if TYPE_CHECKING:
    from .executors import Executor

__all__ = ["Node"]

_log = logging.getLogger(__name__)

#: Budget of :meth:`Node.close` on a frozen or vanished peer (all blocking steps together).
CLOSE_TIMEOUT_S = 3.0
EXECUTOR_MODES = ("thread", "manual")


class Node:
    """A participant of the pub/sub graph.

    ``Node(name, config=None, namespace="", domain_id=None, *, router=None, backends=None,
    executor="thread", waker=None, fast_lane=None, inline_callbacks=True)``: ``config`` is a
    ``zenoh.Config`` or the path of a Zenoh JSON5 file, ``router`` a Zenoh router endpoint (see
    :mod:`buffer_pubsub.config` for the defaults); ``domain_id`` defaults to env
    ``ROS_DOMAIN_ID`` or 0; ``backends`` overrides the buffer backends (by default every
    backend registered in :mod:`rosidl_buffer.registry`, loaded once per process).
    ``executor="thread"`` runs callbacks on a thread of the node;
    ``"manual"`` runs them only inside :meth:`spin` / :meth:`spin_once` on the caller's thread.
    ``waker`` replaces the executor's wake-up source (see :mod:`buffer_pubsub._waker`).
    ``fast_lane``: carry descriptors to same-host subscriptions of other processes over the lane
    (:mod:`buffer_pubsub.fast_lane`); None follows env ``WARP_BUFFER_FAST_LANE`` (on by
    default). The executor's waker (a ``LaneWaker`` unless ``waker`` says otherwise) carries
    the lane: its callbacks run on the executor thread or in :meth:`spin`; a custom ``waker``
    that is not a ``LaneWaker`` turns the lane off.
    ``inline_callbacks`` (``executor="thread"`` only): a subscription whose callbacks proved
    short runs them on the thread its Zenoh sample arrived on when nothing waits before it,
    skipping the hand-off to the node's thread (:mod:`buffer_pubsub._inline`); False always
    hands off. Either way one callback of the node runs at a time, in arrival order.
    Added to an executor (``executor.add_node(node)``, :mod:`buffer_pubsub.executors`), the
    node's callbacks run there instead, as their callback groups allow
    (``default_callback_group``: one at a time).
    Nodes of a process configured alike share one Zenoh session (``node.session``), as
    rmw_zenoh's nodes of one context do (:mod:`buffer_pubsub._sessions`).
    Use as a context manager or call :meth:`close`, which undeclares everything (after the
    callbacks running then ended, within its budget) and closes the session if no other node
    uses it.
    """

    @_process.in_flight
    def __init__(
        self,
        name: str,
        config: zenoh.Config | str | os.PathLike[str] | None = None,
        namespace: str = "",
        domain_id: int | None = None,
        *,
        router: str | None = None,
        backends: Mapping[str, BufferBackend] | None = None,
        executor: str = "thread",
        waker: Waker | None = None,
        fast_lane: bool | None = None,
        inline_callbacks: bool = True,
    ) -> None:
        _process.check_not_exiting()  # fail fast: add_node below refuses it anyway
        self.name = validate_node_name(name)
        self.namespace = validate_namespace(namespace)
        if executor not in EXECUTOR_MODES:
            raise InvalidEndpointError(f"executor must be one of {EXECUTOR_MODES}, got {executor!r}")
        self.domain_id = resolve_domain_id(domain_id)
        self.backends: dict[str, BufferBackend] = (
            dict(backends) if backends is not None else _process.default_backends())
        self.locality = wire.Locality(local_host_id(), os.getpid(), os.getuid())
        self.executor_mode = executor
        self._closed = False
        self._close_done = threading.Event()  # set once close() finished
        self._lock = threading.RLock()
        #: The graph of the domain as this node sees it (it shares the node's lock).
        self.graph = Graph(self._lock)
        self._publishers: list[Publisher] = []
        self._subscriptions: list[Subscription] = []
        self._own_waker = waker is None  # a waker the user gave stays the user's to close
        waker, self.lane = _executor_waker(waker, fast_lane)
        # executor="thread": a Zenoh sample may run its callback on its arrival thread (see
        # buffer_pubsub._inline); the gate keeps one callback of the node at a time.
        self._gate = threading.Lock() if executor == "thread" else None
        self._spin_lock = threading.Lock()  # executor="manual": the one thread that spins
        #: Zenoh arrivals may run short callbacks on their own thread (see the class doc).
        self.inline_callbacks = executor == "thread" and bool(inline_callbacks)
        self._timers = TimerSet(waker.notify)  # due timers are made ready by the node's loop
        self.scheduler = NodeExecutor(waker, _nothing_periodic, self._gate, self._timers)
        self._owner: Executor | None = None  # the user's executor the node was added to
        #: The group of subscriptions and timers created without ``callback_group`` (rclpy's).
        self.default_callback_group: CallbackGroup = MutuallyExclusiveCallbackGroup()
        self._thread: threading.Thread | None = None
        # One logger for the node's life: its filters keep their state per call site.
        # (the manager's getLogger: logging.getLogger("root") is the root logger, and rclpy's
        # node "root" has a logger of its own)
        self._logger = NodeLogger(logging.Logger.manager.getLogger(
            self.get_fully_qualified_name().strip("/").replace("/", ".")))

        try:
            config_obj = make_config(config, router)
            # Nodes configured alike share a session, as rmw_zenoh's nodes of one context do
            # (typed errors, unreachable-router warnings: see connectivity).
            self._shared_session = _sessions.acquire(config_obj)
            self.session: zenoh.Session = self._shared_session.session
        except BaseException:
            self._close_waker()  # its eventfd: a retry loop would run out of fds
            raise
        self.max_message_size = _max_message_size(config_obj)
        try:
            self.zid = str(self.session.zid())
            self.node_id = _process.next_id()
            if executor == "thread":
                self._thread = threading.Thread(
                    target=self.scheduler.run, name=f"buffer_pubsub:{name}", daemon=True)
                self._thread.start()
            with typed_zenoh_errors("cannot declare the node's liveliness"):
                self._node_token = self.session.liveliness().declare_token(wire.NodeToken(
                    self.domain_id, self.zid, self.node_id, self.namespace, name).key())
                self._graph_subscriber = self.session.liveliness().declare_subscriber(
                    wire.liveliness_domain_selector(self.domain_id), self._on_liveliness,
                    history=True)
                self._routes_key = wire.routes_key(self.domain_id, self.zid, self.node_id)
                self._routes_queryable = self.session.declare_queryable(
                    self._routes_key, self._on_routes_query)
            _process.add_node(self)  # closed at exit if nobody closes it
        except BaseException:
            self.scheduler.stop()
            undeclare_quietly(*(getattr(self, name, None) for name in (
                "_routes_queryable", "_graph_subscriber", "_node_token")))
            _sessions.release(self._shared_session, CLOSE_TIMEOUT_S)
            self._close_waker()
            raise

    # -- context manager -----------------------------------------------------------------------
    def __enter__(self) -> Node:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is None:
            self.close()
            return
        try:  # an exception (KeyboardInterrupt, say) is on its way out: never replace it
            self.close()
        except Exception:
            _log.exception("closing node %s while %s propagates", self.name, exc_type.__name__)

    def __repr__(self) -> str:
        return f"Node({self.name!r}, namespace={self.namespace!r}, domain_id={self.domain_id})"

    #: Whether :meth:`close` was called (read-only; a C getter: every callback checks it).
    closed = property(operator.attrgetter("_closed"))

    @_process.in_flight
    def close(self) -> None:
        """Undeclare every endpoint and token, stop the executor and close the Zenoh session
        (when no other node shares it).

        Bounded: the steps that may block on a frozen peer share ``CLOSE_TIMEOUT_S`` seconds
        (what is not done by then finishes in the background); Zenoh failures are logged, never
        raised. Called again meanwhile (another thread, the exit of the interpreter), it returns
        once the first close finished.
        """
        with self._lock:
            closing = self._closed
            self._closed = True
            endpoints: list[Publisher | Subscription] = [*self._publishers, *self._subscriptions]
            self._publishers.clear()
            self._subscriptions.clear()
        if closing:  # another thread closes it: done when that close is (not inside a callback
            # of the node, which that close may be waiting for)
            if not self.scheduler.in_flight.here():
                self._close_done.wait(CLOSE_TIMEOUT_S + 1.0)
            return
        try:
            self._close_steps(endpoints)
        finally:
            endpoints.clear()  # what they hold goes now, on this thread (see Subscription)
            _process.remove_node(self)
            self._close_done.set()

    def _close_steps(self, endpoints: list[Publisher | Subscription]) -> None:
        for timer in self._timers.close():  # none starts from here (a running one is waited for)
            timer.forget()
        self.graph.close()
        self.scheduler.stop()
        deadline = time.monotonic() + CLOSE_TIMEOUT_S

        def left() -> float:  # every step shares one budget; the last still gets a moment
            return max(0.2, deadline - time.monotonic())

        def hand_back() -> None:  # the user's executor runs no more of our callbacks
            owner = self._owner
            if owner is not None:
                owner.remove_node(self, timeout_sec=max(0.0, deadline - time.monotonic()))

        def undeclare() -> None:
            for endpoint in tuple(endpoints):  # (close() clears the list once it returns)
                try:  # one endpoint's failure must not leave the others declared
                    endpoint.destroy()
                except Exception:
                    _log.exception("undeclaring %r of node %s failed", endpoint, self.name)
            undeclare_quietly(self._routes_queryable, self._graph_subscriber, self._node_token)

        # Ctrl-C during a step lets the (bounded) steps finish, then propagates: a session left
        # open keeps Zenoh's callback threads, and the interpreter cannot exit past them.
        # A callback running now (on any thread: Ctrl-C closes the node while one runs) ends
        # before the endpoints are undeclared, so its publishes still go out.
        interrupted: KeyboardInterrupt | None = None
        # (In a fork's child the callbacks in flight were the parent's threads': none ends here.)
        for step in (hand_back,
                     lambda: inherited() or self.scheduler.in_flight.wait_idle(left()),
                     lambda: run_bounded(undeclare, left(), f"undeclaring node {self.name}"),
                     lambda: self._join_executor_thread(left()),
                     self._close_waker,
                     lambda: _sessions.release(self._shared_session, left())):
            try:
                step()
            except KeyboardInterrupt as exc:
                interrupted = exc
        if interrupted is not None:
            raise interrupted

    def _join_executor_thread(self, timeout: float) -> None:
        if self._thread is not None and threading.current_thread() is not self._thread:
            self._thread.join(timeout=timeout)

    def _close_waker(self) -> None:
        # After the executor stopped: a lane waker closes the readers detached from it.
        if self._own_waker:
            self.scheduler.waker.close()  # type: ignore[attr-defined]  # ours: a LaneWaker

    def _check_open(self) -> None:
        if self._closed:
            raise NodeClosedError(f"node {self.name!r} is closed")

    # -- spinning (executor="manual") ----------------------------------------------------------
    def spin_once(self, timeout: float | None = None) -> int:
        """Run the callbacks ready now, waiting up to ``timeout`` seconds for the first (as
        rclpy: None or negative waits until one is ready, 0 does not wait); returns how many ran.
        Only for ``Node(executor="manual")``, one spinning thread at a time."""
        wait = wait_seconds(timeout)
        with self._spinning(), user_spin():
            return self.scheduler.spin_once(wait)

    def spin(self, timeout: float | None = None) -> None:
        """Run callbacks on this thread until the node is closed (or ``timeout`` seconds pass;
        None or negative: no limit). Ctrl-C raises KeyboardInterrupt here, as in rclpy. For
        ``executor="manual"``, one spinning thread at a time; a node that runs its callbacks on
        its own thread (the default) goes on doing so while this waits as long (the port of
        ``rclpy.spin(node)``)."""
        wait = wait_seconds(timeout)
        if self.executor_mode == "thread" and self._owner is None:
            self._check_open()
            if self.scheduler.in_flight.here():
                raise ExecutorModeError(
                    f"spin() inside a callback of node {self.name!r} would hold up its other "
                    "callbacks until it is closed")
            self._close_done.wait(wait)  # (Ctrl-C interrupts the wait, as rclpy.spin)
            return
        with self._spinning(), user_spin():
            deadline = None if wait is None else time.monotonic() + wait
            while not self._closed:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return
                self.scheduler.spin_once(
                    NodeExecutor.TICK_S if left is None else min(left, NodeExecutor.TICK_S))

    @contextlib.contextmanager
    def _spinning(self) -> Iterator[None]:
        """This thread spins the node: refused on a node that spins itself, a closed one, one
        in an executor, or one another thread spins (its callbacks would overlap: they run one
        at a time)."""
        self._check_open()
        if self._owner is not None:
            raise ExecutorModeError(
                f"node {self.name!r} is in {self._owner!r}, which runs its callbacks; spin the "
                "executor, or remove the node from it first")
        if self.executor_mode != "manual":
            raise ExecutorModeError(
                f"node {self.name!r} runs callbacks on its own thread; create it with "
                "executor='manual' to run them in spin_once() (spin() just waits here)")
        if not self._spin_lock.acquire(blocking=False):
            raise ExecutorModeError(f"node {self.name!r} is already spinning (in another "
                                    "thread, or this callback's own spin)")
        try:
            yield
        finally:
            self._spin_lock.release()

    # -- a user's executor (buffer_pubsub.executors) --------------------------------------------
    @property
    def executor(self) -> Executor | None:
        """The executor this node was added to (None: the node runs its own callbacks)."""
        return self._owner

    def enter_executor(self, executor: Executor) -> None:
        """``executor`` takes this node (called by its ``add_node``, not by users); refused
        while the node is closed, in another executor, or spun by another thread
        (executor="manual")."""
        with self._lock:
            self._check_open()
            if self._owner is not None:
                raise ExecutorModeError(f"node {self.name!r} is already in {self._owner!r}; "
                                        "remove it there first")
            if self.executor_mode == "manual" and not self._spin_lock.acquire(blocking=False):
                raise ExecutorModeError(f"node {self.name!r} is spinning (node.spin() in another "
                                        "thread): stop that spin before adding it to an executor")
            self._owner = executor

    def leave_executor(self, executor: Executor) -> None:
        """``executor`` gave the node's callbacks back (called by its ``remove_node``)."""
        with self._lock:
            if self._owner is not executor:
                return
            self._owner = None
            if self.executor_mode == "manual":
                self._spin_lock.release()  # node.spin() may run again

    # -- endpoints -----------------------------------------------------------------------------
    def _resolve_type(self, msg_type: type[Message] | str) -> type[Message]:
        if isinstance(msg_type, str):
            return get_message_type(msg_type)
        if isinstance(msg_type, type) and issubclass(msg_type, Message):
            return msg_type
        raise InvalidEndpointError(f"msg_type must be a message class or name, got {msg_type!r}")

    def _endpoint_token(self, kind: str, topic: str, type_name: str, qos: QoSProfile,
                        backends: dict[str, str] | None) -> wire.EndpointToken:
        return wire.EndpointToken(
            domain_id=self.domain_id, zid=self.zid, node_id=self.node_id,
            entity_id=_process.next_id(), kind=kind, namespace=self.namespace,
            node_name=self.name, topic=topic, type_name=type_name,
            type_hash=get_type_hash(type_name),
            qos=wire.QoSProfile.of(qos.depth, qos.history, qos.durability, qos.reliability),
            backends=backends, locality=self.locality)

    def _installed_metadata(self, names: Sequence[str]) -> dict[str, str]:
        return {name: self.backends[name].get_backend_metadata() for name in names}

    def _topic(self, topic: str) -> str:
        return expand_topic_name(topic, self.name, self.namespace)

    def create_publisher(self, msg_type: type[Message] | str, topic: str,
                         depth: int | QoSProfile = DEFAULT_DEPTH, *,
                         history: str | None = None, reliability: str | None = None,
                         durability: str | None = None,
                         qos_profile: int | QoSProfile | None = None) -> Publisher:
        """A publisher of ``msg_type`` on ``topic`` (relative names resolve in the namespace).

        QoS: keep-last ``depth`` (default 10) and the policy keywords, or a
        :class:`~buffer_pubsub.qos.QoSProfile` in their place (positional, or rclpy's
        ``qos_profile=``): ``create_publisher(Image, "/image", qos_profile_sensor_data)``.
        ``reliability="best_effort"`` puts with Zenoh's best-effort reliability, as rmw_zenoh.

        ``history="keep_last"`` (default) publishes with Zenoh congestion control DROP, so a
        frozen or slow subscriber never stalls ``publish()``; ``"keep_all"`` uses BLOCK (no loss
        in Zenoh's queues, ``publish()`` waits for room), as rmw_zenoh does.
        ``durability="transient_local"`` keeps the last ``depth`` messages for subscriptions
        that come later (latched: ``/tf_static``, a map), as rmw_zenoh's: a Zenoh advanced
        publisher's cache. Its messages travel as CPU bytes (rmw_zenoh routes no buffers for
        transient-local endpoints).
        """
        self._check_open()
        cls = self._resolve_type(msg_type)
        qos = resolve_qos(depth, history, reliability, durability, qos_profile)
        transient = qos.transient_local
        fq_topic = self._topic(topic)
        # As rmw_zenoh's buffer-aware publishers: cpu plus every installed backend's metadata
        # (a type without a top-level uint8[], or a transient-local one, advertises nothing).
        advertised = ({"cpu": "", **self._installed_metadata(list(self.backends))}
                      if buffer_fields(cls) and not transient else None)
        token = self._endpoint_token(wire.PUBLISHER_KIND, fq_topic, cls.__msgtype__, qos,
                                     advertised)
        with typed_zenoh_errors(f"cannot declare a publisher on {fq_topic}"):
            publisher = Publisher(self, cls, token, qos.depth, qos.history,
                                  on_destroy=self._forget)
        with self._lock:
            closed = self._closed  # close() ran meanwhile: it did not see this one
            if not closed:
                self._publishers.append(publisher)
                peers = [t for t in self.graph.endpoints() if publisher.matches(t)]
        if closed:
            publisher.destroy()
            self._check_open()
        for peer in peers:
            publisher.on_subscription(peer, True)
        return publisher

    def create_subscription(
        self,
        msg_type: type[Message] | str,
        topic: str,
        callback: Callable[..., Any],
        depth: int | QoSProfile = DEFAULT_DEPTH,
        acceptable_buffer_backends: str | Sequence[str] = "cpu",
        *,
        with_info: bool = False,
        history: str | None = None,
        reliability: str | None = None,
        durability: str | None = None,
        qos_profile: int | QoSProfile | None = None,
        raw: bool = False,
        max_rate: float | None = None,
        callback_group: CallbackGroup | None = None,
    ) -> Subscription:
        """A subscription calling ``callback(msg)`` (``callback(msg, info)`` with ``with_info``)
        on this node's executor for every message of ``topic``.

        ``acceptable_buffer_backends``: ``"cpu"``, ``"any"`` (every loaded backend) or a comma
        separated list of backend names (or a list of them); advertised to publishers through
        discovery.
        QoS as :meth:`create_publisher` takes it (``depth`` or a ``QoSProfile``).
        ``history="keep_last"`` keeps the newest ``depth`` messages waiting for the callback
        (older ones are dropped and counted); ``"keep_all"`` keeps every one (as rmw_zenoh).
        ``durability="transient_local"`` also receives, first, what transient-local publishers
        published before it came (up to ``depth`` each), as rmw_zenoh's; it takes CPU bytes
        only.
        ``raw=True`` (CPU-only subscriptions) passes the serialized CDR bytes instead of a
        message, decoding nothing (rclpy's ``raw``): for tools that measure or record.
        ``max_rate``: at most this many messages a second from each publisher, the first after
        each interval (a viewer that looks at a few frames a second). Publishers of ours honour
        it before they serialize for this subscription, so they save the work; for others
        (rmw_zenoh knows nothing of it) the subscription drops the extra messages on arrival,
        before decoding them. The keep-last ``depth`` applies to what passes.
        ``callback_group``: which callbacks may run beside this one on a multi-threaded
        executor (:mod:`buffer_pubsub.callback_groups`); default ``default_callback_group``.
        """
        self._check_open()
        if not callable(callback):
            raise InvalidEndpointError(f"callback must be callable, got {callback!r}")
        callback_group = self._callback_group(callback_group)
        cls = self._resolve_type(msg_type)
        qos = resolve_qos(depth, history, reliability, durability, qos_profile)
        transient = qos.transient_local
        fq_topic = self._topic(topic)
        from rosidl_buffer import parse_acceptable_backends

        try:
            accepted = parse_acceptable_backends(
                acceptable_buffer_backends, ["cpu", *self.backends])
        except ValueError as exc:
            raise InvalidEndpointError(str(exc)) from None
        rate = _max_rate(max_rate)
        if transient and accepted != ["cpu"]:
            raise InvalidEndpointError(
                "a transient-local subscription takes CPU bytes only (rmw_zenoh serves those "
                "endpoints on the base key, with no buffer routing): acceptable_buffer_backends="
                f"{acceptable_buffer_backends!r}")
        if raw and accepted != ["cpu"]:
            raise InvalidEndpointError(
                "raw=True takes CPU bytes only: a backend's descriptor means nothing serialized "
                f"(acceptable_buffer_backends={acceptable_buffer_backends!r})")
        advertised = (_subscription_advertisement(acceptable_buffer_backends, accepted, self)
                      if buffer_fields(cls) and not transient else None)
        token = dataclasses.replace(self._endpoint_token(
            wire.SUBSCRIPTION_KIND, fq_topic, cls.__msgtype__, qos, advertised), max_rate_hz=rate)
        with typed_zenoh_errors(f"cannot declare a subscription on {fq_topic}"):
            subscription = Subscription(self, cls, token, callback, qos.depth, accepted,
                                        with_info, qos.history, callback_group, raw=raw,
                                        on_destroy=self._forget)
        with self._lock:
            closed = self._closed  # close() ran meanwhile: it did not see this one
            if not closed:
                self._subscriptions.append(subscription)
        if closed:
            subscription.destroy()
            self._check_open()
        if transient:
            replay_history(subscription)  # this process's transient-local publishers' messages
        return subscription

    def _callback_group(self, group: CallbackGroup | None) -> CallbackGroup:
        if group is None:
            return self.default_callback_group
        if not isinstance(group, CallbackGroup):
            raise InvalidEndpointError(f"callback_group must be a CallbackGroup, got {group!r}")
        return group

    # -- timers --------------------------------------------------------------------------------
    def create_timer(self, timer_period_sec: float, callback: Callable[[], Any],
                     callback_group: CallbackGroup | None = None, *,
                     autostart: bool = True) -> Timer:
        """A timer calling ``callback()`` every ``timer_period_sec`` seconds (steady clock) on
        this node's executor, where its subscription callbacks run, as rclpy's.

        ``callback_group``: which callbacks may run beside it on a multi-threaded executor;
        default ``default_callback_group``. ``autostart=False`` creates it cancelled, for
        :meth:`Timer.reset` to start. A late timer skips the ticks it missed rather than
        running them in a burst. Raises InvalidEndpointError for a period that is not a
        positive, finite number of seconds, a callback that is not callable or a bad group;
        NodeClosedError on a closed node.
        """
        self._check_open()
        period = period_ns(timer_period_sec)
        if not callable(callback):
            raise InvalidEndpointError(f"callback must be callable, got {callback!r}")
        timer = Timer(self, self._timers, callback, period,
                      self._callback_group(callback_group), autostart=bool(autostart))
        self._timers.add(timer)  # NodeClosedError if close() ran meanwhile
        return timer

    def destroy_timer(self, timer: Timer) -> bool:
        """Cancel ``timer`` for good and drop it (a callback running now finishes); whether it
        was a timer of this node (as rclpy's)."""
        if not isinstance(timer, Timer) or timer.node is not self:
            return False
        known = self._timers.remove(timer)
        timer.forget()
        return known

    # -- rclpy's names ---------------------------------------------------------------------------
    def get_name(self) -> str:
        """The node's name, without its namespace."""
        return self.name

    def get_namespace(self) -> str:
        """The node's namespace (``"/"`` for the root namespace, as rclpy reports it)."""
        return self.namespace or "/"

    def get_fully_qualified_name(self) -> str:
        """The node's namespace and name joined by a slash (``/ns/camera``, ``/camera``)."""
        return f"{self.namespace}/{self.name}"

    def get_logger(self) -> NodeLogger:
        """The node's logger (always the same one): a Python logger named after the node
        (``<namespace>.<name>``, dots for slashes, as rclpy names a node's logger) that also
        takes rclpy's calls (``throttle_duration_sec=``, ``once=``, ``skip_first=``, ``warn``,
        ``fatal``, ``get_child``: :mod:`buffer_pubsub.node_logger`). Configure its output with
        :mod:`logging` (``basicConfig``): the library adds no handler."""
        return self._logger

    def destroy_publisher(self, publisher: Publisher) -> bool:
        """Destroy ``publisher`` (:meth:`Publisher.destroy`); whether it was this node's."""
        return self._destroy_endpoint(publisher, self._publishers)

    def destroy_subscription(self, subscription: Subscription) -> bool:
        """Destroy ``subscription`` (:meth:`Subscription.destroy`); whether it was this
        node's."""
        return self._destroy_endpoint(subscription, self._subscriptions)

    def _destroy_endpoint(self, endpoint: Any, group: list[Any]) -> bool:
        with self._lock:
            known = endpoint in group
        if known:
            endpoint.destroy()
        return known

    def destroy_node(self) -> None:
        """rclpy's name of :meth:`close`."""
        self.close()

    @property
    def timers(self) -> list[Timer]:
        """The node's timers (not destroyed), as rclpy's ``Node.timers``."""
        return self._timers.timers()

    def _forget(self, endpoint: Publisher | Subscription) -> None:
        with self._lock:
            for group in (self._publishers, self._subscriptions):
                if endpoint in group:
                    group.remove(endpoint)

    def routes(self) -> list[dict[str, Any]]:
        """Every publisher of this node with the route it takes to each subscription now
        (:meth:`Publisher.routes`), as plain data (what the node answers on its admin key)."""
        with self._lock:
            publishers = list(self._publishers)
        return [{"publisher": publisher.gid.hex(), "topic": publisher.topic_name,
                 "type": publisher.msg_type.__msgtype__,
                 "routes": [{"subscription": r.subscription_gid.hex(), "route": r.route,
                             "via": r.via, "reason": r.reason} for r in publisher.routes()]}
                for publisher in publishers]

    def _on_routes_query(self, query: zenoh.Query) -> None:
        try:
            payload = json.dumps({"node": self.name, "namespace": self.namespace or "/",
                                  "publishers": self.routes()})
            query.reply(self._routes_key, payload.encode())
        except Exception:  # a Zenoh thread: never raise into it
            _log.debug("answering a routes query failed", exc_info=True)

    # -- discovery -----------------------------------------------------------------------------
    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            token = wire.parse_token(key)
            if isinstance(token, wire.EndpointToken):
                token.gid  # derived from the key: a malformed one fails here, not in a hook
        except RosidlBufferError as exc:  # PubSubError, or a type name no message can have
            _log.debug("ignoring liveliness token %s: %s", key, exc)
            return
        graph = self.graph
        with self._lock:
            if self._closed:
                return
            events = (graph.put(key, token) if sample.kind == zenoh.SampleKind.PUT
                      else graph.delete(key))
            hooks = [(token, appeared, [p for p in self._publishers if p.matches(token)],
                      [s for s in self._subscriptions if s.matches(token)])
                     for token, appeared in events]
            graph.changed.notify_all()
        # Hooks run outside the lock (a backend may be slow); Publisher.on_subscription
        # re-checks the graph under the lock before it keeps a peer, so a DELETE racing past
        # its PUT leaves no ghost behind.
        for token, appeared, publishers, subscriptions in hooks:
            for publisher in publishers:
                try:
                    publisher.on_subscription(token, appeared)
                except Exception:  # a failing backend hook must not break discovery
                    _log.exception("negotiation with %s failed", token.key())
            for subscription in subscriptions:
                subscription.on_publisher(token, appeared)
            if not appeared and not token.is_publisher:
                # Only its departure ends what backends keep for a subscription (blocks owed
                # to it): not the end of one of our publishers, whose frames it may still
                # import. Reported whether or not a publisher of ours still matches it.
                endpoint_gone(self.backends.values(), endpoint_info(token))

    # -- the graph (rclpy's names; a closed node knows no graph: NodeClosedError) ----------------
    def get_topic_names_and_types(self) -> list[tuple[str, list[str]]]:
        """Topics seen in the graph (this domain) with their type names, like rclpy."""
        self._check_open()
        return _names_and_types((t.topic, t.type_name) for t in self.graph.endpoints())

    def get_node_names_and_namespaces(self) -> list[tuple[str, str]]:
        """``(name, namespace)`` of every node of the domain, this one included, like rclpy: two
        nodes that share a name are listed twice."""
        return sorted((n.name, n.namespace) for n in self.get_nodes())

    def get_nodes(self) -> list[NodeInfo]:
        """Every node of the domain (name, namespace, enclave, Zenoh session), this one
        included."""
        self._check_open()
        return sorted((node_info(t) for t in self.graph.nodes()),  # one token per node
                      key=lambda n: (n.namespace, n.name, n.zid))

    def _endpoints(self, kind: str, topic: str | None) -> list[TopicEndpointInfo]:
        self._check_open()
        tokens = self.graph.endpoints(kind, topic)
        return [TopicEndpointInfo.from_token(t) for t in sorted(
            tokens, key=lambda t: (t.topic, t.namespace, t.node_name, t.gid))]

    def get_publishers_info_by_topic(self, topic_name: str) -> list[TopicEndpointInfo]:
        """Every publisher of ``topic_name`` (relative names resolve in this node's namespace)
        in the domain, ours and other ROS 2 nodes', with QoS and advertised backends."""
        return self._endpoints(wire.PUBLISHER_KIND, self._topic(topic_name))

    def get_subscriptions_info_by_topic(self, topic_name: str) -> list[TopicEndpointInfo]:
        """Every subscription of ``topic_name`` in the domain (see
        :meth:`get_publishers_info_by_topic`)."""
        return self._endpoints(wire.SUBSCRIPTION_KIND, self._topic(topic_name))

    def count_publishers(self, topic_name: str) -> int:
        """How many publishers ``topic_name`` has in the domain (see
        :meth:`get_publishers_info_by_topic`)."""
        return len(self.get_publishers_info_by_topic(topic_name))

    def count_subscribers(self, topic_name: str) -> int:
        """How many subscriptions ``topic_name`` has in the domain (see
        :meth:`get_subscriptions_info_by_topic`)."""
        return len(self.get_subscriptions_info_by_topic(topic_name))

    def get_endpoints_by_node(self, node_name: str, node_namespace: str = "/"
                              ) -> list[TopicEndpointInfo]:
        """The publishers and subscriptions of one node (``ros2 node info``)."""
        return self._endpoints_of(node_name, node_namespace,
                                  (wire.PUBLISHER_KIND, wire.SUBSCRIPTION_KIND))

    def get_publisher_names_and_types_by_node(self, node_name: str, node_namespace: str = "/"
                                              ) -> list[tuple[str, list[str]]]:
        """The topics one node publishes, with their types, like rclpy."""
        return self._topics_of(node_name, node_namespace, wire.PUBLISHER_KIND)

    def get_subscriber_names_and_types_by_node(self, node_name: str, node_namespace: str = "/"
                                               ) -> list[tuple[str, list[str]]]:
        """The topics one node subscribes to, with their types, like rclpy."""
        return self._topics_of(node_name, node_namespace, wire.SUBSCRIPTION_KIND)

    def _topics_of(self, node_name: str, node_namespace: str, kind: str
                   ) -> list[tuple[str, list[str]]]:
        return _names_and_types((info.topic_name, info.topic_type)
                                for info in self._endpoints_of(node_name, node_namespace, (kind,)))

    def _endpoints_of(self, node_name: str, node_namespace: str, kinds: tuple[str, ...]
                      ) -> list[TopicEndpointInfo]:
        namespace = _namespace(node_namespace)
        return [info for kind in kinds for info in self._endpoints(kind, None)
                if info.node_name == node_name and _namespace(info.node_namespace) == namespace]

    # Services: other nodes' servers and clients, as their tokens declare them (this transport
    # has no services of its own to offer or call).
    def get_service_names_and_types(self) -> list[tuple[str, list[str]]]:
        """Services seen in the graph (a server or a client declares one) with their types,
        like rclpy."""
        self._check_open()
        return _names_and_types((t.topic, t.type_name) for t in self.graph.services())

    def get_service_names_and_types_by_node(self, node_name: str, node_namespace: str = "/"
                                            ) -> list[tuple[str, list[str]]]:
        """The services one node serves (``ros2 node info``'s Service Servers)."""
        return self._services_of(node_name, node_namespace, servers=True)

    def get_client_names_and_types_by_node(self, node_name: str, node_namespace: str = "/"
                                           ) -> list[tuple[str, list[str]]]:
        """The services one node calls (``ros2 node info``'s Service Clients)."""
        return self._services_of(node_name, node_namespace, servers=False)

    def _services_of(self, node_name: str, node_namespace: str, servers: bool
                     ) -> list[tuple[str, list[str]]]:
        self._check_open()
        namespace = _namespace(node_namespace)
        return _names_and_types(
            (t.topic, t.type_name) for t in self.graph.services()
            if (t.kind == wire.SERVICE_KIND) == servers and t.node_name == node_name
            and _namespace(t.namespace) == namespace)


def _namespace(namespace: str) -> str:
    """A node namespace in one form for comparing ("/" and "" alike, no trailing slash)."""
    return "" if namespace in ("", "/") else "/" + namespace.strip("/")


def _names_and_types(pairs: Iterable[tuple[str, str]]) -> list[tuple[str, list[str]]]:
    """``(name, [types])`` sorted, from ``(name, type)`` pairs (rclpy's names-and-types)."""
    found: dict[str, set[str]] = {}
    for name, type_name in pairs:
        found.setdefault(name, set()).add(type_name)
    return sorted((name, sorted(types)) for name, types in found.items())


def _max_rate(value: float | None) -> float:
    """A subscription's ``max_rate`` in Hz (0: none); InvalidEndpointError unless positive and
    finite."""
    if value is None:
        return 0.0
    try:
        rate = float(value)
    except (TypeError, ValueError):
        raise InvalidEndpointError(f"max_rate must be a number of Hz, got {value!r}") from None
    if isinstance(value, bool) or not 0 < rate < math.inf:
        raise InvalidEndpointError(f"max_rate must be a positive, finite rate in Hz, got "
                                   f"{value!r}")
    return rate


def _nothing_periodic() -> None:
    """The executor's housekeeping hook: nodes have no periodic work."""


def _subscription_advertisement(option: str | Sequence[str], accepted: list[str], node: Node
                                ) -> dict[str, str] | None:
    """What a subscription advertises, as rmw_zenoh's ``SubscriptionData::make``: accepting only
    CPU -> exactly ``cpu``; ``"any"`` -> every installed backend's metadata (no ``cpu``); a list
    -> its backends besides ``cpu``. None when that leaves nothing (``any`` without backends):
    such a subscription advertises no backends and listens on its own stream."""
    backends = [name for name in accepted if name != "cpu"]
    if not backends and not (isinstance(option, str) and option.strip() == "any"):
        return {"cpu": ""}
    return node._installed_metadata(backends) or None


def _executor_waker(waker: Waker | None, option: bool | None
                    ) -> tuple[Waker, _fast_lane.LaneWaker | None]:
    """The executor's waker (the user's, or a new :class:`~.fast_lane.LaneWaker`: one kind of
    waker whether the lane runs or not) and the lane it carries (None: the lane is off for this
    node, or the user's waker is not a lane waker).

    Raises:
        LaneUnavailableError: no eventfd could be made (out of file descriptors)."""
    if waker is None:
        waker = _fast_lane.LaneWaker()
    if isinstance(waker, _fast_lane.LaneWaker) and _fast_lane.status(option).available:
        return waker, waker
    return waker, None



#: Zenoh 1.10 delivers no network message over 1 GiB, whatever ``max_message_size`` says
#: (measured: 2**30 - 64 bytes arrive, 2**30 - 1 vanish without an error on either side).
ZENOH_MESSAGE_CEILING = 1 << 30
#: Room left for what Zenoh adds to a payload (key expression, attachment, encoding, framing).
FRAMING_RESERVE = 4096


def _max_message_size(config: zenoh.Config) -> int:
    """The largest serialized message this node publishes: the smaller of the configured
    ``transport/link/rx/max_message_size`` and Zenoh's ceiling, less the framing reserve. A
    larger one raises PayloadTooLargeError at publish() instead of vanishing."""
    try:
        configured = int(config.get_json("transport/link/rx/max_message_size"))
    except (zenoh.ZError, ValueError, TypeError):
        configured = ZENOH_MESSAGE_CEILING
    return min(configured, ZENOH_MESSAGE_CEILING) - FRAMING_RESERVE
