"""Stage 3 of the camera pipeline: a CPU viewer of the features, which also checks frames.

Run with ``camera.py`` and ``infer.py`` (see ``camera.py``); ``python examples/viewer.py``
(``--no-images`` leaves the frames alone: then only the small feature maps reach this process).

Two callbacks of different speeds on one node: the features (small, 30 a second) and a frame
check (2.7 MB frames, slow). A node runs its callbacks one at a time, so a slow frame check
would hold up every feature map behind it. Here the node is added to a ``MultiThreadedExecutor``
and the frame check has a callback group of its own: the features never wait for it
(docs/executors.md). The capture stamp arrives in the features' header, so the latency printed
is camera to viewer; ``MessageInfo`` adds when ``infer.py`` published them.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from pipeline_common import (
    FEATURES_TOPIC, IMAGE_TOPIC, POOL, expected_feature_rows, expected_pixels, image_phase,
    node_options, parse_args, percentile_ms, ready, stamp_ns, stop_on_signals, summary,
    until_interrupted,
)
from buffer_pubsub import Node
from buffer_pubsub.callback_groups import MutuallyExclusiveCallbackGroup
from buffer_pubsub.executors import MultiThreadedExecutor
from tensor_conversions import numpy as tn

#: Pixels of a frame the frame check compares with the pattern.
CHECKED_PIXELS = 200_000


class Viewer:
    def __init__(self) -> None:
        self.lock = threading.Lock()  # the two callbacks may run at once
        self.features = self.frames = self.wrong_features = self.wrong_frames = 0
        self.latencies_ns: list[int] = []  # capture -> features here
        self.hop_ns: list[int] = []  # infer's publish -> features here
        self.rng = np.random.default_rng(0)

    def on_features(self, msg, info) -> None:
        received = time.time_ns()
        captured = stamp_ns(msg.header)
        features = tn.from_input_tensor_msg(msg.tensor, clone=False)  # (3, 90, 160) float32
        rows = np.arange(0, features.shape[1], 15)  # a few rows of the map against the pattern
        expected = expected_feature_rows(image_phase(captured), rows, features.shape[2] * POOL)
        ok = np.allclose(features[:, rows], expected, atol=1e-5)
        with self.lock:
            self.features += 1
            self.wrong_features += not ok
            self.latencies_ns.append(received - captured)
            self.hop_ns.append(info.received_timestamp_ns - info.source_timestamp_ns)

    def on_image(self, msg) -> None:
        image = tn.from_input_image_msg(msg, clone=False)  # (720, 1280, 3) uint8 on the CPU
        rows = self.rng.integers(0, image.shape[0], CHECKED_PIXELS // image.shape[1])
        ok = np.array_equal(image[rows], expected_pixels(
            image_phase(stamp_ns(msg.header)), rows, image.shape[1]))
        with self.lock:
            self.frames += 1
            self.wrong_frames += not ok

    def report(self) -> dict:
        with self.lock:
            return {"features": self.features, "wrong_features": self.wrong_features,
                    "frames_checked": self.frames, "wrong_frames": self.wrong_frames,
                    "camera_to_viewer_p50_ms": percentile_ms(self.latencies_ns, 50),
                    "camera_to_viewer_p99_ms": percentile_ms(self.latencies_ns, 99),
                    "infer_to_viewer_p50_ms": percentile_ms(self.hop_ns, 50)}


def main() -> int:
    args = parse_args(__doc__.splitlines()[0],
                      no_images=(bool, False, "do not subscribe to the frames"),
                      image_rate=(float, 5.0, "frames a second to check (the camera "
                                              "serializes no more than that for us)"))
    stop_on_signals()
    viewer = Viewer()
    with Node("viewer", executor="manual", **node_options(args)) as node, \
            MultiThreadedExecutor(num_threads=2) as executor:
        node.create_subscription("warp_buffer_msgs/msg/StampedTensor", FEATURES_TOPIC,
                                 viewer.on_features, depth=10, with_info=True)
        if not args.no_images:
            # A few frames a second are enough to check: max_rate makes the camera send (and
            # serialize to CPU bytes) only those, not all 30 a second.
            node.create_subscription("sensor_msgs/msg/Image", IMAGE_TOPIC, viewer.on_image,
                                     depth=1, callback_group=MutuallyExclusiveCallbackGroup(),
                                     max_rate=args.image_rate)
        executor.add_node(node)
        if args.duration > 0:
            stop = threading.Timer(args.duration, executor.shutdown)
            stop.daemon = True
            stop.start()
        with until_interrupted():  # (ready inside: a Ctrl-C right after it still ends well)
            ready("viewer")
            executor.spin()  # until executor.shutdown() (the duration is over), or Ctrl-C
    summary("viewer", **viewer.report())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
