"""Peer: ``torch.multiprocessing`` sharing a CPU tensor through a queue.

The sending child starts the receiver with torch's own ``spawn`` context and hands it a
``torch.multiprocessing`` queue, as a PyTorch user would. Tensors are moved to shared memory
once (``share_memory_()`` while preparing a size, not timed) and reused from a small pool, the
peer's best case: each ``put`` then passes a file descriptor, and the receiver maps the storage
(cached by torch after the first time) and reads the stamp in place: no payload copies.
"""

from __future__ import annotations

import queue
from typing import Any, Callable

from benchmarks.paths import PathSettings, PathUnavailable
from benchmarks.protocol import STAMP_SIZE, stamp_into

LABEL = "torch.multiprocessing"
KIND = "peer"
TOPOLOGY = "spawn"
POOL_BYTES = 512 << 20  # shared tensors kept per size, at most this much memory
POOL_MAX = 16  # more than the rate window: a reused tensor is never still in flight


def _torch() -> Any:
    try:
        import torch
    except ImportError as error:
        raise PathUnavailable(f"torch not installed ({error})") from error
    return torch


def make_shared(settings: PathSettings) -> tuple[Any, Any]:
    """torch's spawn context and the queue both sides use."""
    context = _torch().multiprocessing.get_context("spawn")
    return context, context.Queue()


class TorchSender:
    """Puts tensors that already live in shared memory."""

    def __init__(self, tensors: Any) -> None:
        self._torch = _torch()
        self._queue = tensors
        self._pool: list[Any] = []
        self._next = 0

    def prepare(self, nbytes: int) -> None:
        """Allocate this size's pool in shared memory."""
        self._pool.clear()
        self._next = 0
        count = max(2, min(POOL_MAX, POOL_BYTES // nbytes))
        self._pool = [self._torch.empty(nbytes, dtype=self._torch.uint8).share_memory_()
                      for _ in range(count)]

    def send(self, seq: int) -> None:
        """Stamp the next pooled tensor and put it."""
        tensor = self._pool[self._next]
        self._next = (self._next + 1) % len(self._pool)
        stamp_into(memoryview(tensor.numpy()[:STAMP_SIZE]), seq)
        self._queue.put(tensor)

    def close(self) -> None:
        """Drop the pool; flush the queue's feeder thread."""
        self._pool.clear()
        self._queue.close()
        self._queue.join_thread()


class TorchReceiver:
    """Gets tensors from the queue (blocking briefly so control messages are still served)."""

    polls = True

    def __init__(self, tensors: Any) -> None:
        _torch()
        self._queue = tensors
        self._deliver: Callable[[bytes | memoryview], None] | None = None

    def prepare(self, nbytes: int, deliver: Callable[[bytes | memoryview], None]) -> None:
        """Any size arrives on the same queue."""
        self._deliver = deliver

    def poll(self) -> bool:
        """Take one tensor if one comes within 10 ms."""
        try:
            tensor = self._queue.get(timeout=0.01)
        except queue.Empty:
            return False
        self._deliver(memoryview(tensor.numpy()[:STAMP_SIZE]))
        return True

    def close(self) -> None:
        """Nothing held beyond the queue."""
        self._queue.close()


def make_sender(settings: PathSettings, shared: Any) -> TorchSender:
    """The putting side."""
    return TorchSender(shared)


def make_receiver(settings: PathSettings, shared: Any) -> TorchReceiver:
    """The getting side."""
    return TorchReceiver(shared)
