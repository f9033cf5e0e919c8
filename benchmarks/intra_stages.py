"""Where an in-process message's time goes, stage by stage, hot and after a pause.

``python -m benchmarks.intra_stages [--count N] [--pause-us US]``: one process, one node (its
default executor thread), a prepared 4 KiB CPU tensor message published to a subscription of
the same node (the bench's ``intra_prepared`` path), one message in flight. Interleaved with it,
the bare hand-off the bench judges it against: a ``queue.SimpleQueue`` put to a thread blocked
in ``get()``.

Both run twice: **hot** (the next message right after the previous one's callback) and **after
a pause** (``--pause-us``, default 500 us, before every message: the bench's situation, where
the sender waits for each acknowledgement and the process sleeps). The pause is what separates
the two columns: the same Python code runs several times slower right after the thread slept,
so an in-process budget is set by how much code a message runs, not by any one stage.

Stage boundaries are stamped with ``perf_counter_ns`` by thin wrappers the benchmark puts, in
its own process only, around ``seal_and_list_backends`` (as the publisher calls it, after
validating the fields) and the executor's waker (``notify`` from the publisher, ``wait``
returning on the executor thread); the callback stamps its entry. Each wrapper costs ~0.3 us.
"""

from __future__ import annotations

import argparse
import json
import queue
import statistics
import threading
import time
import uuid
from typing import Any

TENSOR_TYPE = "tensor_msgs/msg/ExperimentalTensor"
NBYTES = 4096
WARMUP = 50
# (label, from stamp, to stamp), in the order a message passes them.
STAGES = (
    ("publish: validate fields, seal + backends", "t0", "sealed"),
    ("publish: number, route, queue, notify", "sealed", "notified"),
    ("publish: rest until publish() returns", "notified", "returned"),
    ("executor: notify -> its wait returns (wake-up)", "notified", "woken"),
    ("executor: woken -> user callback", "woken", "callback"),
    ("one-way total (publish -> callback)", "t0", "callback"),
)
BARE_LABEL = "bare hand-off: put -> get returns (the floor)"


class _StampedWaker:
    """The node's waker with its ``notify`` and ``wait`` stamped (the benchmark's own wrapper:
    the real waker's slots cannot take patched methods)."""

    def __init__(self, waker: Any, stamps: dict[str, int]) -> None:
        self._waker = waker
        self._stamps = stamps

    def notify(self) -> None:
        self._stamps["notified"] = time.perf_counter_ns()
        self._waker.notify()

    def wait(self, timeout: float | None) -> None:
        self._waker.wait(timeout)
        if "notified" in self._stamps:  # not a housekeeping tick's timeout
            self._stamps.setdefault("woken", time.perf_counter_ns())

    def __getattr__(self, name: str) -> Any:
        return getattr(self._waker, name)


