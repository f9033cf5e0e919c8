"""A child for the introspection CLI tests: ``python -m tests._graph_talker talker|viewer
--domain D --topic T [--rate HZ]``. ``talker`` (node ``/talker``) publishes Images at a steady
rate (absolute schedule), frame_id ``talker/<index>``; ``viewer`` (node ``/robot/viewer``)
subscribes accepting warp. Prints ``READY`` once its endpoint exists, runs until stdin closes."""

from __future__ import annotations

import argparse
import sys
import threading
import time

import numpy as np


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("role", choices=["talker", "viewer"])
    parser.add_argument("--domain", type=int, required=True)
    parser.add_argument("--topic", required=True)
    parser.add_argument("--rate", type=float, default=20.0)
    args = parser.parse_args()
    from buffer_pubsub import Node
    from rosidl_buffer.messages import get_message_type

    image = get_message_type("sensor_msgs/msg/Image")
    stop = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.readline(), stop.set()), daemon=True).start()
    if args.role == "viewer":
        with Node("viewer", namespace="/robot", domain_id=args.domain) as node:
            node.create_subscription(image, args.topic, lambda m: None,
                                     acceptable_buffer_backends="warp")
            print("READY", flush=True)
            stop.wait(120)
        return 0
    with Node("talker", domain_id=args.domain) as node:
        pub = node.create_publisher(image, args.topic)
        print("READY", flush=True)
        period, start, index = 1.0 / args.rate, time.monotonic(), 0
        while not stop.is_set() and index < args.rate * 120:
            msg = image(height=2, width=4, encoding="mono8", step=4,
                        data=np.arange(8, dtype=np.uint8) + index % 200)
            msg.header.frame_id = f"talker/{index}"
            pub.publish(msg)
            index += 1
            stop.wait(max(0.0, start + index * period - time.monotonic()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
