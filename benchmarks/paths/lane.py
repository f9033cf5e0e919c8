"""Ours: the same-host fast lane (``buffer_pubsub.fast_lane``) carrying a descriptor message.

What travels is what the lane carries for a zero-copy message: a 602-byte message (the size of
today's warp descriptor message for a 4 KiB tensor; the payload itself stays where the
publisher wrote it, in shared memory, so the message is the same at every size). The receiver
blocks in ``LaneWaker.wait`` (``ppoll`` on the ring's eventfd doorbell, no polling) and reads
the stamp from the message it took. The import of the descriptor is not part of this
path: ``benchmarks/lane_stages.py`` measures it, stage by stage.
"""

from __future__ import annotations

import hashlib
import time
from typing import Any, Callable

from benchmarks.paths import PathSettings, PathUnavailable
from benchmarks.protocol import STAMP_SIZE, stamp_into

LABEL = "ours: fast lane (descriptor through a ring, eventfd doorbell)"
KIND = "ours"
TOPOLOGY = "pair"
MESSAGE_BYTES = 602
WAIT_S = 0.05  # the receiver loop checks its control pipe this often while idle


def _lane() -> Any:
    from buffer_pubsub import fast_lane

    state = fast_lane.status(True)
    if not state.available:
        raise PathUnavailable(state.reason)
    return fast_lane


def _route(settings: PathSettings) -> str:
    gid = hashlib.sha256(settings.run_id.encode()).digest()[:16]
    return _lane().service_name(f"warp_buffer_bench/{settings.run_id}", gid)


class LaneSender:
    """Stamps a prepared descriptor-sized message and writes it to the lane."""

    def __init__(self, settings: PathSettings) -> None:
        self._route = _route(settings)
        self._writer: Any = None
        self._message = bytearray(MESSAGE_BYTES)
        self._sizes: list[int] = []

    def prepare(self, nbytes: int) -> None:
        """Open the receiver's lane (it exists once the receiver said it is ready)."""
        if self._writer is None:
            self._writer = _lane().LaneWriter(self._route)
        self._sizes.append(nbytes)

    def send(self, seq: int) -> None:
        """Stamp, write (one copy of 602 B into the ring), wake the receiver."""
        stamp_into(self._message, seq)
        self._writer.write(self._message)

    def report(self) -> dict:
        """Bytes copied per message: the 602-byte message into the ring (never the
        payload, which stays in shared memory)."""
        return {"per_size": {str(n): {"serialized_bytes_per_message": MESSAGE_BYTES}
                             for n in self._sizes}}

    def close(self) -> None:
        """Drop the writer."""
        if self._writer is not None:
            self._writer.close()


class LaneReceiver:
    """Blocks in the lane waker; delivers the stamp of each message on the waiting thread."""

    polls = True

    def __init__(self, settings: PathSettings, busy_poll_s: float = 0.0) -> None:
        lane = _lane()
        self._reader = lane.LaneReader(_route(settings), depth=16)
        self._waker = lane.LaneWaker(busy_poll_s=busy_poll_s)
        self._started = (time.monotonic(), time.process_time())
        self._deliver: Callable[[bytes | memoryview], None] | None = None
        self._delivered = False
        self._sizes: list[int] = []
        self._waker.attach(self._reader, self._on_message)

    def _on_message(self, data: bytes) -> None:
        if self._deliver is not None:
            self._deliver(memoryview(data)[:STAMP_SIZE])
            self._delivered = True

    def prepare(self, nbytes: int, deliver: Callable[[bytes | memoryview], None]) -> None:
        """The same lane carries every size."""
        self._deliver = deliver
        self._sizes.append(nbytes)

    def report(self) -> dict:
        """Bytes copied per message (the message out of the ring) and the
        CPU this receiver process used per second of the run (1.0 = a core held)."""
        wall = time.monotonic() - self._started[0]
        return {"per_size": {str(n): {"received_wire_bytes": MESSAGE_BYTES, "backend": "lane",
                                      "tensor_lives_in": "shared memory (not read here)"}
                             for n in self._sizes},
                "cpu_per_wall_s": (time.process_time() - self._started[1]) / wall}

    def poll(self) -> bool:
        """Block up to WAIT_S for lane messages; True when one was delivered."""
        self._delivered = False
        self._waker.wait(WAIT_S)
        return self._delivered

    def close(self) -> None:
        """Drop the waker and the reader; say what CPU the receiver used."""
        from benchmarks.protocol import progress

        progress(f"  [lane receiver, busy_poll_s={self._waker.busy_poll_s:g}] CPU "
                 f"{self.report()['cpu_per_wall_s']:.2f} s per s of the run")
        self._waker.close()
        self._reader.close()


def make_sender(settings: PathSettings, shared: Any) -> LaneSender:
    """The publishing side."""
    return LaneSender(settings)


def make_receiver(settings: PathSettings, shared: Any) -> LaneReceiver:
    """The subscribing side."""
    return LaneReceiver(settings)
