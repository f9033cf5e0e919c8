"""Peer: Zenoh's shared-memory transport through its SHM API (``zenoh.shm.ShmProvider``).

The sender allocates each payload from a ShmProvider and fills it; Python's ``ZShmMut`` offers
only item assignment from bytes, so the user's data is copied in. Zenoh passes the SHM chunk by
reference; the subscriber gets a ``ZShm`` without buffer protocol, so ``bytes(zshm)`` copies it
out. Both copies are inherent to Zenoh's Python API today.
"""

from __future__ import annotations

from typing import Any

from benchmarks.paths import PathSettings, PathUnavailable
from benchmarks.paths.zenoh_common import ZenohReceiver, declare_blocking_publisher, open_session
from benchmarks.protocol import STAMP_SIZE, stamp_into

LABEL = "Zenoh SHM"
KIND = "peer"
TOPOLOGY = "pair"
POOL_SLOTS = 3  # payloads of the largest size the provider holds at once


class ZenohShmSender:
    """Allocates every payload from a shared-memory provider."""

    def __init__(self, settings: PathSettings) -> None:
        import zenoh

        self._zenoh = zenoh
        self._session = open_session(settings, listen=False, shared_memory=True)
        self._publisher = declare_blocking_publisher(self._session, settings)
        try:
            self._provider = zenoh.shm.ShmProvider.default_backend(
                POOL_SLOTS * max(settings.max_nbytes, 1 << 20))
        except Exception as error:
            raise PathUnavailable(f"no Zenoh SHM provider: {error}") from error
        self._policy = zenoh.shm.BlockOn(zenoh.shm.GarbageCollect())
        self._data = bytearray(STAMP_SIZE)

    def prepare(self, nbytes: int) -> None:
        """The user's data: a bytearray of ``nbytes``."""
        self._data = bytearray(nbytes)

    def send(self, seq: int) -> None:
        """Stamp, allocate a chunk, copy the data in, put the chunk."""
        stamp_into(self._data, seq)
        chunk = self._provider.alloc(len(self._data), self._policy)
        chunk[:] = self._data
        self._publisher.put(self._zenoh.ZBytes(chunk))

    def close(self) -> None:
        """Undeclare and close."""
        self._publisher.undeclare()
        self._session.close()


def _read_shm(sample: Any) -> bytes:
    shm = sample.payload.as_shm()
    if shm is None:  # delivered by copy (e.g. SHM negotiation failed): count it as such
        return sample.payload.to_bytes()
    return bytes(shm)


def make_sender(settings: PathSettings, shared: Any) -> ZenohShmSender:
    """The publishing side."""
    return ZenohShmSender(settings)


def make_receiver(settings: PathSettings, shared: Any) -> ZenohReceiver:
    """The subscribing side: copies the SHM chunk out with ``bytes()``."""
    return ZenohReceiver(settings, shared_memory=True, read=_read_shm)
