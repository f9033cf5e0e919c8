"""Peer: raw Zenoh ``put`` of the payload bytes, shared memory disabled (the copy path).

The sender's data lives in a bytearray; ``put`` copies it into Zenoh, TCP carries it, and the
subscriber's ``payload.to_bytes()`` copies it out into Python (ZBytes has no buffer protocol).
"""

from __future__ import annotations

from typing import Any

from benchmarks.paths import PathSettings
from benchmarks.paths.zenoh_common import ZenohReceiver, declare_blocking_publisher, open_session
from benchmarks.protocol import STAMP_SIZE, stamp_into

LABEL = "Zenoh put (copy)"
KIND = "peer"
TOPOLOGY = "pair"


class ZenohCopySender:
    """Puts a bytearray the size of the payload."""

    def __init__(self, settings: PathSettings) -> None:
        self._session = open_session(settings, listen=False, shared_memory=False)
        self._publisher = declare_blocking_publisher(self._session, settings)
        self._data = bytearray(STAMP_SIZE)

    def prepare(self, nbytes: int) -> None:
        """The user's data: a bytearray of ``nbytes``."""
        self._data = bytearray(nbytes)

    def send(self, seq: int) -> None:
        """Stamp and put (Zenoh copies the bytes)."""
        stamp_into(self._data, seq)
        self._publisher.put(self._data)

    def close(self) -> None:
        """Undeclare and close."""
        self._publisher.undeclare()
        self._session.close()


def make_sender(settings: PathSettings, shared: Any) -> ZenohCopySender:
    """The publishing side."""
    return ZenohCopySender(settings)


def make_receiver(settings: PathSettings, shared: Any) -> ZenohReceiver:
    """The subscribing side: copies each payload out with ``to_bytes()``."""
    return ZenohReceiver(settings, shared_memory=False, read=lambda s: s.payload.to_bytes())
