"""Print a topic's type, as ``ros2 topic type`` does (one line per type; exit 1 when no endpoint
of the graph has the topic)."""

from __future__ import annotations

import argparse

from .._arguments import absolute_topic_name
from .._graph import add_graph_options, graph_node, unknown_topic
from .list import topics


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("topic_name", type=absolute_topic_name,
                        help="the topic, e.g. /camera/image")
    add_graph_options(parser)


def run(args: argparse.Namespace) -> int:
    with graph_node(args) as node:
        types = topics(node, args).get(args.topic_name)
        if not types:
            raise unknown_topic(node, args.topic_name)
    for type_name in sorted(types):
        print(type_name)
    return 0
