"""Print the rate a topic's messages arrive at, once a second, as ``ros2 topic hz`` does:
average rate over the last ``--window`` messages, with the min, max and standard deviation of
the intervals. Payloads are not decoded."""

from __future__ import annotations

import argparse
import statistics

from ._window import Window, add_window_options, measure


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_window_options(parser, default_window=10000)


def report(window: Window) -> bool:
    times, _sizes, _total = window.snapshot()
    if len(times) < 2:
        return False
    gaps = [b - a for a, b in zip(times, times[1:])]
    mean = sum(gaps) / len(gaps)
    print(f"average rate: {1 / mean:.3f}\n\tmin: {min(gaps):.3f}s max: {max(gaps):.3f}s "
          f"std dev: {statistics.pstdev(gaps):.5f}s window: {len(gaps) + 1}", flush=True)
    return True


def run(args: argparse.Namespace) -> int:
    return measure(args, report)
