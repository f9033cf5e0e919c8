"""Stage 1 of the camera pipeline: a 720x1280 rgb8 camera at 30 Hz, drawn by a Warp kernel
straight into loaned messages.

Run the three stages in three terminals (same host; ``--device cuda:0`` where there is a GPU)::

    python examples/infer.py
    python examples/viewer.py
    python examples/camera.py --subscribers 2

Each frame is a ``sensor_msgs/msg/Image`` loaned from the publisher (``pub.loan(...)``: the
message's warp storage is filled in place, published when the ``with`` block ends). The
subscription of ``infer.py`` accepts ``warp``: on this host it maps the frame with no copy.
``header.stamp`` is the capture time; it travels on to the features (see ``infer.py``).
Across hosts, add ``--router tcp/<router host>:7447`` to every stage (docs/examples.md).
"""

from __future__ import annotations

import functools
import time

import warp as wp

import pipeline_kernels
from pipeline_common import (
    IMAGE_TOPIC, default_device, image_phase, node_options, paced, parse_args, stamp,
    stop_on_signals, summary, until_interrupted,
)
from buffer_pubsub import Node
from tensor_conversions import warp as tw

HEIGHT, WIDTH = 720, 1280


def main() -> int:
    args = parse_args(__doc__.splitlines()[0],
                      rate=(float, 30.0, "frames per second"),
                      device=(str, None, "Warp device of the frames (default: cuda:0, else cpu)"),
                      subscribers=(int, 1, "image subscriptions to wait for before the first "
                                           "frame (up to 30 s)"))
    stop_on_signals()
    device = args.device or default_device()
    # Made once, outside the loop: every loan then draws from one pool (keyed by the factory).
    new_frame = functools.partial(tw.allocate_image_msg, HEIGHT, WIDTH, "rgb8",
                                  backend="warp", device=device)
    published = 0
    # Compiled before the first frame, not at its launch (seconds on a cold kernel cache).
    wp.load_module(pipeline_kernels, device=device)
    with Node("camera", **node_options(args)) as node:
        images = node.create_publisher("sensor_msgs/msg/Image", IMAGE_TOPIC, depth=2)
        matched = images.wait_for_subscriptions(args.subscribers, timeout=30)
        print(f"camera: {HEIGHT}x{WIDTH} rgb8 at {args.rate:g} Hz on {device}; "
              f"{'subscribers matched' if matched else 'no subscriber yet'}", flush=True)
        with until_interrupted():
            for _ in paced(args.rate, args.duration):
                with images.loan(new_frame) as frame:  # published at the end of the block
                    captured = time.time_ns()
                    stamp(frame.header, captured)
                    frame.header.frame_id = "camera"
                    wp.launch(pipeline_kernels.draw_test_pattern, dim=(HEIGHT, WIDTH),
                              inputs=[tw.from_output_image_msg(frame), image_phase(captured)],
                              device=device)
                published += 1
    summary("camera", published=published, device=device)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
