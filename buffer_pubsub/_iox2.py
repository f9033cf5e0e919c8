"""iceoryx2 access for the fast lane: import, our resource prefix, one node per process, and
iceoryx2's dead-node cleanup.

Every iceoryx2 resource the lane creates (``/dev/shm`` segments, files under iceoryx2's root
path ``/tmp/iceoryx2/``) carries the prefix :func:`resource_prefix`, which is iceoryx2's own
notion of a *domain* (its ``global.prefix``): programs that use iceoryx2 with its default
``iox2_`` prefix never see our services and we never see theirs, and a leak check can tell our
files from everyone else's by name alone.

iceoryx2 removes a node's resources when the node is dropped (clean exit, :func:`close_node`,
the ``atexit`` hook); resources of a process that died (SIGKILL, SIGTERM without a handler, a
crash) stay until some process runs :func:`cleanup_dead_nodes`, which the lane does whenever it
starts in a process and whenever the transport learns that a peer is gone.
"""

from __future__ import annotations

import atexit
import logging
import os
import re
import threading
import weakref
from types import ModuleType
from typing import Any

__all__ = ["ENV_DOMAIN", "LaneStartError", "cleanup_dead_nodes", "close_node", "config",
           "load", "process_node", "resource_prefix", "track"]

_log = logging.getLogger(__name__)

#: Environment variable naming the lane's iceoryx2 domain; processes talk over the lane only
#: within one domain (default: ``u<uid>``, one per user: the lane serves processes of one user
#: only, and another user's files would not open). The test suite gives each run its own.
ENV_DOMAIN = "WARP_BUFFER_FAST_LANE_DOMAIN"
DEFAULT_DOMAIN = f"u{os.getuid()}"
_SHM = "/dev/shm"
PREFIX = "warp_lane_"
_DOMAIN = re.compile(r"^[A-Za-z0-9]{1,32}$")

_lock = threading.Lock()
_node: Any = None
_node_pid = 0  # the process that created _node: a forked child must not use its parent's node
# Lane objects holding ports, by the process that made them (see track): (early, others).
_owners: dict[int, tuple[weakref.WeakSet[Any], weakref.WeakSet[Any]]] = {}
_inherited: list[Any] = []  # nodes a forked child inherited (never dropped there)


class LaneStartError(RuntimeError):
    """iceoryx2 is missing or cannot start here; the message says why."""


def load() -> ModuleType:
    """The ``iceoryx2`` module, its logging quietened to errors.

    Raises:
        LaneStartError: iceoryx2 is not installed or does not import.
    """
    try:
        import iceoryx2
    except ImportError as error:
        raise LaneStartError(f"iceoryx2 is not installed ({error}); "
                             f"pip install 'iceoryx2==0.10.*'") from None
    iceoryx2.set_log_level_from_env_or(iceoryx2.LogLevel.Error)
    return iceoryx2


def domain() -> str:
    """The lane's iceoryx2 domain from :data:`ENV_DOMAIN`.

    Raises:
        LaneStartError: the variable is not 1-32 letters or digits.
    """
    value = os.environ.get(ENV_DOMAIN, "") or DEFAULT_DOMAIN
    if not _DOMAIN.match(value):
        raise LaneStartError(f"{ENV_DOMAIN}={value!r}: use 1-32 letters or digits")
    return value


def resource_prefix(domain_name: str | None = None) -> str:
    """The prefix of every iceoryx2 file the lane creates in ``domain_name`` (default: ours)."""
    return f"{PREFIX}{domain() if domain_name is None else domain_name}_"


def config() -> Any:
    """An iceoryx2 config: the global one with our resource prefix."""
    iox2 = load()
    cfg = iox2.config.global_config()
    cfg.global_cfg.prefix = iox2.FileName.new(resource_prefix())
    return cfg


