"""One Zenoh session per process and configuration, shared by the nodes that use it.

rmw_zenoh opens one session per context, whatever the number of nodes in it; its nodes are told
apart by their node id, not their session. A session is the expensive part of a node (its
runtime's threads, a socket per peer it links to, about half a second to open), so nodes made
with the same resolved configuration share one: its first user opens it, its last one closes it.
A fork's child starts with none (Zenoh sessions do not survive a fork; see
:mod:`buffer_pubsub.connectivity`).
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass, field

import zenoh

from ._zenoh import inherited, run_bounded
from .connectivity import open_session

__all__ = ["SharedSession", "acquire", "close_all", "release"]


@dataclass(eq=False)
class SharedSession:
    """A session and the number of nodes using it (the registry's lock guards ``users``)."""

    key: str
    session: zenoh.Session | None = None
    users: int = 0
    opening: threading.Lock = field(default_factory=threading.Lock)  # one open per key
    failures: int = 0  # opens that failed (under ``opening``)
    error: BaseException | None = None  # what the last one raised


_lock = threading.Lock()
_shared: dict[str, SharedSession] = {}


def acquire(config: zenoh.Config) -> SharedSession:
    """The session of ``config`` (a resolved configuration), opened by its first user.

    Raises what :func:`~buffer_pubsub.connectivity.open_session` raises; the nodes that waited
    for that open raise the same error at once. A failed open leaves nothing behind once those
    nodes are gone, and the next node tries again."""
    key = str(config)  # its complete JSON: nodes configured alike share
    with _lock:
        entry = _shared.get(key)
        if entry is None:
            entry = _shared[key] = SharedSession(key)
        entry.users += 1
    failures = entry.failures  # an open that fails from now on is one this node waits for
    try:
        with entry.opening:  # nodes of another configuration do not wait for this one
            if entry.session is None:
                if entry.failures > failures and entry.error is not None:
                    # the open this node waited for failed: fail alike, not one after another
                    raise entry.error.with_traceback(None)
                try:
                    entry.session = open_session(config)
                except BaseException as error:
                    entry.error = error
                    entry.failures += 1
                    raise
    except BaseException:
        _drop(entry)
        raise
    return entry


def release(entry: SharedSession, timeout: float) -> None:
    """One user less; the last one closes the session (bounded by ``timeout`` seconds)."""
    if _drop(entry):
        _close(entry, timeout)


def close_all(timeout: float) -> None:
    """At the interpreter's exit, once its nodes are closed: close every session still open,
    whoever still holds it (a daemon thread's node made meanwhile). A session left open keeps
    Zenoh threads that call into the interpreter while it finalizes, and the process aborts.
    A node still using one sees Zenoh errors from then on."""
    with _lock:
        entries = list(_shared.values())
        _shared.clear()
    for entry in entries:
        _close(entry, timeout)


def _close(entry: SharedSession, timeout: float) -> None:
    """Close ``entry``'s session if it opened and is not closed yet (bounded: Zenoh can block
    on a frozen peer). A fork's child leaves its parent's alone (see ``_zenoh.inherited``)."""
    session = entry.session
    if session is not None and not inherited() and not session.is_closed():
        run_bounded(session.close, timeout, "closing the Zenoh session")


def _drop(entry: SharedSession) -> bool:
    """Count a user out; True when it was the last (the entry leaves the registry)."""
    with _lock:
        entry.users -= 1
        if entry.users > 0:
            return False
        if _shared.get(entry.key) is entry:
            del _shared[entry.key]
        return True


def _forget_in_child() -> None:
    # The parent's sessions are not the child's (their threads were not forked): its nodes
    # must not find them.
    global _lock
    _lock = threading.Lock()
    _shared.clear()


os.register_at_fork(after_in_child=_forget_in_child)
