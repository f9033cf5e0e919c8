"""Open a node's Zenoh session and say so, on stderr through :mod:`logging`, when the routers or
peers its configuration names cannot be reached.

Zenoh itself is silent about that: a peer keeps retrying in the background and a client waits
for its router inside ``zenoh.open``. A node therefore warns after :data:`WARN_AFTER_S` seconds
(while a client is still waiting, or once a peer is open but linked to none of its configured
endpoints), and a client that reaches no router within its connect timeout raises
:class:`~buffer_pubsub.errors.TransportConfigError` naming the endpoints.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import threading
from collections.abc import Callable

import zenoh

from . import _zenoh
from .config import LOCAL_ROUTER, make_config, zenoh_error_text
from .errors import ForkedAfterZenohError, TransportConfigError

__all__ = ["WARN_AFTER_S", "open_session", "out_of_fds_hint"]

_log = logging.getLogger("buffer_pubsub")

#: Seconds after which an unreachable router or peer is reported.
WARN_AFTER_S = 3.0
_HINT = "is a router running there? start one with `warp-buffer router`"
_LOCAL_HINT = "check the Zenoh configuration (listen and connect endpoints)"
_FD_HINT = ("the process is out of file descriptors: raise `ulimit -n`, or share one Node "
            "between publishers and subscriptions instead of a Node each (each holds a Zenoh "
            "session)")


def out_of_fds_hint(text: str) -> str | None:
    """The remedy when ``text`` (an error's) says the process ran out of file descriptors (a
    Zenoh session, a node's eventfd), else None."""
    return _FD_HINT if os.strerror(errno.EMFILE) in text else None  # (ENFILE's says it too)


def _get(config: zenoh.Config, key: str) -> object:
    try:
        return json.loads(config.get_json(key))
    except (zenoh.ZError, ValueError):
        return None


def open_session(config: zenoh.Config | str | os.PathLike[str] | None = None,
                 router: str | None = None) -> zenoh.Session:
    """``zenoh.open`` of :func:`~buffer_pubsub.config.make_config`'s result, with the warnings
    and errors described in the module docstring."""
    if _zenoh.inherited():
        raise ForkedAfterZenohError(
            f"this process (pid {os.getpid()}) was forked from one that had opened a Zenoh "
            "session, and Zenoh cannot start in it (its runtime's threads are not forked; a "
            "session would hang): create fork workers before the first Node, or use the "
            "'spawn' or 'forkserver' start method of multiprocessing")
    zconfig = make_config(config, router)
    endpoints = _get(zconfig, "connect/endpoints")
    endpoints = [str(e) for e in endpoints] if isinstance(endpoints, list) else []
    client = _get(zconfig, "mode") == "client"
    opened = threading.Event()
    if endpoints and client:
        _after(WARN_AFTER_S, opened, lambda: _log.warning(
            "still waiting for Zenoh router %s after %.0f s (%s)",
            ", ".join(endpoints), WARN_AFTER_S, _HINT))
    _zenoh.mark_opened()  # from here a fork's child cannot start Zenoh
    try:
        session = zenoh.open(zconfig)
    except zenoh.ZError as exc:
        where = f"Zenoh router {', '.join(endpoints)}" if endpoints else "Zenoh"
        text = zenoh_error_text(exc)
        hint = out_of_fds_hint(text) or (_HINT if endpoints else _LOCAL_HINT)
        raise TransportConfigError(f"cannot connect to {where}: {text} ({hint})") from exc
    finally:
        opened.set()
    if not client and _get(zconfig, "scouting/multicast/enabled") is True:
        # A peer that scouts needs no router: this host's (rmw_zenoh's default) when one runs.
        endpoints = [e for e in endpoints if e != LOCAL_ROUTER]
    if endpoints and not client:
        _after(WARN_AFTER_S, threading.Event(), lambda: _warn_if_alone(session, endpoints))
    return session


def _after(delay: float, cancel: threading.Event, action: Callable[[], None]) -> None:
    def run() -> None:
        if not cancel.wait(delay):
            action()

    threading.Thread(target=run, name="buffer_pubsub:connectivity", daemon=True).start()


def _warn_if_alone(session: zenoh.Session, endpoints: list[str]) -> None:
    try:
        if session.is_closed():  # a closed session lists no links: nothing to report
            return
        linked = any(True for _ in session.info.routers_zid()) or any(
            True for _ in session.info.peers_zid())
    except zenoh.ZError:  # closed meanwhile
        return
    if not linked:
        _log.warning("none of the configured Zenoh endpoints %s answered within %.0f s; the "
                     "node keeps retrying (%s)", ", ".join(endpoints), WARN_AFTER_S, _HINT)
