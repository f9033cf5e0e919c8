"""A point-cloud pipeline, stage 1: a lidar publishing ``sensor_msgs/msg/PointCloud2`` scans
(x, y, z, intensity as float32) at 10 Hz, written by a Warp kernel into the message's storage.

Run both stages (same host; ``--device cuda:0`` where there is a GPU)::

    python examples/ranges.py
    python examples/lidar.py

A scan is 32 rings of 2048 points (1 MiB), loaned from the publisher and filled in place through
a ``warp_buffer`` write handle; ``ranges.py`` maps it with no copy. ``header.stamp`` is the scan
time.
"""

from __future__ import annotations

import functools
import time

import warp as wp

import pipeline_kernels
from pipeline_common import (
    AZIMUTHS, RANGE_M, RING_SPACING_M, RINGS, SCAN_TOPIC, default_device, node_options, paced,
    parse_args, scan_rotation, stamp, stop_on_signals, summary, until_interrupted,
)
import warp_buffer
from buffer_pubsub import Node
from rosidl_buffer.messages import get_message_type

PointCloud2 = get_message_type("sensor_msgs/msg/PointCloud2")
PointField = get_message_type("sensor_msgs/msg/PointField")
POINTS = RINGS * AZIMUTHS
POINT_BYTES = 16  # four float32


def new_scan(device: str):
    """An empty scan whose storage is Warp memory on ``device`` (the loan's factory)."""
    fields = [PointField(name=name, offset=4 * i, datatype=PointField.FLOAT32, count=1)
              for i, name in enumerate(("x", "y", "z", "intensity"))]
    return PointCloud2(height=1, width=POINTS, fields=fields, is_bigendian=False,
                       point_step=POINT_BYTES, row_step=POINT_BYTES * POINTS, is_dense=True,
                       data=warp_buffer.allocate_buffer(POINT_BYTES * POINTS, device=device))


def main() -> int:
    args = parse_args(__doc__.splitlines()[0],
                      rate=(float, 10.0, "scans per second"),
                      device=(str, None, "Warp device of the scans (default: cuda:0, else cpu)"),
                      subscribers=(int, 1, "subscriptions to wait for first (up to 30 s)"))
    stop_on_signals()
    device = args.device or default_device()
    factory = functools.partial(new_scan, device)  # once: the loan pool is keyed by it
    published = 0
    # Compiled before the first frame, not at its launch (seconds on a cold kernel cache).
    wp.load_module(pipeline_kernels, device=device)
    with Node("lidar", **node_options(args)) as node:
        scans = node.create_publisher(PointCloud2, SCAN_TOPIC, depth=2)
        scans.wait_for_subscriptions(args.subscribers, timeout=30)
        print(f"lidar: {POINTS} points at {args.rate:g} Hz on {device}", flush=True)
        with until_interrupted():
            for _ in paced(args.rate, args.duration):
                with scans.loan(factory) as scan:  # published at the end of the block
                    started = time.time_ns()
                    stamp(scan.header, started)
                    scan.header.frame_id = "lidar"
                    with warp_buffer.from_output_buffer(scan.data) as out:
                        wp.launch(pipeline_kernels.scan_rings, dim=POINTS, device=device,
                                  inputs=[out.view(wp.vec4f), AZIMUTHS, scan_rotation(started),
                                          RANGE_M, RING_SPACING_M])
                published += 1
    summary("lidar", published=published, points=POINTS, device=device)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