def measure(count: int, pause_us: float, domain_id: int) -> dict[str, Any]:
    """Per mode ("hot", "after a pause"): the median of every stage and of the bare hand-off."""
    import numpy as np

    import buffer_pubsub
    import buffer_pubsub.publisher as publisher_module
    import tensor_conversions.numpy as tc
    from rosidl_buffer.messages import get_message_type

    stamps: dict[str, int] = {}
    clock = time.perf_counter_ns

    def after(name: str, function: Any) -> Any:
        def stamped(*args: Any) -> Any:
            result = function(*args)
            stamps[name] = clock()
            return result
        return stamped

    seal = publisher_module.seal_and_list_backends
    publisher_module.seal_and_list_backends = after("sealed", seal)
    done = queue.SimpleQueue()
    bare_in: queue.SimpleQueue[Any] = queue.SimpleQueue()
    bare_out: queue.SimpleQueue[int] = queue.SimpleQueue()

    def bare_receiver() -> None:
        while bare_in.get() is not None:
            bare_out.put(clock())

    def on_message(msg: Any) -> None:
        stamps["callback"] = clock()
        done.put(None)

    thread = threading.Thread(target=bare_receiver, daemon=True)
    thread.start()
    name = f"intra_stages_{uuid.uuid4().hex[:8]}"
    msg_type = get_message_type(TENSOR_TYPE)
    results: dict[str, Any] = {}
    try:
        with buffer_pubsub.Node(name, domain_id=domain_id) as node:
            executor = node.scheduler
            executor.waker = _StampedWaker(executor.waker, stamps)
            executor.waker.notify()  # the executor thread's current wait returns on the old one
            node.create_subscription(msg_type, f"/{name}", on_message, depth=16,
                                     acceptable_buffer_backends="cpu")
            pub = node.create_publisher(msg_type, f"/{name}", depth=16)
            msg = tc.allocate_tensor_msg((NBYTES,), np.uint8, backend="cpu")
            payload = bytearray(NBYTES)
            for mode, pause_s in (("hot", 0.0), ("after a pause", pause_us / 1e6)):
                rows: list[dict[str, int]] = []
                bare: list[int] = []
                for i in range(count + WARMUP):
                    if pause_s:
                        time.sleep(pause_s)
                    stamps.clear()
                    stamps["t0"] = clock()
                    pub.publish(msg)
                    stamps["returned"] = clock()
                    done.get(timeout=5.0)
                    record = dict(stamps)
                    if pause_s:
                        time.sleep(pause_s)
                    sent = clock()
                    bare_in.put(payload)
                    received = bare_out.get(timeout=5.0)
                    if i >= WARMUP:
                        rows.append(record)
                        bare.append(received - sent)
                results[mode] = _summary(rows, bare)
    finally:
        publisher_module.seal_and_list_backends = seal
        bare_in.put(None)
        thread.join(timeout=1.0)
    return {"count": count, "pause_us": pause_us, "nbytes": NBYTES, "modes": results}


def _summary(rows: list[dict[str, int]], bare: list[int]) -> dict[str, float]:
    summary = {label: statistics.median(row[end] - row[start] for row in rows) / 1e3
               for label, start, end in STAGES}
    summary[BARE_LABEL] = statistics.median(bare) / 1e3
    return summary


def format_report(report: dict[str, Any]) -> str:
    """The stage table, one column per mode, and the ratio the bench judges."""
    modes = list(report["modes"])
    width = max(len(label) for label, _, _ in STAGES) + 2
    lines = [f"In-process stages ({report['nbytes'] // 1024} KiB prepared CPU message, median us "
             f"of {report['count']}; 'after a pause': {report['pause_us']:g} us of sleep before "
             "each message)",
             f"{'stage':<{width}}" + "".join(f"{mode:>16}" for mode in modes)]
    for label in [label for label, _, _ in STAGES] + [BARE_LABEL]:
        lines.append(f"{label:<{width}}" + "".join(
            f"{report['modes'][mode][label]:>16.1f}" for mode in modes))
    total = "one-way total (publish -> callback)"
    lines.append(f"{'ours / bare hand-off':<{width}}" + "".join(
        f"{report['modes'][m][total] / report['modes'][m][BARE_LABEL]:>15.2f}x" for m in modes))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks.intra_stages``."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.intra_stages",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--count", type=int, default=1000, help="messages per mode")
    parser.add_argument("--pause-us", type=float, default=500.0,
                        help="sleep before each message in the 'after a pause' mode")
    parser.add_argument("--domain", type=int, default=None,
                        help="ROS domain id (default: one of 100-199 for this run)")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = parser.parse_args(argv)
    if args.count < 1 or not 0 <= args.pause_us <= 1e6:
        parser.error("--count must be >= 1 and --pause-us within 0..1e6")
    domain = args.domain if args.domain is not None else 100 + uuid.uuid4().int % 100
    report = measure(args.count, args.pause_us, domain)
    print(json.dumps(report) if args.json else format_report(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
