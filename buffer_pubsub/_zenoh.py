"""Small helpers over the Zenoh API shared by nodes, publishers and subscriptions."""

from __future__ import annotations

import atexit
import contextlib
import logging
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import zenoh

from .errors import TransportError

_log = logging.getLogger(__name__)

_opened = False  # this process opened a Zenoh session
_inherited = False  # the process this one was forked from had (see inherited())


def mark_opened() -> None:
    """A Zenoh session is being opened here: a fork's child from now on inherits it."""
    global _opened
    _opened = True


def inherited() -> bool:
    """Is this a fork's child of a process that had opened Zenoh? Then every Zenoh object here
    is the parent's, and its runtime's threads did not fork: a session cannot open, and a call
    into an inherited one (an undeclare, a close) would wait for them forever. Teardown leaves
    those objects alone; the parent's peers see nothing of the child."""
    return _inherited


def undeclare_quietly(*entities: Any) -> None:
    """Undeclare Zenoh entities (publishers, subscribers, tokens), ignoring ones already gone:
    teardown runs on close, on destroy and on peer loss, in any order. None is skipped; so is
    everything in a fork's child (see :func:`inherited`)."""
    if _inherited:
        return
    for entity in entities:
        if entity is None:
            continue
        try:
            entity.undeclare()
        except zenoh.ZError:
            pass
        except RuntimeError as exc:  # zenoh-python's "Already borrowed": in use on another thread
            _log.debug("undeclaring %r: %s", entity, exc)


@contextlib.contextmanager
def typed_zenoh_errors(what: str) -> Iterator[None]:
    """Re-raise ``zenoh.ZError`` as :class:`TransportError` (a library raises its own types)."""
    try:
        yield
    except zenoh.ZError as exc:
        raise TransportError(f"{what}: {exc}") from exc


#: How long the interpreter's exit waits for teardown helpers still inside Zenoh (see
#: :func:`run_bounded`): one that returns into Python while the interpreter finalizes aborts
#: the process ("FATAL: exception not rethrown"): a frozen peer that resumes as the program
#: exits, or a session close that a starved machine slowed past the close's own bound (seen at
#: a load of 12 on 2 cores). Past this the process exits anyway: a call still blocked then
#: waits on a peer frozen for longer, and is unlikely to return in finalization's moment.
EXIT_WAIT_S = 10.0
#: The same after the program ended on Ctrl-C (an uncaught KeyboardInterrupt): out promptly.
#: A Ctrl-C during the longer wait also ends it.
INTERRUPTED_EXIT_WAIT_S = 1.0
_background: set[threading.Event] = set()  # the done flags of helpers still running
_background_lock = threading.Lock()


def _await_background() -> None:
    with _background_lock:
        running = [done for done in _background if not done.is_set()]
    if not running:
        return
    # An uncaught Ctrl-C leaves its type here before the exit (an interactive session, which
    # keeps it from an earlier prompt, is never that exit: ps1 is set there)
    interrupted = (getattr(sys, "last_type", None) is KeyboardInterrupt
                   and not hasattr(sys, "ps1"))
    wait_s = INTERRUPTED_EXIT_WAIT_S if interrupted else EXIT_WAIT_S
    if not interrupted:
        _log.warning("waiting up to %.0f s for %d Zenoh teardown call(s) before exiting (a "
                     "frozen peer, or a busy machine; Ctrl-C ends the wait)", wait_s,
                     len(running))
    deadline = time.monotonic() + wait_s
    try:
        for done in running:
            done.wait(max(0.0, deadline - time.monotonic()))
    except KeyboardInterrupt:
        pass  # the user wants out now
    blocked = sum(not done.is_set() for done in running)
    if blocked:
        _log.warning("exiting with %d Zenoh teardown call(s) still blocked (a frozen peer?)",
                     blocked)


atexit.register(_await_background)


def _after_fork_in_child() -> None:
    # The parent's helpers are not running here: nothing for this process's exit to wait for.
    global _background_lock, _inherited
    _inherited = _inherited or _opened
    _background.clear()
    _background_lock = threading.Lock()


os.register_at_fork(after_in_child=_after_fork_in_child)


def run_bounded(work: Callable[[], None], timeout: float, what: str) -> bool:
    """Run ``work`` on a helper thread and wait at most ``timeout`` seconds for it.

    Teardown calls into Zenoh can block on a frozen peer (a full transmit queue waits for the
    link to close); the caller goes on after ``timeout`` and the helper finishes in the
    background. Errors of ``work`` are logged, never raised: teardown must not replace an
    exception already on its way out. True when ``work`` finished in time.
    """
    done = threading.Event()  # not Thread.join: an interrupted join may report it finished
    with _background_lock:
        _background.add(done)

    def run() -> None:
        try:
            work()
        except Exception as exc:  # logged: nobody is left to handle it
            _log.warning("%s failed: %s", what, exc)
        finally:
            done.set()
            with _background_lock:
                _background.discard(done)

    thread = threading.Thread(target=run, name=f"buffer_pubsub:{what}", daemon=True)
    thread.start()
    deadline = time.monotonic() + timeout
    interrupted: BaseException | None = None
    while not done.is_set():  # Ctrl-C waits for the bounded teardown, then goes on its way:
        left = deadline - time.monotonic()  # an interpreter exiting while the helper is still
        if left <= 0:  # inside Zenoh aborted the process (a second Ctrl-C here did)
            break
        try:
            done.wait(left)
        except KeyboardInterrupt as exc:
            interrupted = exc
    if interrupted is not None:
        raise interrupted
    if not done.is_set():
        _log.warning("%s did not finish within %.1f s; left to finish in the background",
                     what, timeout)
        return False
    return True
