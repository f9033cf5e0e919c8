"""Receive a topic's messages as serialized bytes (no decoding: a CPU-only raw subscription)
and keep a window of arrival times and sizes, for ``hz`` and ``bw``."""

from __future__ import annotations

import argparse
import collections
import threading
import time

from .._arguments import absolute_topic_name
from .._graph import GraphCommandError, add_graph_options, graph_node, wait_for_topic

__all__ = ["Window", "add_window_options", "measure"]


class Window:
    """The last ``size`` arrivals (monotonic seconds, bytes)."""

    def __init__(self, size: int) -> None:
        self.times: collections.deque[float] = collections.deque(maxlen=size + 1)
        self.sizes: collections.deque[int] = collections.deque(maxlen=size)
        self.total = 0
        self.lock = threading.Lock()

    def add(self, nbytes: int) -> None:
        with self.lock:
            self.times.append(time.monotonic())
            self.sizes.append(nbytes)
            self.total += 1

    def snapshot(self) -> tuple[list[float], list[int], int]:
        with self.lock:
            return list(self.times), list(self.sizes), self.total


def add_window_options(parser: argparse.ArgumentParser, default_window: int) -> None:
    parser.add_argument("topic_name", type=absolute_topic_name,
                        help="the topic, e.g. /camera/image")
    parser.add_argument("-w", "--window", type=int, default=default_window, metavar="N",
                        help=f"messages in the window (default {default_window})")
    parser.add_argument("--count", type=int, default=0, metavar="N",
                        help="exit after N reports (default 0: until Ctrl-C)")
    add_graph_options(parser)


def measure(args: argparse.Namespace, report) -> int:
    """Subscribe and call ``report(window)`` once a second until Ctrl-C or ``--count``."""
    if args.window < 1 or args.count < 0:
        raise GraphCommandError("--window must be >= 1 and --count >= 0")
    window = Window(args.window)
    with graph_node(args) as node:
        topic, type_name = wait_for_topic(node, args.topic_name)
        node.create_subscription(type_name, topic, lambda data: window.add(len(data)),
                                 depth=100, raw=True)
        reports = 0
        while not args.count or reports < args.count:
            time.sleep(1.0)
            if report(window):
                reports += 1
    return 0
