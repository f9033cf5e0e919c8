"""The executor waker's cost: the fast lane's native waker (ppoll on eventfds) against a threading.Condition.

``python -m benchmarks.waker_cost [--count N]``, one process, side by side:
- ``notify()`` with nobody waiting (what every Zenoh-route delivery pays to post a task);
- ``wait(0)`` with nothing pending (an executor checking before it sleeps);
- the wake-up: one thread in ``wait(1.0)``, another stamps and calls ``notify()``; the time
  until the waiting thread runs again (one hand-off in flight, p50 / p99).
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from typing import Any


class ConditionWaker:
    """The plain threading waker (what ``buffer_pubsub._waker`` does by default)."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._notified = False

    def notify(self) -> None:
        with self._cond:
            self._notified = True
            self._cond.notify()

    def wait(self, timeout: float | None = None) -> None:
        with self._cond:
            if not self._notified:
                self._cond.wait(timeout)
            self._notified = False

    def close(self) -> None:
        pass


def _per_call_us(function: Any, count: int) -> float:
    start = time.perf_counter_ns()
    for _ in range(count):
        function()
    return (time.perf_counter_ns() - start) / count / 1000


def _wake_latency_us(waker: Any, count: int) -> tuple[float, float]:
    stamps: list[int] = []
    woke: list[int] = []
    done = threading.Event()
    waiting = threading.Event()

    def waiter() -> None:
        while not done.is_set():
            waiting.set()
            waker.wait(1.0)
            woke.append(time.perf_counter_ns())

    thread = threading.Thread(target=waiter, daemon=True)
    thread.start()
    for _ in range(count):
        waiting.wait(1.0)
        waiting.clear()
        time.sleep(0.0005)  # let the waiter block
        stamps.append(time.perf_counter_ns())
        waker.notify()
        while len(woke) < len(stamps):
            time.sleep(0)
    done.set()
    waker.notify()
    thread.join(2.0)
    delays = sorted((w - s) / 1000 for s, w in zip(stamps, woke))
    return delays[len(delays) // 2], delays[min(len(delays) - 1, int(0.99 * len(delays)))]


def main(argv: list[str] | None = None) -> int:
    """Measure both wakers; print one line each."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.waker_cost")
    parser.add_argument("--count", type=int, default=2000)
    args = parser.parse_args(argv)
    from buffer_pubsub import fast_lane

    if not fast_lane.status(True).available:
        print(f"fast lane unavailable: {fast_lane.status(True).reason}")
        return 1
    rows = []
    for label, waker in (("threading.Condition", ConditionWaker()),
                         ("LaneWaker (native: eventfd + ppoll)", fast_lane.LaneWaker())):
        notify = _per_call_us(waker.notify, args.count)
        waker.wait(0.0)
        idle = _per_call_us(lambda: waker.wait(0.0), args.count)
        p50, p99 = _wake_latency_us(waker, max(200, args.count // 10))
        waker.close()
        rows.append((label, notify, idle, p50, p99))
    width = max(len(r[0]) for r in rows)
    print(f"{'waker':<{width}}  notify us  wait(0) us  wake p50 us  wake p99 us")
    for label, notify, idle, p50, p99 in rows:
        print(f"{label:<{width}}  {notify:9.2f}  {idle:10.2f}  {p50:11.1f}  {p99:11.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