def process_node() -> Any:
    """This process's iceoryx2 node, created on first use (dead nodes are cleaned up first).

    Signal handling stays with the application: iceoryx2 would otherwise swallow SIGINT
    (no ``KeyboardInterrupt``) while a wait runs.

    Raises:
        LaneStartError: iceoryx2 is missing or the node cannot be created.
    """
    global _node, _node_pid
    with _lock:
        pid = os.getpid()
        if _node is not None and _node_pid == pid:
            return _node
        if _node is not None:  # a forked child: dropping the parent's node here would remove
            _inherited.append(_node)  # it from under the parent, so it is kept, unused
        iox2 = load()
        _cleanup_locked(iox2)
        try:
            _node = (iox2.NodeBuilder.new().config(config())
                     .name(iox2.NodeName.new(f"warp_buffer.{pid}"))
                     .signal_handling_mode(iox2.SignalHandlingMode.Disabled)
                     .create(iox2.ServiceType.Ipc))
        except Exception as error:  # NodeCreationFailure and friends: iceoryx2 cannot run here
            raise LaneStartError(f"iceoryx2 node creation failed: "
                                 f"{type(error).__name__}: {error}") from None
        if _node_pid == 0:
            atexit.register(close_node)
        _node_pid = pid
        _make_private(resource_prefix())
        return _node


def _make_private(prefix: str) -> None:
    """Owner-only modes for the domain's files iceoryx2 creates readable by all (its per-domain
    ``global_mgmt`` segment, 0666): nothing of ours in /dev/shm is open to other users."""
    try:
        names = [n for n in os.listdir(_SHM) if n.startswith(prefix)]
    except OSError:
        return
    uid = os.getuid()
    for name in names:
        try:  # through an fd opened without following links: the file itself, nothing else
            fd = os.open(os.path.join(_SHM, name), os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
        except OSError:  # removed meanwhile, a link, or not ours to open
            continue
        try:
            info = os.fstat(fd)
            if info.st_uid == uid and info.st_mode & 0o077:
                os.fchmod(fd, info.st_mode & 0o700)
        except OSError:
            pass
        finally:
            os.close(fd)


def track(owner: Any, early: bool = False) -> None:
    """Close ``owner`` (an object with ``close()`` holding iceoryx2 ports) at exit at the latest:
    objects still alive when the interpreter shuts down are not reliably dropped, and a port
    that outlives the process keeps its node's files in place. ``early`` owners (wakers, whose
    WaitSets watch the ports of others) close first."""
    with _lock:
        sets = _owners.setdefault(os.getpid(), (weakref.WeakSet(), weakref.WeakSet()))
    sets[0 if early else 1].add(owner)


def close_node() -> None:
    """Close every tracked owner, then drop this process's node: iceoryx2 removes its files.

    Only what this process made: in a forked child, the node and ports it inherited are its
    parent's, and deleting them would remove them from under the parent."""
    global _node
    if _node_pid != os.getpid():
        return
    early, others = _owners.get(os.getpid(), ((), ()))
    for owner in [*early, *others]:
        try:
            owner.close()
        except Exception:  # exit path: close what can be closed
            _log.debug("closing %r at exit failed", owner, exc_info=True)
    with _lock:
        node, _node = _node, None
    del node  # the last reference: iceoryx2 removes the node's files when it is dropped


def cleanup_dead_nodes() -> int:
    """Remove the iceoryx2 resources of every dead node of our domain; how many were removed.

    Cheap (about 30 us with nothing to do, 1-2 ms per dead node): call it when a peer is
    known to be gone. Never raises: a failure is logged.
    """
    try:
        iox2 = load()
    except LaneStartError:
        return 0
    with _lock:
        return _cleanup_locked(iox2)


def _cleanup_locked(iox2: ModuleType) -> int:
    removed = 0
    try:
        states = iox2.Node.list(iox2.ServiceType.Ipc, config())
    except Exception as error:  # NodeListFailure: nothing we can clean now
        _log.debug("iceoryx2 node list failed: %s", error)
        return 0
    for state in states:
        if not isinstance(state, iox2.NodeState.Dead):
            continue
        try:
            state[0].try_remove_stale_resources()
            removed += 1
        except Exception as error:  # NodeCleanupFailure: another process may be cleaning it
            _log.debug("iceoryx2 dead-node cleanup failed: %s", error)
    if removed:
        _log.debug("removed the resources of %d dead iceoryx2 node(s)", removed)
    return removed
