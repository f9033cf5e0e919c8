"""Print the bandwidth a topic uses, once a second, as ``ros2 topic bw`` does: bytes per second
over the last ``--window`` messages and their mean, min and max serialized size (buffers as CPU
bytes: it subscribes with the CPU backend). Payloads are not decoded."""

from __future__ import annotations

import argparse

from ._window import Window, add_window_options, measure


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_window_options(parser, default_window=100)


def human(nbytes: float) -> str:
    for unit in ("B", "KB", "MB"):
        if nbytes < 1000:
            return f"{nbytes:.2f} {unit}"
        nbytes /= 1000
    return f"{nbytes:.2f} GB"


def report(window: Window) -> bool:
    times, sizes, _total = window.snapshot()
    if len(times) < 2:
        return False
    span = times[-1] - times[0]
    counted = sizes[-(len(times) - 1):]  # the bytes that arrived within the span
    rate = sum(counted) / span if span > 0 else 0.0
    print(f"{human(rate)}/s from {len(sizes)} messages\n\tMessage size mean: "
          f"{human(sum(sizes) / len(sizes))} min: {human(min(sizes))} max: {human(max(sizes))}",
          flush=True)
    return True


def run(args: argparse.Namespace) -> int:
    return measure(args, report)
