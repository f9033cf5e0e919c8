"""The measurement protocol every path shares: endpoints, stamps, acknowledgements, loops.

One-way latency is measured with timestamps, not ping-pong: the sender writes
``(seq, time.perf_counter_ns())`` into the first 16 bytes of the payload right before it hands
the message to the transport (before any loan, allocation or copy-in the transport needs); the
receiver takes ``perf_counter_ns()`` once the payload is usable in its process (a view mapped or a
copy made) and reads the stamp from the payload itself. ``perf_counter_ns`` is CLOCK_MONOTONIC on
Linux, one clock for every process on the host, so the difference is the one-way latency.
The receiver acknowledges each message on a side pipe (not timed) so that exactly one message is
in flight during latency runs and a bounded window during rate runs.
"""

from __future__ import annotations

import json
import struct
import sys
import time
from multiprocessing.connection import Connection
from typing import Any, Callable, Protocol

STAMP = struct.Struct("<qq")  # seq, t_send_ns: written at the start of every payload
ACK = struct.Struct("<qqq")  # seq, t_send_ns, t_recv_ns
READY_SEQ = -1  # ack seq telling the sender the receiver is prepared for the announced size
STAMP_SIZE = STAMP.size
METHOD = "one-way, timestamps: time.perf_counter_ns (CLOCK_MONOTONIC, shared by processes)"

Deliver = Callable[[bytes | memoryview], None]


class SenderEndpoint(Protocol):
    """The publishing side of one path."""

    def prepare(self, nbytes: int) -> None:
        """Get ready to send payloads of ``nbytes`` (called once per size, before any send)."""

    def send(self, seq: int) -> None:
        """Stamp ``(seq, now)`` into a fresh payload of the prepared size and publish it."""

    def close(self) -> None:
        """Release every resource (ports, sessions, shared memory)."""


class ReceiverEndpoint(Protocol):
    """The subscribing side of one path.

    ``polls`` False: messages arrive through callbacks on the transport's threads after
    ``prepare``; True: the receiver loop calls ``poll`` (which may block briefly) to take one.
    """

    polls: bool

    def prepare(self, nbytes: int, deliver: Deliver) -> None:
        """Be ready to receive payloads of ``nbytes``; call ``deliver(first_16_bytes)`` for each."""

    def poll(self) -> bool:
        """Take at most one message (polling receivers only); True when one was delivered."""

    def close(self) -> None:
        """Release every resource."""


def receiver_report(receiver: object) -> dict:
    """What a receiver counted (``report()`` when it has one, e.g. copies per message)."""
    report = getattr(receiver, "report", None)
    return dict(report()) if callable(report) else {}


def progress(message: str) -> None:
    """One progress line on stderr (the runner's terminal)."""
    print(message, file=sys.stderr, flush=True)


def stamp_into(buffer: Any, seq: int, t_send_ns: int | None = None) -> None:
    """Write ``(seq, t_send_ns)`` at the start of ``buffer`` (default: now, read last). Paths
    that must loan or allocate the payload first read the clock before doing so."""
    STAMP.pack_into(buffer, 0, seq, time.perf_counter_ns() if t_send_ns is None else t_send_ns)


def stamp_bytes(seq: int) -> bytes:
    """``(seq, now)`` as 16 bytes, for transports that copy the payload in from bytes."""
    return STAMP.pack(seq, time.perf_counter_ns())


# ---------------------------------------------------------------------------------------------
# Receiver side


class _Acknowledger:
    """``deliver`` callback: reads the stamp, acks ``(seq, t_send, t_recv)`` on the ack pipe."""

    def __init__(self, ack: Connection) -> None:
        self._ack = ack

    def __call__(self, head: bytes | memoryview) -> None:
        t_recv = time.perf_counter_ns()
        seq, t_send = STAMP.unpack_from(head, 0)
        self._ack.send_bytes(ACK.pack(seq, t_send, t_recv))


def serve_receiver(receiver: ReceiverEndpoint, ctrl: Connection, ack: Connection) -> None:
    """Answer the sender's control messages until it says stop; close the receiver at the end."""
    deliver = _Acknowledger(ack)

    def handle(command: dict) -> bool:
        if command["op"] == "stop":
            note_mapped_shm_files()
            ack.send_bytes(json.dumps(receiver_report(receiver)).encode())
            return False
        receiver.prepare(int(command["nbytes"]), deliver)
        ack.send_bytes(ACK.pack(READY_SEQ, 0, 0))
        return True

    from benchmarks.shm import note_mapped_shm_files

    try:
        running = True
        while running:
            if receiver.polls:
                if not receiver.poll() and ctrl.poll(0):
                    running = handle(json.loads(ctrl.recv_bytes()))
            else:
                running = handle(json.loads(ctrl.recv_bytes()))
    except EOFError:
        pass  # the sender went away: nothing left to serve
    finally:
        receiver.close()


