"""Zenoh sessions for the peer benchmarks: two peers on loopback, isolated from other sessions.

Multicast scouting is off and the receiver listens on a port of its own that the sender connects
to, so concurrent Zenoh users on this host never join (and never share memory with) our run.
"""

from __future__ import annotations

import json
from typing import Any, Callable

from benchmarks.paths import PathSettings, PathUnavailable


def make_config(settings: PathSettings, listen: bool, shared_memory: bool | None) -> Any:
    """Peer config: the receiver (``listen``) listens on ``settings.port``, the sender connects
    to it; ``shared_memory`` None leaves Zenoh's default (SHM on, with its transport
    optimization for payloads over 3 KiB)."""
    try:
        import zenoh
    except ImportError as error:
        raise PathUnavailable(f"eclipse-zenoh not installed ({error})") from error
    config = zenoh.Config()
    endpoint = json.dumps([f"tcp/127.0.0.1:{settings.port}"])
    config.insert_json5("mode", '"peer"')
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("listen/endpoints", endpoint if listen else "[]")
    config.insert_json5("connect/endpoints", "[]" if listen else endpoint)
    if shared_memory is not None:
        config.insert_json5("transport/shared_memory/enabled", json.dumps(shared_memory))
    return config


def our_node_config(settings: PathSettings, listen: bool) -> Any:
    """:func:`make_config` (SHM off) with the transport settings of buffer_pubsub's embedded
    default that shape delivery (the fragments' deadline of keep-last messages), so our nodes
    run here as they do out of the box."""
    from buffer_pubsub.config import DROP_FRAGMENTS_WAIT_US

    config = make_config(settings, listen, shared_memory=False)
    config.insert_json5("transport/link/tx/queue/congestion_control/drop/"
                        "max_wait_before_drop_fragments", str(DROP_FRAGMENTS_WAIT_US))
    return config


def open_session(settings: PathSettings, listen: bool, shared_memory: bool | None) -> Any:
    """A peer session configured by :func:`make_config`."""
    import zenoh

    return zenoh.open(make_config(settings, listen, shared_memory))


def key(settings: PathSettings) -> str:
    """The key expression of this run."""
    return f"warp_buffer_bench/{settings.run_id}/{settings.name}"


def declare_blocking_publisher(session: Any, settings: PathSettings) -> Any:
    """A publisher that blocks rather than drops when Zenoh's queues are full: with the default
    (drop), messages of tens of MiB are lost, which no user moving tensors can accept."""
    import zenoh

    return session.declare_publisher(key(settings),
                                      congestion_control=zenoh.CongestionControl.BLOCK)


class ZenohReceiver:
    """Subscribes with a callback; ``read(sample)`` makes the payload usable and returns it."""

    polls = False

    def __init__(self, settings: PathSettings, shared_memory: bool,
                 read: Callable[[Any], bytes | memoryview]) -> None:
        self._session = open_session(settings, listen=True, shared_memory=shared_memory)
        self._deliver: Callable[[bytes | memoryview], None] | None = None
        self._read = read
        self._subscriber = self._session.declare_subscriber(key(settings), self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        if self._deliver is not None:
            self._deliver(self._read(sample))

    def prepare(self, nbytes: int, deliver: Callable[[bytes | memoryview], None]) -> None:
        """Payloads of any size arrive on the same key; just (re)bind the callback."""
        self._deliver = deliver

    def poll(self) -> bool:
        """Not a polling receiver."""
        return False

    def close(self) -> None:
        """Undeclare and close the session."""
        self._subscriber.undeclare()
        self._session.close()
