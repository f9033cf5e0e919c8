"""Peer: iceoryx2 zero-copy publish-subscribe woken by an iceoryx2 event (blocking listener).

The same payload path as ``iceoryx2_pubsub`` (a loaned slice, stamped in place, read in place),
but the subscriber sleeps in ``Listener.timed_wait`` until the sender's notifier fires, as a
Python application that must not burn a core would run it: the bar the fast lane is held to.
"""

from __future__ import annotations

from typing import Any

from benchmarks.paths import PathSettings
from benchmarks.paths.iceoryx2_pubsub import (  # noqa: F401 - shm_prefixes: the runner's
    Iceoryx2Receiver,
    Iceoryx2Sender,
    shm_prefixes,
)

LABEL = "iceoryx2 (zero-copy, blocking listener)"
KIND = "peer"
TOPOLOGY = "pair"
WAIT_S = 0.05  # the receiver loop checks its control pipe this often while idle


def _event(service: Any) -> Any:
    """The event service beside the payload services of this run."""
    iox2 = service.iox2
    name = iox2.ServiceName.new(f"warp_buffer_bench/{service._settings.run_id}/event")
    return service.node.service_builder(name).event().open_or_create()


class ListenerSender(Iceoryx2Sender):
    """Sends as the busy-poll peer does, then notifies the listener."""

    def __init__(self, settings: PathSettings) -> None:
        super().__init__(settings)
        self._notifier = _event(self._service).notifier_builder().create()

    def send(self, seq: int) -> None:
        """Loan, stamp, send, notify."""
        super().send(seq)
        self._notifier.notify()

    def close(self) -> None:
        """Drop the notifier, then the publisher and node."""
        self._notifier.delete()
        super().close()


class ListenerReceiver(Iceoryx2Receiver):
    """Sleeps in the listener until notified, then takes what arrived."""

    def __init__(self, settings: PathSettings) -> None:
        super().__init__(settings)
        self._listener = _event(self._service).listener_builder().create()
        self._wait = self._service.iox2.Duration.from_secs_f64(WAIT_S)

    def poll(self) -> bool:
        """Block up to WAIT_S for a notification, then take every waiting sample."""
        if self._subscriber is None:
            return False
        self._listener.timed_wait(self._wait)
        delivered = False
        while super().poll():
            delivered = True
        return delivered

    def close(self) -> None:
        """Drop the listener, then the subscriber and node."""
        self._listener.delete()
        super().close()


def make_sender(settings: PathSettings, shared: Any) -> ListenerSender:
    """The publishing side."""
    return ListenerSender(settings)


def make_receiver(settings: PathSettings, shared: Any) -> ListenerReceiver:
    """The subscribing side."""
    return ListenerReceiver(settings)
