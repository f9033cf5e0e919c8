"""The transport's side of the fast lane: which peers it serves, its frame, clean-up on loss.

Small pure pieces the publisher, subscription and node call (see /tmp/notes/issue15.md for where):

- :func:`serves`: the route decision for one matched subscription;
- :func:`open_writer` / :func:`open_reader`: a lane for a route, or None (Zenoh carries it);
- :func:`split_frame`: a lane message is the attachment (as Zenoh carries it beside the
  payload) then the CDR payload, ``writer.write(attachment, payload)``, so lane and Zenoh
  deliveries enter one receive path;
- :class:`DeadPeerSweeper`: iceoryx2's dead-node clean-up when discovery says a same-host peer
  of another process is gone (Zenoh's liveliness DELETE arrives at once, SIGKILL included).
"""

from __future__ import annotations

import logging
import os
import resource
import threading
import time

from . import fast_lane, wire

__all__ = ["DeadPeerSweeper", "fd_headroom", "open_reader", "open_writer", "queue_depth",
           "serves", "split_frame"]

_log = logging.getLogger(__name__)


def serves(local: wire.Locality, peer: wire.EndpointToken, *, individual: bool, served: bool,
           keep_all: bool = False) -> bool:
    """Whether the lane should carry a publisher's messages to the subscription ``peer``.

    Only subscriptions of ours with a channel of their own (``individual``: they accept a
    backend besides CPU) that a backend agreed to serve (``served``), on this host, as this
    user, in another process (same-process subscriptions are served in-process), keep-last
    (``keep_all`` peers stay on Zenoh, whose BLOCK congestion control bounds a stall; iceoryx2's
    retry would block ``publish()`` without bound).
    """
    theirs = peer.locality  # None: not one of ours, so it has no lane
    return (individual and served and not keep_all and theirs is not None
            and theirs.host_id == local.host_id and theirs.user_id == local.user_id
            and theirs.process_id != local.process_id)


def queue_depth(peer: wire.EndpointToken) -> int:
    """How many frames the lane to subscription ``peer`` holds before it overwrites the oldest:
    the reader made its iceoryx2 queue as deep as its keep-last depth (see
    :meth:`Subscription.__init__`, at most :data:`fast_lane.MAX_DEPTH`)."""
    return min(max(1, peer.qos.depth), fast_lane.MAX_DEPTH)


#: File descriptors one lane end costs (iceoryx2's node, service and port files, ~8-10).
LANE_FDS = 12
#: Descriptors left free for what cannot do without them (an import's hand-off socket and the
#: arena it receives, Zenoh's connections): the lane is an optimization and gives way first.
FD_RESERVE = 64


def fd_headroom() -> int | None:
    """How many more descriptors this process may open (None: no limit)."""
    soft, _hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY:
        return None
    try:
        in_use = len(os.listdir("/proc/self/fd"))
    except OSError:  # no /proc, or no descriptor even for the listing
        return 0
    return soft - in_use


def _room_for_a_lane(what: str) -> bool:
    headroom = fd_headroom()
    if headroom is None or headroom >= LANE_FDS + FD_RESERVE:
        return True
    _log.info("no fast lane for %s: %d file descriptors left (RLIMIT_NOFILE); Zenoh carries it",
              what, headroom)
    return False


def open_writer(base_key: str, subscriber_gid: bytes) -> fast_lane.LaneWriter | None:
    """The lane to ``subscriber_gid``'s reader, or None when it has none (lane off there, an
    older peer, another lane domain) or this process is short of file descriptors: the Zenoh
    channel serves it then."""
    if not _room_for_a_lane(f"subscription {subscriber_gid.hex()}"):
        return None
    try:
        return fast_lane.LaneWriter(fast_lane.service_name(base_key, subscriber_gid))
    except fast_lane.LaneUnavailableError as error:
        _log.debug("no lane to %s: %s", subscriber_gid.hex(), error)
        return None


def open_reader(base_key: str, gid: bytes, depth: int) -> fast_lane.LaneReader | None:
    """A reader for this subscription's route, or None (the reason is logged)."""
    if not _room_for_a_lane(f"subscription {gid.hex()}"):
        return None
    try:
        return fast_lane.LaneReader(fast_lane.service_name(base_key, gid), depth=depth)
    except fast_lane.LaneUnavailableError as error:
        _log.info("fast lane off for %s: %s", gid.hex(), error)
        return None


def split_frame(data: bytes) -> tuple[wire.Attachment, memoryview]:
    """The attachment and the CDR payload of a lane message.

    Raises:
        WireFormatError: shorter than an attachment, or a malformed one.
    """
    head = data[:wire.ATTACHMENT_SIZE]
    return wire.Attachment.decode(head), memoryview(data)[wire.ATTACHMENT_SIZE:]


class DeadPeerSweeper:
    """Runs iceoryx2's dead-node clean-up when a same-host peer of another process vanished,
    at most once per ``interval_s`` (a burst of DELETEs from one dead process cleans once), and
    once more ``settle_s`` later: Zenoh may report the death before the kernel has released
    the dead process's locks, which is how iceoryx2 tells a dead node from a live one."""

    def __init__(self, local: wire.Locality, interval_s: float = 0.1,
                 settle_s: float = 0.5) -> None:
        self._local = local
        self._interval_s = interval_s
        self._settle_s = max(settle_s, interval_s)
        self._lock = threading.Lock()
        self._last = 0.0
        self._timer: threading.Timer | None = None
        self.sweeps = 0

    def peer_gone(self, token: wire.EndpointToken) -> None:
        """Discovery saw ``token`` vanish (call it from the liveliness DELETE handler)."""
        theirs = token.locality
        if (theirs is None or theirs.host_id != self._local.host_id
                or theirs.process_id == self._local.process_id):
            return
        with self._lock:
            now = time.monotonic()
            run_now = now - self._last >= self._interval_s
            if run_now:
                self._last = now
            if self._timer is None:  # the follow-up sweep, one per burst
                self._timer = threading.Timer(self._settle_s, self._sweep_later)
                self._timer.daemon = True
                self._timer.start()
        if run_now:
            self._sweep()

    def close(self) -> None:
        """Cancel a pending sweep."""
        with self._lock:
            timer, self._timer = self._timer, None
        if timer is not None:
            timer.cancel()

    def _sweep_later(self) -> None:
        with self._lock:
            self._timer = None
            self._last = time.monotonic()
        self._sweep()

    def _sweep(self) -> None:
        self.sweeps += 1
        fast_lane.cleanup_dead_nodes()
