"""Child programs for the ``warp-buffer bag`` tests (tests/test_bag_cli.py).

Run as ``python -m tests._bag_helpers <role> ...`` from the repository root. Protocol on stdout:
``READY`` once its endpoints exist, then one ``RESULT <json>`` line.

- ``publish``: waits for a subscription on each topic, then publishes ``--count`` messages
  (keep-all) on two topics at ``--rate``: ``<topic>`` ExperimentalTensor frames whose bytes follow
  :func:`frame_bytes` (``--backend`` warp or cpu storage) and ``<topic>_text`` std_msgs/String;
  then waits for ``stop`` on stdin (warp frames stay alive until their readers are done).
  ``--custom`` publishes one type only this process knows instead.
- ``listen``: subscribes to the same two topics (``--accept`` warp or cpu) and, after ``--count``
  messages per topic or ``stop`` on stdin, reports each message: topic, publish time (the
  source timestamp, s: when the player sent it), the backend of its buffer, and its CDR (hex).
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from typing import Any

import numpy as np

from tests._pubsub_helpers import _emit, _stdin_stop

TENSOR = "tensor_msgs/msg/ExperimentalTensor"
STRING = "std_msgs/msg/String"
CUSTOM = "bag_test_msgs/msg/Custom"
CUSTOM_DEFINITION = "int32 value\nstring label\n"


def frame_bytes(index: int, size: int) -> np.ndarray:
    """The payload of frame ``index``: a pattern no two frames share at the same offset."""
    k = np.arange(size, dtype=np.uint32)
    return ((k * 7 + index * 13) % 251).astype(np.uint8)


def expected_messages(index: int, size: int) -> tuple[Any, Any]:
    """Frame ``index`` as published (CPU storage: its CDR is the same whatever the backend)."""
    from rosidl_buffer.messages import get_message_type

    data = frame_bytes(index, size)
    tensor = get_message_type(TENSOR)(dtype_code=1, dtype_bits=8, dtype_lanes=1,
                                      shape=[size], data=data)
    text = get_message_type(STRING)(data=f"frame {index}")
    return tensor, text


def run_publish(args: argparse.Namespace) -> int:
    from buffer_pubsub import Node
    from rosidl_buffer.messages import get_message_type, register_message_definitions

    with Node("bag_test_publisher", domain_id=args.domain) as node:
        if args.custom:
            register_message_definitions({CUSTOM: CUSTOM_DEFINITION})
            custom = node.create_publisher(CUSTOM, args.topic, depth=args.count)
            _emit("READY")
            custom.wait_for_subscriptions(1, timeout=args.timeout)
            for index in range(args.count):
                custom.publish(get_message_type(CUSTOM)(value=index, label="x"))
                time.sleep(1.0 / args.rate)
            _emit("RESULT " + json.dumps({"published": args.count}))
            _stdin_stop(args.timeout).wait()
            return 0
        # Keep-all (Zenoh's BLOCK): a keep-last publisher's sample may be dropped by Zenoh on a
        # busy machine, and the tests compare every message.
        tensors = node.create_publisher(TENSOR, args.topic, depth=args.count,
                                        history="keep_all")
        texts = node.create_publisher(STRING, args.topic + "_text", depth=args.count,
                                      history="keep_all")
        _emit("READY")
        matched = (tensors.wait_for_subscriptions(1, timeout=args.timeout)
                   and texts.wait_for_subscriptions(1, timeout=args.timeout))
        time.sleep(0.3)  # let the subscriber's backend negotiation settle: one route from here
        kept = []
        for index in range(args.count):
            tensor, text = expected_messages(index, args.size)
            if args.backend == "warp":
                import warp_buffer

                buffer = warp_buffer.allocate_buffer(args.size, device="cpu")
                with warp_buffer.from_output_buffer(buffer) as out:
                    warp_buffer.to_buffer(tensor.data.numpy(writable=False), out)
                tensor.data = buffer
            tensors.publish(tensor)
            texts.publish(text)
            kept.append(tensor)
            time.sleep(1.0 / args.rate)
        _emit("RESULT " + json.dumps({"published": args.count, "matched": bool(matched),
                                      "backend": kept[-1].data.get_backend_type()}))
        _stdin_stop(args.timeout).wait()
    return 0


def run_listen(args: argparse.Namespace) -> int:
    from buffer_pubsub import Node
    from rosidl_buffer.messages import serialize_message

    got: list[dict[str, Any]] = []
    lock = threading.Lock()

    def on_message(topic: str) -> Any:
        def callback(msg: Any, info: Any) -> None:
            backend = msg.data.get_backend_type() if hasattr(msg.data, "get_backend_type") \
                else ""
            cdr = bytes(serialize_message(msg)).hex()
            with lock:
                got.append({"topic": topic, "t": info.source_timestamp_ns / 1e9,
                            "backend": backend, "cdr": cdr})

        return callback

    with Node("bag_test_listener", domain_id=args.domain) as node:
        node.create_subscription(TENSOR, args.topic, on_message(args.topic), depth=1000,
                                 acceptable_buffer_backends=args.accept, with_info=True)
        node.create_subscription(STRING, args.topic + "_text", on_message(args.topic + "_text"),
                                 depth=1000, with_info=True)
        _emit("READY")
        stop = _stdin_stop(args.timeout)
        while not stop.wait(0.05):
            with lock:
                if len(got) >= 2 * args.count:
                    break
    _emit("RESULT " + json.dumps({"messages": got}))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="tests._bag_helpers")
    parser.add_argument("role", choices=["publish", "listen"])
    parser.add_argument("--domain", type=int, required=True)
    parser.add_argument("--topic", required=True)
    parser.add_argument("--count", type=int, default=10)
    parser.add_argument("--rate", type=float, default=20.0)
    parser.add_argument("--size", type=int, default=4096)
    parser.add_argument("--backend", choices=["warp", "cpu"], default="cpu")
    parser.add_argument("--accept", default="cpu")
    parser.add_argument("--custom", action="store_true")
    parser.add_argument("--timeout", type=float, default=60.0)
    args = parser.parse_args(argv)
    from warp_buffer import init_warp

    init_warp()  # quiet Warp: stdout is the protocol
    if args.role == "publish":
        return run_publish(args)
    return run_listen(args)


if __name__ == "__main__":
    sys.exit(main())
