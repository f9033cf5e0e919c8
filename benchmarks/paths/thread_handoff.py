"""Peer: a bare hand-off between two threads of one process (the floor of any executor thread).

The sender stamps a prepared bytearray and puts it into a ``queue.SimpleQueue``; a receiving
thread blocked on ``get()`` delivers it. This is the least any design that runs callbacks on a
thread other than the publisher's can cost; ours in-process is judged against it in the same run.
"""

from __future__ import annotations

import queue
import threading
from typing import Any, Callable

from benchmarks.paths import PathSettings
from benchmarks.protocol import STAMP_SIZE, stamp_into

LABEL = "bare thread hand-off"
KIND = "peer"
TOPOLOGY = "thread"

# One process: sender and receiver of a run meet here (the runner builds both in this process).
_channels: dict[str, queue.SimpleQueue] = {}
_lock = threading.Lock()


def _channel(settings: PathSettings) -> queue.SimpleQueue:
    with _lock:
        return _channels.setdefault(settings.run_id, queue.SimpleQueue())


class HandoffSender:
    """Stamps one prepared bytearray per size and hands it over."""

    def __init__(self, settings: PathSettings) -> None:
        self._queue = _channel(settings)
        self._data = bytearray(STAMP_SIZE)

    def prepare(self, nbytes: int) -> None:
        """The payload: a bytearray of ``nbytes``, prepared untimed."""
        self._data = bytearray(nbytes)

    def send(self, seq: int) -> None:
        """Stamp and hand the payload to the receiving thread."""
        stamp_into(self._data, seq)
        self._queue.put(self._data)

    def close(self) -> None:
        """Tell the receiving thread to end."""
        self._queue.put(None)


class HandoffReceiver:
    """A thread blocked on the queue delivers every payload it gets."""

    polls = False

    def __init__(self, settings: PathSettings) -> None:
        self._queue = _channel(settings)
        self._deliver: Callable[[Any], None] | None = None
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            payload = self._queue.get()
            if payload is None:
                return
            if self._deliver is not None:
                self._deliver(memoryview(payload)[:STAMP_SIZE])

    def prepare(self, nbytes: int, deliver: Callable[[Any], None]) -> None:
        """(Re)bind the delivery callback."""
        self._deliver = deliver

    def poll(self) -> bool:
        """Not a polling receiver."""
        return False

    def close(self) -> None:
        """The sender's close ends the thread."""
        self._thread.join(timeout=1.0)


def make_sender(settings: PathSettings, shared: Any) -> HandoffSender:
    """The publishing side."""
    return HandoffSender(settings)


def make_receiver(settings: PathSettings, shared: Any) -> HandoffReceiver:
    """The receiving side (a thread of the same process)."""
    return HandoffReceiver(settings)
