"""Executors side by side: what a slow callback does to another, and what an executor costs.

``python -m benchmarks.executors [--seconds S] [--count N]``, one process, two parts:

1. *Held up*: 30 Hz features and 30 Hz frames on one viewer; the frame callback takes 100 ms
   (a sleep). Features delivered and their delay, with the frames' subscription on the same node
   (the default), on a second node, or on the same node in a callback group of its own under a
   ``MultiThreadedExecutor(2)`` (docs/executors.md).
2. *Cost*: small messages at 1 kHz between two nodes of the process; delivery delay by where the
   callbacks run (the node's thread, ``node.spin()``, the two executors).
"""

from __future__ import annotations

import argparse
import itertools
import os
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from buffer_pubsub import Node
from buffer_pubsub.callback_groups import MutuallyExclusiveCallbackGroup
from buffer_pubsub.executors import Executor, MultiThreadedExecutor, SingleThreadedExecutor

STRING = "std_msgs/msg/String"
RATE_HZ = 30.0
SLOW_S = 0.1
_domains = itertools.count(200 + os.getpid() % 50 * 2)


def _spin_in_background(executor: Executor | None, node: Node | None = None) -> None:
    target: Callable[[], Any] | None = executor.spin if executor is not None else (
        node.spin if node is not None else None)
    if target is not None:
        threading.Thread(target=target, daemon=True).start()


def held_up(arrangement: str, seconds: float) -> dict[str, float]:
    """Features delivered and their delay (ms) behind a 100 ms frame callback."""
    delays: list[int] = []
    domain = next(_domains)
    def on_features(msg: Any, info: Any) -> None:
        delays.append(time.time_ns() - info.source_timestamp_ns)

    with Node("viewer", domain_id=domain) as node, \
            Node("viewer_frames", domain_id=domain) as other:
        node.create_subscription(STRING, "features", on_features, depth=10, with_info=True)
        group = MutuallyExclusiveCallbackGroup() if arrangement == "own group" else None
        (other if arrangement == "second node" else node).create_subscription(
            STRING, "frames", lambda m: time.sleep(SLOW_S), depth=1, callback_group=group)
        executor = None
        if arrangement == "own group":
            executor = MultiThreadedExecutor(num_threads=2)
            executor.add_node(node)
            _spin_in_background(executor)
        sent = 0
        with Node("camera", domain_id=domain) as camera:
            features = camera.create_publisher(STRING, "features")
            frames = camera.create_publisher(STRING, "frames")
            features.wait_for_subscriptions(1, 10)
            frames.wait_for_subscriptions(1, 10)
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                frames.publish(frames.msg_type(data="frame"))
                features.publish(features.msg_type(data="features"))
                sent += 1
                time.sleep(1.0 / RATE_HZ)
            time.sleep(2 * SLOW_S)
        if executor is not None:
            executor.shutdown()
    ms = np.asarray(delays) / 1e6
    return {"sent": sent, "delivered": len(ms), "p50_ms": float(np.percentile(ms, 50)),
            "p99_ms": float(np.percentile(ms, 99))}


def cost(where: str, count: int) -> dict[str, float]:
    """Delivery delay (us) of small messages at 1 kHz, by where the callbacks run."""
    delays: list[int] = []
    domain = next(_domains)
    mode = "thread" if where == "node thread" else "manual"
    def on_message(msg: Any, info: Any) -> None:
        delays.append(time.time_ns() - info.source_timestamp_ns)

    with Node("sub", domain_id=domain, executor=mode) as node:
        node.create_subscription(STRING, "t", on_message, depth=100, with_info=True)
        executor: Executor | None = None
        if where == "SingleThreadedExecutor":
            executor = SingleThreadedExecutor()
        elif where.startswith("MultiThreadedExecutor"):
            executor = MultiThreadedExecutor(num_threads=int(where[-2]))
        if executor is not None:
            executor.add_node(node)
        _spin_in_background(executor, node if where == "node.spin()" else None)
        with Node("pub", domain_id=domain) as sender:
            pub = sender.create_publisher(STRING, "t", depth=100)
            pub.wait_for_subscriptions(1, 10)
            for _ in range(count):
                pub.publish(pub.msg_type(data="x"))
                time.sleep(0.001)
            time.sleep(0.3)
        if executor is not None:
            executor.shutdown()
    us = np.asarray(delays) / 1e3
    return {"delivered": len(us), "p50_us": float(np.percentile(us, 50)),
            "p99_us": float(np.percentile(us, 99))}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.executors")
    parser.add_argument("--seconds", type=float, default=6.0, help="part 1: seconds each")
    parser.add_argument("--count", type=int, default=2000, help="part 2: messages each")
    args = parser.parse_args(argv)
    print(f"Held up: {RATE_HZ:g} Hz features beside {RATE_HZ:g} Hz frames whose callback "
          f"takes {SLOW_S * 1e3:g} ms")
    for arrangement in ("same node", "second node", "own group"):
        r = held_up(arrangement, args.seconds)
        print(f"  {arrangement:12s} features {r['delivered']:4d}/{r['sent']:<4d} delay p50 "
              f"{r['p50_ms']:8.1f} ms  p99 {r['p99_ms']:8.1f} ms")
    print("Cost: 1 kHz small messages between two nodes of one process")
    for where in ("node thread", "node.spin()", "SingleThreadedExecutor",
                  "MultiThreadedExecutor(1)", "MultiThreadedExecutor(2)"):
        r = cost(where, args.count)
        print(f"  {where:26s} delivered {r['delivered']:5d}  delay p50 {r['p50_us']:6.0f} us  "
              f"p99 {r['p99_us']:6.0f} us")
    return 0


if __name__ == "__main__":
    sys.exit(main())
