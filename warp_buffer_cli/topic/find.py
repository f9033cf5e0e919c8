"""Print the topics of a type, one per line, as ``ros2 topic find`` does (``-c``: only how
many; nothing, exit 0, when no topic has it). The type is matched by name (``pkg/Name`` or
``pkg/msg/Name``): it need not be installed here, a ROS 2 peer's own types are found too."""

from __future__ import annotations

import argparse

from rosidl_buffer.messages import normalize_type_name

from .._graph import add_graph_options, graph_node, print_names
from .list import topics


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("topic_type", help="the message type, e.g. sensor_msgs/msg/Image")
    parser.add_argument("-c", "--count-topics", action="store_true",
                        help="print only the number of topics")
    add_graph_options(parser)


def run(args: argparse.Namespace) -> int:
    type_name = normalize_type_name(args.topic_type)  # not a type name at all: an error
    with graph_node(args) as node:
        found = sorted(topic for topic, types in topics(node, args).items() if type_name in types)
    return print_names(found, args.count_topics)
