"""A slow subscriber child: its callback blocks on the first frame until the parent says
``go`` (one line on stdin), then counts; ``stop`` (a second line) prints its RESULT and exits.

Run as ``python -m tests._slow_child slow --domain D --topic T --depth N`` (see
tests/test_pubsub_holds.py).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading

from tests._pubsub_helpers import TENSOR, check_frame


def _emit(line: str) -> None:
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("role", choices=["slow"])
    parser.add_argument("--domain", type=int, required=True)
    parser.add_argument("--topic", required=True)
    parser.add_argument("--depth", type=int, default=1)
    args = parser.parse_args(argv)
    from buffer_pubsub import Node

    go, stop = threading.Event(), threading.Event()

    def watch() -> None:
        sys.stdin.readline()
        go.set()
        sys.stdin.readline()
        stop.set()

    threading.Thread(target=watch, daemon=True).start()
    seen: list[int] = []

    def on_msg(msg) -> None:
        seen.append(check_frame(msg)["index"])
        if len(seen) == 1:
            _emit("BLOCKED")
            go.wait(30)

    with Node(f"slow_{os.getpid()}", domain_id=args.domain) as node:
        sub = node.create_subscription(TENSOR, args.topic, on_msg, depth=args.depth,
                                       acceptable_buffer_backends="warp")
        _emit("READY")
        stop.wait(60)
        counters = sub.counters
        _emit("RESULT " + json.dumps({"seen": seen, "dropped": counters.dropped,
                                      "errors": counters.errors, "lost": counters.lost}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
