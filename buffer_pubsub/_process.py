"""Process-wide state shared by every node of this process (rmw's "context").

- one id counter for node and entity ids (rmw_zenoh numbers them per context);
- the registry of local subscriptions, for intra-process delivery, and of local publisher gids, so
  a subscription drops the Zenoh copy of a sample it already got intra-process;
- the backends loaded once from the registry (a backend may hold per-process state such as an
  IPC manager, so every node of the process shares one instance of each);
- the nodes still open, closed when the interpreter exits (:func:`close_open_nodes`).
"""

from __future__ import annotations

import atexit
import collections
import functools
import itertools
import logging
import os
import threading
import weakref
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from rosidl_buffer import BufferBackend
from rosidl_buffer import registry

from . import _sessions
from .errors import NodeClosedError

if TYPE_CHECKING:
    from .node import Node
    from .subscription import Subscription

_log = logging.getLogger(__name__)
_exiting = False  # the exit's close_open_nodes ran: no new node (see add_node)
#: How long the exit waits for a daemon thread's node call, then for each session's close.
EXIT_WAIT_S = 3.0

_lock = threading.Lock()
_busy = 0  # Node() and Node.close() calls running now (see in_flight)
_idle = threading.Condition(_lock)
_ids = itertools.count(0)
#: The local subscriptions by domain-qualified base data key: a tuple per key, replaced (never
#: changed in place) under ``_lock``, so a publish reads it without the lock.
SUBSCRIPTIONS: dict[str, tuple[Subscription, ...]] = {}
_subscription_gids: set[bytes] = set()
#: The gids of this process's publishers (and of the last RETIRED_PUBLISHERS removed): a
#: subscription drops the Zenoh copy of a sample whose gid is here (one set lookup, no lock).
PUBLISHER_GIDS: set[bytes] = set()
#: How many removed local publishers' gids are still recognized (see remove_publisher).
RETIRED_PUBLISHERS = 4096
_retired: collections.deque[bytes] = collections.deque()
_backends: dict[str, BufferBackend] | None = None
#: The nodes of this process not closed yet (weakly: a node nobody references is not kept).
_open_nodes: weakref.WeakSet[Node] = weakref.WeakSet()


def next_id() -> int:
    with _lock:
        return next(_ids)


def default_backends() -> dict[str, BufferBackend]:
    """Every registered backend that loads (broken plugins are logged by the registry, skipped)."""
    global _backends
    with _lock:
        if _backends is None:
            _backends, _errors = registry.load_backends()
        return dict(_backends)


def add_subscription(key: str, subscription: Subscription) -> None:
    with _lock:
        SUBSCRIPTIONS[key] = (*SUBSCRIPTIONS.get(key, ()), subscription)
        _subscription_gids.add(subscription.gid)


def remove_subscription(key: str, subscription: Subscription) -> None:
    with _lock:
        subs = tuple(s for s in SUBSCRIPTIONS.get(key, ()) if s is not subscription)
        if subs:
            SUBSCRIPTIONS[key] = subs
        else:
            SUBSCRIPTIONS.pop(key, None)
        _subscription_gids.discard(subscription.gid)


def local_subscriptions(key: str) -> tuple[Subscription, ...]:
    """The local subscriptions of ``key`` now (a snapshot; ``SUBSCRIPTIONS.get`` is the same
    without a call, for the publish path)."""
    return SUBSCRIPTIONS.get(key, ())


def is_local_subscription(gid: bytes) -> bool:
    return gid in _subscription_gids  # one set lookup is atomic under the GIL: no lock


def add_publisher(gid: bytes) -> None:
    with _lock:
        PUBLISHER_GIDS.add(gid)


def remove_publisher(gid: bytes) -> None:
    """A local publisher is gone. Its gid stays known as local for the next
    :data:`RETIRED_PUBLISHERS` removals: Zenoh copies of its last samples may still be on their
    way to this process's subscriptions, which had them intra-process already."""
    with _lock:
        _retired.append(gid)
        if len(_retired) > RETIRED_PUBLISHERS:
            PUBLISHER_GIDS.discard(_retired.popleft())


def add_node(node: Node) -> None:
    """Count ``node`` open (closed at exit if nobody closes it). Refused once the exit began:
    a node opened after the exit's close would outlive it, its Zenoh threads calling into an
    interpreter that is finalizing (the process aborts)."""
    with _lock:
        check_not_exiting()
        _open_nodes.add(node)


def in_flight(method: Callable[..., Any]) -> Callable[..., Any]:
    """Count the calls of ``method`` (``Node.__init__``, ``Node.close``) while they run: the
    exit waits for them to leave Zenoh's code before it closes the sessions, since a daemon
    thread still inside it when the interpreter finalizes takes the process down."""

    @functools.wraps(method)
    def counted(*args: Any, **kwargs: Any) -> Any:
        global _busy
        with _lock:
            _busy += 1
        try:
            return method(*args, **kwargs)
        finally:
            with _lock:
                _busy -= 1
                if not _busy:
                    _idle.notify_all()

    return counted


def check_not_exiting() -> None:
    """Raise NodeClosedError once the interpreter's exit closed the nodes."""
    if _exiting:
        raise NodeClosedError("the interpreter is exiting: no new node")


def remove_node(node: Node) -> None:
    with _lock:
        _open_nodes.discard(node)


def close_open_nodes() -> None:
    """Close the nodes still open as the interpreter exits. Zenoh runs Python callbacks on
    non-daemon threads of its own, which end only with their session: a script that never
    closed its node (or died of an exception before it did) would otherwise never exit, where
    an rclpy script does. The application's own non-daemon threads are waited for first (they
    may still use the nodes: the interpreter would have waited for them too); a node another
    thread is closing is waited for (``Node.close`` returns once it is closed)."""
    global _exiting
    for thread in threading.enumerate():
        if not thread.daemon and thread is not threading.current_thread() \
                and thread is not threading.main_thread() and not _zenoh_thread(thread):
            thread.join()
    with _lock:
        _exiting = True  # a daemon thread's new node is refused from here
        nodes = list(_open_nodes)
    for node in nodes:
        try:
            node.close()
        except Exception:  # one node's failure must not keep the others (and the exit) waiting
            _log.exception("closing node %s at exit failed", node.name)
    with _lock:  # a daemon thread's node being made or closed now: let it finish (bounded)
        _idle.wait_for(lambda: _busy == 0, timeout=EXIT_WAIT_S)
    _sessions.close_all(timeout=EXIT_WAIT_S)  # and the sessions a daemon thread still holds


def _zenoh_thread(thread: threading.Thread) -> bool:
    """Is ``thread`` one zenoh-python started to run a session's Python callbacks? (Its target
    is a pyo3 closure: ``Thread-N (pyo3-closure)``; it ends when its session closes.)"""
    return thread.name.endswith("(pyo3-closure)")


try:
    # threading's exit hooks run before the interpreter joins non-daemon threads; atexit's run
    # after that join (too late). Private API, the one concurrent.futures uses (Python 3.9+).
    threading._register_atexit(close_open_nodes)  # type: ignore[attr-defined]
except (AttributeError, RuntimeError):  # no such hook, or imported while the interpreter exits
    # (nodes made then are closed by atexit, after the threads they would keep alive: hang)
    atexit.register(close_open_nodes)


def _after_fork_in_child() -> None:
    # The parent's nodes are not this process's: their sessions' threads did not fork with it.
    global _busy
    _open_nodes.clear()
    _busy = 0  # (the threads making those calls did not fork either)


os.register_at_fork(after_in_child=_after_fork_in_child)
