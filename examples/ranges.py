"""A point-cloud pipeline, stage 2: the nearest point of each lidar scan, computed with torch
on zero-copy views of the scan.

Run with ``lidar.py`` (see there); ``python examples/ranges.py``.

``from_input_pointcloud_msg(msg, fields, clone=False)`` gives an ``(N, len(fields))`` strided
view of the points (read-only) when the fields are adjacent float32 columns, as x, y, z are;
on the device the lidar wrote them (its GPU, or the CPU). Every scan is checked against the
rings the lidar draws for its stamp.
"""

from __future__ import annotations

import math
import time

import torch

from pipeline_common import (
    RANGE_M, RING_SPACING_M, SCAN_TOPIC, node_options, parse_args, percentile_ms, ready,
    run_for, scan_rotation, stamp_ns, stop_on_signals, summary, until_interrupted,
)
from buffer_pubsub import Node
from tensor_conversions import torch as tc


class Ranges:
    def __init__(self) -> None:
        self.scans = self.wrong = 0
        self.nearest_m: float | None = None
        self.latencies_ns: list[int] = []

    def on_scan(self, msg) -> None:
        xyz = tc.from_input_pointcloud_msg(msg, ("x", "y", "z"), clone=False)  # (N, 3) view
        ring = tc.from_input_pointcloud_msg(msg, ("intensity",), clone=False)[:, 0]
        distance = torch.linalg.vector_norm(xyz[:, :2], dim=1)  # in the x-y plane
        self.nearest_m = float(distance.min())
        # The lidar's rings, from the stamp: distances by ring, and the first point's azimuth.
        expected = RANGE_M + ring * RING_SPACING_M
        rotation = scan_rotation(stamp_ns(msg.header))
        first = math.atan2(float(xyz[0, 1]), float(xyz[0, 0])) % (2 * math.pi)
        turned = abs((first - rotation + math.pi) % (2 * math.pi) - math.pi)
        ok = bool(torch.allclose(distance, expected, atol=1e-3)) and turned < 1e-3
        self.scans += 1
        self.wrong += not ok
        self.latencies_ns.append(time.time_ns() - stamp_ns(msg.header))


def main() -> int:
    args = parse_args(__doc__.splitlines()[0])
    stop_on_signals()
    ranges = Ranges()
    with Node("ranges", executor="manual", **node_options(args)) as node:
        node.create_subscription("sensor_msgs/msg/PointCloud2", SCAN_TOPIC, ranges.on_scan,
                                 depth=2, acceptable_buffer_backends="warp")
        with until_interrupted():  # (ready inside: a Ctrl-C right after it still ends well)
            ready("ranges")
            node.spin(timeout=run_for(args.duration))
    summary("ranges", scans=ranges.scans, wrong=ranges.wrong, nearest_m=ranges.nearest_m,
            scan_to_result_p50_ms=percentile_ms(ranges.latencies_ns, 50))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
