"""Peer: iceoryx2 zero-copy publish-subscribe (``Slice[c_uint8]`` payloads, one service per size).

The sender loans a slice from its shared-memory data segment and sends it; the subscriber maps
the same segment and reads the stamp in place: no payload copy on either side. The subscriber
busy-polls, the way iceoryx2's own latency benchmarks run.
"""

from __future__ import annotations

import ctypes
import time
from typing import Any, Callable

from benchmarks.paths import PathSettings, PathUnavailable
from benchmarks.protocol import STAMP_SIZE, stamp_into

LABEL = "iceoryx2 (zero-copy)"
KIND = "peer"
TOPOLOGY = "pair"
BUFFER = 16  # subscriber queue and publisher loans: more than the rate window


def _iox2() -> Any:
    try:
        import iceoryx2
    except ImportError as error:
        raise PathUnavailable(f"iceoryx2 not installed ({error})") from error
    iceoryx2.set_log_level_from_env_or(iceoryx2.LogLevel.Error)
    return iceoryx2


def shm_prefixes(settings: PathSettings) -> tuple[str, ...]:
    """The prefix of every iceoryx2 file this run creates (iceoryx2's ``global.prefix``, its own
    notion of a domain): the leftovers the runner may remove are this run's, never those of
    another iceoryx2 program on the host, which keeps the default ``iox2_``."""
    return (f"iox2b_{settings.run_id}_",)


class _Service:
    """A node and, per payload size, a publish-subscribe service of its own."""

    def __init__(self, settings: PathSettings, role: str) -> None:
        self.iox2 = _iox2()
        self._settings = settings
        name = self.iox2.NodeName.new(f"bench_{role}_{settings.run_id}")
        config = self.iox2.config.global_config()
        config.global_cfg.prefix = self.iox2.FileName.new(shm_prefixes(settings)[0])
        self.node = (self.iox2.NodeBuilder.new().name(name).config(config)
                     .create(self.iox2.ServiceType.Ipc))

    def open(self, nbytes: int) -> Any:
        """The service carrying payloads of ``nbytes`` (created by whoever comes first)."""
        service_name = self.iox2.ServiceName.new(
            f"warp_buffer_bench/{self._settings.run_id}/{nbytes}")
        return (self.node.service_builder(service_name)
                .publish_subscribe(self.iox2.Slice[ctypes.c_uint8])
                .subscriber_max_buffer_size(BUFFER)
                .history_size(0)
                .open_or_create())


class Iceoryx2Sender:
    """Loans a slice per message, stamps it in place, sends it."""

    def __init__(self, settings: PathSettings) -> None:
        self._service = _Service(settings, "pub")
        self._publisher: Any = None
        self._port: Any = None
        self._nbytes = 0

    def prepare(self, nbytes: int) -> None:
        """A publisher on this size's service (the subscriber already waits there)."""
        self._drop()
        self._port = self._service.open(nbytes)
        self._publisher = (self._port.publisher_builder().initial_max_slice_len(nbytes)
                           .max_loaned_samples(2).create())
        self._nbytes = nbytes

    def send(self, seq: int) -> None:
        """Loan, stamp, send: zero copies. The clock is read before the loan."""
        t_send = time.perf_counter_ns()
        sample = self._publisher.loan_slice_uninit(self._nbytes)
        view = (ctypes.c_uint8 * STAMP_SIZE).from_address(sample.payload_ptr)
        stamp_into(memoryview(view).cast("B"), seq, t_send)
        sample.assume_init().send()

    def _drop(self) -> None:
        if self._publisher is not None:
            self._publisher.delete()
        self._publisher = self._port = None

    def close(self) -> None:
        """Drop the publisher and the node (iceoryx2 removes its shared memory)."""
        self._drop()
        self._service.node = None


class Iceoryx2Receiver:
    """Busy-polls a subscriber; reads the stamp where the publisher wrote it."""

    polls = True

    def __init__(self, settings: PathSettings) -> None:
        self._service = _Service(settings, "sub")
        self._subscriber: Any = None
        self._port: Any = None
        self._deliver: Callable[[bytes | memoryview], None] | None = None

    def prepare(self, nbytes: int, deliver: Callable[[bytes | memoryview], None]) -> None:
        """Subscribe to this size's service."""
        self._drop()
        self._port = self._service.open(nbytes)
        self._subscriber = self._port.subscriber_builder().buffer_size(BUFFER).create()
        self._deliver = deliver

    def poll(self) -> bool:
        """Take one sample if there is one."""
        if self._subscriber is None:
            return False
        sample = self._subscriber.receive()
        if sample is None:
            return False
        head = (ctypes.c_uint8 * STAMP_SIZE).from_address(sample.payload_ptr)
        self._deliver(memoryview(head).cast("B"))
        sample.delete()
        return True

    def _drop(self) -> None:
        if self._subscriber is not None:
            self._subscriber.delete()
        self._subscriber = self._port = None

    def close(self) -> None:
        """Drop the subscriber and the node."""
        self._drop()
        self._service.node = None


def make_sender(settings: PathSettings, shared: Any) -> Iceoryx2Sender:
    """The publishing side."""
    return Iceoryx2Sender(settings)


def make_receiver(settings: PathSettings, shared: Any) -> Iceoryx2Receiver:
    """The subscribing side."""
    return Iceoryx2Receiver(settings)
