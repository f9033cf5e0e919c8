"""Stage 2 of the camera pipeline: camera frames, zero-copy into a torch convolution; the
feature map published with the frame's stamp.

Run with ``camera.py`` and ``viewer.py`` (see ``camera.py``); ``python examples/infer.py``.

The subscription accepts ``warp``, so a frame of a camera on this host arrives as the camera's
own memory: ``from_input_image_msg(msg, clone=False)`` is a torch view of it (on the GPU where
the camera drew it), read-only: torch refuses writes into it. The features (the frame averaged
over 8x8 blocks, per channel: a strided ``conv2d``) go out as a
``warp_buffer_msgs/msg/StampedTensor``: upstream's ``ExperimentalTensor`` has no header, so the
wrapper carries the frame's ``header`` (its capture stamp) to the viewer.
"""

from __future__ import annotations

import time

import numpy as np
import torch
import torch.nn.functional as F

from pipeline_common import (
    FEATURES_TOPIC, IMAGE_TOPIC, POOL, expected_pixels, image_phase, node_options, parse_args,
    percentile_ms, ready, run_for, stamp_ns, stop_on_signals, summary, until_interrupted,
)
from buffer_pubsub import Node
from rosidl_buffer.messages import get_message_type
from tensor_conversions import torch as tc

StampedTensor = get_message_type("warp_buffer_msgs/msg/StampedTensor")


class Inference:
    """The image callback: features out, and a count of frames that were not the pattern."""

    def __init__(self, node: Node) -> None:
        self.features = node.create_publisher(StampedTensor, FEATURES_TOPIC, depth=10)
        self.frames = 0
        self.wrong = 0
        self.storage: dict[str, int] = {}  # frames by storage: "warp" when they came zero-copy
        self.latencies_ns: list[int] = []  # capture -> features published
        self.weight: torch.Tensor | None = None

    def on_image(self, msg) -> None:
        image = tc.from_input_image_msg(msg, clone=False)  # (720, 1280, 3) uint8, no copy
        captured = stamp_ns(msg.header)
        if self.weight is None:  # a box filter per channel, on the frames' device
            self.weight = torch.zeros((3, 3, POOL, POOL), device=image.device)
            for channel in range(3):  # (not groups=3: torch's CPU kernel for that is ~10x slower)
                self.weight[channel, channel] = 1.0 / POOL**2
        with torch.inference_mode():
            batch = image.permute(2, 0, 1).unsqueeze(0).float() / 255.0  # NCHW, a new tensor
            features = F.conv2d(batch, self.weight, stride=POOL)[0]  # (3, 90, 160)
        self.frames += 1
        backend = msg.data.get_backend_type()
        self.storage[backend] = self.storage.get(backend, 0) + 1
        row = self.frames % image.shape[0]  # one row a frame, checked on the CPU
        expected = expected_pixels(image_phase(captured), np.array([row]), image.shape[1])[0]
        if not torch.equal(image[row].cpu(), torch.from_numpy(expected)):
            self.wrong += 1
        self.features.publish(StampedTensor(header=msg.header,
                                            tensor=tc.to_tensor_msg(features)))
        self.latencies_ns.append(time.time_ns() - captured)


def main() -> int:
    args = parse_args(__doc__.splitlines()[0])
    stop_on_signals()
    with Node("infer", executor="manual", **node_options(args)) as node:
        inference = Inference(node)
        node.create_subscription("sensor_msgs/msg/Image", IMAGE_TOPIC, inference.on_image,
                                 depth=2, acceptable_buffer_backends="warp")
        with until_interrupted():  # (ready inside: a Ctrl-C right after it still ends well)
            ready("infer")
            node.spin(timeout=run_for(args.duration))  # callbacks run here, on this thread
    summary("infer", frames=inference.frames, wrong=inference.wrong, storage=inference.storage,
            capture_to_features_p50_ms=percentile_ms(inference.latencies_ns, 50))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
