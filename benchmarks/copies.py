"""Bytes copied per message on our paths, counted while the benchmark runs.

Nothing is added to library code. The benchmark child wraps the two functions through which
buffer_pubsub moves payload bytes, in buffer_pubsub's own module namespace:

- ``buffer_pubsub.publisher.serialize_message``: every byte it returns was written (copied) by
  the CDR serializer: the whole payload on the CPU route, only a descriptor on a buffer route;
- ``buffer_pubsub.subscription.deserialize_message``: its input is the subscription's copy of the
  wire payload (``ZBytes.to_bytes()``), so its length is the bytes copied out of Zenoh.

The receiver then checks where the delivered tensor lives: inside the received wire bytes (a
view: no further copy), in a /dev/shm mapping (the publisher's export: zero-copy), the very memory
the publisher filled (intra-process), or elsewhere (a copy of the tensor: ``materialized``).
Zenoh-internal copies of the wire bytes (its copy-in on ``put``, the socket) are not counted.
"""

from __future__ import annotations

import bisect
import threading
from typing import Any, Callable

import numpy as np

# Process-local: data pointers of tensors published in this process (intra-process check).
PUBLISHED_POINTERS: dict[int, int] = {}


class ByteCounter:
    """Counts calls and bytes through one wrapped function."""

    def __init__(self) -> None:
        self.calls = 0
        self.nbytes = 0
        self.last: Any = None
        self._lock = threading.Lock()

    def add(self, nbytes: int, last: Any = None) -> None:
        with self._lock:
            self.calls += 1
            self.nbytes += nbytes
            self.last = last

    def take(self) -> tuple[int, int]:
        """(calls, bytes) since the last take."""
        with self._lock:
            counted = (self.calls, self.nbytes)
            self.calls = self.nbytes = 0
            return counted


def wrap_serializer(module: Any, counter: ByteCounter) -> None:
    """Count the output of ``module.serialize_message``."""
    original: Callable[..., Any] = module.serialize_message

    def counted(*args: Any, **kwargs: Any) -> Any:
        data = original(*args, **kwargs)
        counter.add(len(data))
        return data

    module.serialize_message = counted


def wrap_deserializer(module: Any, counter: ByteCounter) -> None:
    """Count the input of ``module.deserialize_message`` and remember it for aliasing checks."""
    original: Callable[..., Any] = module.deserialize_message

    def counted(data: Any, *args: Any, **kwargs: Any) -> Any:
        counter.add(len(data), data)
        return original(data, *args, **kwargs)

    module.deserialize_message = counted


def address_of(buffer: Any) -> int:
    """Address of the first byte of a bytes-like object or array."""
    return int(np.frombuffer(buffer, dtype=np.uint8).ctypes.data) if len(buffer) else 0


class ShmMappings:
    """Address ranges of the shared memory this process maps: /dev/shm files and memfds
    (refreshed on demand)."""

    def __init__(self) -> None:
        self._starts: list[int] = []
        self._ranges: list[tuple[int, int, str]] = []

    def refresh(self) -> None:
        ranges = []
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as maps:
            for line in maps:
                parts = line.split(maxsplit=5)
                # /dev/shm files, and memfd arenas (warp_buffer's shared memory has no name)
                if len(parts) == 6 and parts[5].startswith(("/dev/shm/", "/memfd:")):
                    start, end = (int(x, 16) for x in parts[0].split("-"))
                    ranges.append((start, end, parts[5].strip()))
        ranges.sort()
        self._ranges = ranges
        self._starts = [r[0] for r in ranges]

    def file_of(self, address: int) -> str | None:
        """The /dev/shm file mapped at ``address``, if any."""
        index = bisect.bisect_right(self._starts, address) - 1
        if index >= 0 and address < self._ranges[index][1]:
            return self._ranges[index][2]
        return None


def classify_delivery(data_ptr: int, nbytes: int, seq: int, wire: Any,
                      mappings: ShmMappings) -> tuple[str, int]:
    """Where the delivered tensor lives and how many of its bytes were copied to get there."""
    if PUBLISHED_POINTERS.get(seq) == data_ptr:
        return "same memory as published (intra-process)", 0
    if wire is not None and len(wire):
        start = address_of(wire)
        if start <= data_ptr and data_ptr + nbytes <= start + len(wire):
            return "view into the received wire bytes", 0
    mappings.refresh()
    shm_file = mappings.file_of(data_ptr)
    if shm_file is not None:
        return f"shared mapping {shm_file.rsplit('/', 1)[-1]} (publisher's export)", 0
    return "private copy", nbytes
