"""Print the messages of a topic as ``ros2 topic echo`` does: YAML documents separated by
``---`` (``--csv``: one line each), ``uint8[]`` buffers summarised as backend, size and first
bytes. It subscribes with the CPU backend, so it changes no route but its own; ``--backend warp``
takes warp buffers zero-copy where the publisher can serve them."""

from __future__ import annotations

import argparse
import queue
import sys

from .._arguments import absolute_topic_name
from .._graph import (GraphCommandError, add_graph_options, graph_node, latched_durability,
                      wait_for_topic)
from ._fields import csv_line, pick, to_plain, yaml_lines


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("topic_name", type=absolute_topic_name,
                        help="the topic, e.g. /camera/image")
    parser.add_argument("message_type", nargs="?", default=None,
                        help="its type, e.g. sensor_msgs/msg/Image (as ros2 topic echo takes "
                             "it: subscribe at once, without waiting to discover the topic)")
    parser.add_argument("--once", action="store_true", help="print the first message and exit")
    parser.add_argument("--csv", action="store_true", help="one comma-separated line a message")
    parser.add_argument("--field", default="", help="print only this field, e.g. header.stamp")
    parser.add_argument("--truncate-length", type=int, default=128, metavar="N",
                        help="longest string or array printed (default 128, 0: no limit)")
    parser.add_argument("--backend", choices=["cpu", "warp"], default="cpu",
                        help="the buffer backend to accept (default cpu)")
    parser.add_argument("--count", type=int, default=0, metavar="N",
                        help="exit after N messages (default 0: until Ctrl-C)")
    add_graph_options(parser)


def run(args: argparse.Namespace) -> int:
    if args.truncate_length < 0 or args.count < 0:
        raise GraphCommandError("--truncate-length and --count must be >= 0")
    wanted = 1 if args.once else args.count
    inbox: queue.SimpleQueue = queue.SimpleQueue()
    with graph_node(args) as node:
        if args.message_type is None:
            topic, type_name = wait_for_topic(node, args.topic_name)
        else:
            from rosidl_buffer.messages import get_message_type

            # (a name no message has: UnknownMessageTypeError, one line from main)
            topic, type_name = args.topic_name, get_message_type(args.message_type).__msgtype__
        durability = latched_durability(node, topic)
        node.create_subscription(
            type_name, topic, lambda msg: inbox.put(to_plain(msg, args.truncate_length)),
            depth=100, durability=durability, acceptable_buffer_backends=(
                "cpu" if durability == "transient_local" else args.backend))
        printed = 0
        while not wanted or printed < wanted:
            try:
                plain = inbox.get(timeout=0.2)
            except queue.Empty:
                continue
            if args.field:
                try:
                    plain = pick(plain, args.field)
                except KeyError as exc:
                    raise GraphCommandError(
                        f"{type_name} has no field {args.field!r} (no {exc.args[0]!r})") from None
            if args.csv:
                print(csv_line(plain))
            else:
                print("\n".join(yaml_lines(plain)))
                print("---")
            sys.stdout.flush()
            printed += 1
    return 0
