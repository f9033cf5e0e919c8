"""What the example stages share: their command line, stamps, and the test pattern every stage
can check.

The camera draws a test pattern whose phase is its capture time (``header.stamp``), and the
lidar scans rings whose rotation is too, so every later stage recomputes what it should have got
from the stamp alone and counts what differs. Replace them with your own data; keep the
stamps.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import math
import signal
import time
from collections.abc import Iterator
from typing import Any

import numpy as np

IMAGE_TOPIC = "camera/image"
FEATURES_TOPIC = "camera/features"
SCAN_TOPIC = "lidar/points"
#: The feature map is the image averaged over POOL x POOL pixel blocks, per channel.
POOL = 8
#: Lidar scan: RINGS rings of AZIMUTHS points, ring r at RANGE_M + r * RING_SPACING_M metres.
RINGS, AZIMUTHS = 32, 2048
RANGE_M, RING_SPACING_M = 4.0, 0.25


def parse_args(description: str, **extra: Any) -> argparse.Namespace:
    """The options every stage takes, plus ``extra`` (name -> (type, default, help))."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--duration", type=float, default=0.0,
                        help="seconds to run (default: until Ctrl-C)")
    parser.add_argument("--domain", type=int, default=None,
                        help="ROS domain id (default: env ROS_DOMAIN_ID, else 0)")
    parser.add_argument("--namespace", default="",
                        help="node namespace: the topics are relative to it")
    parser.add_argument("--router", default=None,
                        help="Zenoh router endpoint to connect through, e.g. tcp/10.0.0.1:7447 "
                             "(see `warp-buffer router`); default: peers of this host")
    for name, (kind, default, text) in extra.items():
        flag = f"--{name.replace('_', '-')}"
        if kind is bool:
            parser.add_argument(flag, action="store_true", help=text)
        else:
            parser.add_argument(flag, type=kind, default=default, help=text)
    return parser.parse_args()


def stop_on_signals() -> None:
    """Stop on Ctrl-C and on SIGTERM (``kill``, systemd, docker) alike: KeyboardInterrupt in
    the main thread, so the stage closes its node and prints its summary. SIGINT too: a stage
    started from a background job (``&``, nohup, a script) inherits it ignored."""
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.default_int_handler)


def node_options(args: argparse.Namespace) -> dict[str, Any]:
    """The ``Node`` keyword arguments the command line chose."""
    return {"namespace": args.namespace, "domain_id": args.domain, "router": args.router}


def default_device() -> str:
    """Warp's first GPU if there is one, else its cpu device."""
    import warp as wp

    return "cuda:0" if wp.get_cuda_device_count() else "cpu"


# -- stamps -------------------------------------------------------------------------------------
def stamp(header: Any, nanoseconds: int) -> None:
    """Write ``nanoseconds`` since the epoch into ``header.stamp``."""
    header.stamp.sec, header.stamp.nanosec = divmod(nanoseconds, 1_000_000_000)


def stamp_ns(header: Any) -> int:
    """``header.stamp`` in nanoseconds since the epoch."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


# -- the test pattern ---------------------------------------------------------------------------
def image_phase(nanoseconds: int) -> int:
    """The pattern's phase for a frame captured at ``nanoseconds``: it moves once a ms."""
    return (nanoseconds // 1_000_000) % 256


def expected_pixels(phase: int, rows: np.ndarray, width: int) -> np.ndarray:
    """The camera's pattern on ``rows``: ``(len(rows), width, 3)`` uint8, value
    ``(y + x + 64 * channel + phase) % 256`` (what ``draw_test_pattern`` draws)."""
    y = rows.reshape(-1, 1, 1)
    x = np.arange(width).reshape(1, -1, 1)
    channel = np.arange(3).reshape(1, 1, 3)
    return ((y + x + 64 * channel + phase) % 256).astype(np.uint8)


def expected_feature_rows(phase: int, feature_rows: np.ndarray, width: int) -> np.ndarray:
    """Rows ``feature_rows`` of the feature map the inference stage computes from the pattern:
    ``(3, len(feature_rows), width // POOL)`` float32, each the mean of a block / 255."""
    image_rows = (feature_rows.reshape(-1, 1) * POOL + np.arange(POOL)).reshape(-1)
    pixels = expected_pixels(phase, image_rows, width).astype(np.float32) / 255.0
    blocks = pixels.reshape(len(feature_rows), POOL, width // POOL, POOL, 3)
    return blocks.mean(axis=(1, 3)).transpose(2, 0, 1)


def scan_rotation(nanoseconds: int) -> float:
    """The lidar's azimuth offset (radians) for a scan started at ``nanoseconds``."""
    return (nanoseconds // 1_000_000) % 1000 * 2 * math.pi / 1000


# -- running ------------------------------------------------------------------------------------
def run_for(duration: float) -> float | None:
    """``--duration`` as a spin timeout: None (no limit) for 0."""
    return duration if duration > 0 else None


def paced(rate: float, duration: float) -> Iterator[int]:
    """Frame numbers at ``rate`` a second, for ``duration`` seconds (0: for ever)."""
    end = time.monotonic() + duration if duration > 0 else math.inf
    due = time.monotonic()
    for number in itertools.count():
        if time.monotonic() >= end:
            return
        yield number
        due += 1.0 / rate
        time.sleep(max(0.0, due - time.monotonic()))


@contextlib.contextmanager
def until_interrupted() -> Iterator[None]:
    """Run the block until it ends or Ctrl-C (or SIGTERM, see :func:`stop_on_signals`)."""
    try:
        yield
    except KeyboardInterrupt:
        pass


# -- reporting ----------------------------------------------------------------------------------

def percentile_ms(values_ns: list[int], q: float) -> float | None:
    """The ``q`` percentile of ``values_ns``, in milliseconds (None when empty)."""
    if not values_ns:
        return None
    return round(float(np.percentile(np.asarray(values_ns), q)) / 1e6, 3)


def summary(stage: str, **figures: Any) -> None:
    """Print the stage's last line: ``<stage> summary {json}`` (also what the tests read)."""
    print(f"{stage} summary {json.dumps(figures)}", flush=True)


def ready(stage: str, detail: str = "") -> None:
    """Say the stage's endpoints exist (its subscriptions can receive from now on)."""
    print(f"{stage} ready {detail}".rstrip(), flush=True)