# ---------------------------------------------------------------------------------------------
# Sender side


class BenchmarkTimeout(RuntimeError):
    """The receiver did not acknowledge in time."""


class ReceiverUnavailable(RuntimeError):
    """The receiver could not build its endpoint (the message says why)."""


class _Acks:
    """Reads ``ACK`` records from the ack pipe."""

    def __init__(self, ack: Connection) -> None:
        self.raw = ack

    def next(self, timeout_s: float) -> tuple[int, int, int] | None:
        if not self.raw.poll(timeout_s):
            return None
        message = self.raw.recv_bytes()
        if len(message) != ACK.size:  # the receiver failed and says why
            raise ReceiverUnavailable(json.loads(message).get("unavailable", "receiver failed"))
        return ACK.unpack(message)

    def wait_for(self, seq: int, timeout_s: float) -> tuple[int, int, int] | None:
        """The ack of ``seq`` (stale acks of earlier sends are skipped), or None on timeout."""
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            record = self.next(max(left, 0.0))
            if record is None:
                return None
            if record[0] == seq:
                return record


class SenderDriver:
    """Runs the latency and rate phases from the sending side."""

    def __init__(self, sender: SenderEndpoint, ctrl: Connection, ack: Connection,
                 timeout_s: float = 60.0) -> None:
        self._sender = sender
        self._ctrl = ctrl
        self._acks = _Acks(ack)
        self._timeout_s = timeout_s
        self._seq = 0
        self._connected = False

    def _announce(self, nbytes: int) -> None:
        try:
            self._ctrl.send_bytes(json.dumps({"op": "prepare", "nbytes": nbytes}).encode())
        except OSError:  # the receiver is gone: it may have said why before leaving
            self._acks.next(1.0)
            raise BenchmarkTimeout("the receiver exited") from None
        if self._acks.wait_for(READY_SEQ, self._timeout_s) is None:
            raise BenchmarkTimeout(f"receiver not ready for {nbytes} bytes")
        self._sender.prepare(nbytes)

    def _send_one(self) -> tuple[int, int, int]:
        """Send one message and wait for its ack; resend while the peers are still discovering."""
        self._seq += 1
        self._sender.send(self._seq)
        if self._connected:
            record = self._acks.wait_for(self._seq, self._timeout_s)
        else:  # discovery: messages sent before the match are lost, so resend with backoff
            deadline, wait = time.monotonic() + self._timeout_s, 0.05
            record = self._acks.wait_for(self._seq, wait)
            while record is None and time.monotonic() < deadline:
                wait = min(wait * 2, 1.0)
                self._seq += 1
                self._sender.send(self._seq)
                record = self._acks.wait_for(self._seq, wait)
            self._connected = record is not None
        if record is None:
            raise BenchmarkTimeout(f"no ack for message {self._seq}")
        return record

    def latency(self, nbytes: int, iterations: int, warmup: int, budget_s: float,
                min_samples: int = 3) -> list[int]:
        """One-way latency samples (ns) of ``nbytes`` payloads, one message in flight."""
        self._announce(nbytes)
        for _ in range(warmup):
            self._send_one()
        samples: list[int] = []
        deadline = time.monotonic() + budget_s
        while len(samples) < iterations and (
            len(samples) < min_samples or time.monotonic() < deadline
        ):
            _, t_send, t_recv = self._send_one()
            samples.append(t_recv - t_send)
        return samples

    def rate(self, nbytes: int, count: int, window: int, budget_s: float) -> dict[str, float]:
        """Messages per second of ``nbytes`` payloads with up to ``window`` unacknowledged."""
        self._announce(nbytes)
        self._send_one()  # connected and warm
        first = self._seq + 1
        sent = acked = 0
        start = time.perf_counter()
        deadline = time.monotonic() + budget_s
        while acked < count:
            while sent - acked < window and sent < count and time.monotonic() < deadline:
                self._seq += 1
                self._sender.send(self._seq)
                sent += 1
            if sent == acked:
                break  # budget spent and nothing in flight
            record = self._acks.next(self._timeout_s)
            if record is None:
                raise BenchmarkTimeout(f"rate run stalled after {acked} of {sent} messages")
            if record[0] >= first:
                acked += 1
        elapsed = time.perf_counter() - start
        return {"nbytes": nbytes, "messages": acked, "window": window, "seconds": elapsed,
                "msgs_per_s": acked / elapsed}

    def stop(self, timeout_s: float = 10.0) -> dict:
        """Tell the receiver to finish; return its report (empty when it sent none in time)."""
        try:
            self._ctrl.send_bytes(json.dumps({"op": "stop"}).encode())
            deadline = time.monotonic() + timeout_s
            while self._acks.raw.poll(max(deadline - time.monotonic(), 0.0)):
                message = self._acks.raw.recv_bytes()
                if len(message) != ACK.size:
                    return json.loads(message)
        except (OSError, EOFError, ValueError):
            pass
        return {}
