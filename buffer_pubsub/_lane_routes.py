"""The transport's side of the fast lane: which peers it serves, and its frame.

Small pure pieces the publisher, subscription and node call:

- :func:`serves`: the route decision for one matched subscription;
- :func:`open_writer` / :func:`open_reader`: a lane for a route, or None (Zenoh carries it);
- a lane message is the attachment (as Zenoh carries it beside the payload) then the CDR
  payload, ``writer.write(attachment, payload)``, so lane and Zenoh deliveries enter one
  receive path (:func:`.wire.split_frame` takes it apart).

A lane leaves nothing behind when a peer dies (the kernel reclaims its memfds, sockets and
eventfds): there is nothing to clean up on loss.
"""

from __future__ import annotations

import logging
import os
import resource

from . import fast_lane, wire

__all__ = ["fd_headroom", "open_reader", "open_writer", "queue_depth",
           "serves"]

_log = logging.getLogger(__name__)


def serves(local: wire.Locality, peer: wire.EndpointToken, *, individual: bool, served: bool,
           keep_all: bool = False) -> bool:
    """Whether the lane should carry a publisher's messages to the subscription ``peer``.

    Only subscriptions of ours with a channel of their own (``individual``: they accept a
    backend besides CPU) that a backend agreed to serve (``served``), on this host, as this
    user, in another process (same-process subscriptions are served in-process), keep-last
    (``keep_all`` peers stay on Zenoh, whose BLOCK congestion control bounds a stall; the
    lane's ring overwrites the oldest frame instead).
    """
    theirs = peer.locality  # None: not one of ours, so it has no lane
    return (individual and served and not keep_all and theirs is not None
            and theirs.host_id == local.host_id and theirs.user_id == local.user_id
            and theirs.process_id != local.process_id)


def queue_depth(peer: wire.EndpointToken) -> int:
    """How many frames the lane to subscription ``peer`` holds before it overwrites the oldest:
    its keep-last depth (the reader keeps as many, see :meth:`Subscription.__init__`), at most
    :data:`fast_lane.MAX_DEPTH`."""
    return min(max(1, peer.qos.depth), fast_lane.MAX_DEPTH)


#: File descriptors one lane end costs: a reader's listening socket, a writer's connection and
#: doorbell (and the reader's copies of them), and the memfd while it is handed over.
LANE_FDS = 4
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


def open_writer(base_key: str, subscriber_gid: bytes,
                depth: int = fast_lane.DEFAULT_DEPTH) -> fast_lane.LaneWriter | None:
    """The lane to ``subscriber_gid``'s reader (a ring of ``depth`` frames: its keep-last depth,
    :func:`queue_depth`), or None when it has none (lane off there, an older peer, another
    user) or this process is short of file descriptors: the Zenoh channel serves it then."""
    if not _room_for_a_lane(f"subscription {subscriber_gid.hex()}"):
        return None
    try:
        return fast_lane.LaneWriter(fast_lane.service_name(base_key, subscriber_gid),
                                    depth=depth)
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
