"""Print a topic's type, as ``ros2 topic type`` does (one line per type; exit 1 when no endpoint
of the graph has the topic)."""

from __future__ import annotations

import argparse

from .._arguments import absolute_topic_name
from .._graph import UnknownTopicError, add_graph_options, graph_node
from .list import topics


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("topic_name", type=absolute_topic_name,
                        help="the topic, e.g. /camera/image")
    add_graph_options(parser)


def run(args: argparse.Namespace) -> int:
    with graph_node(args) as node:
        types = topics(node, args).get(args.topic_name)
        if not types:
            raise UnknownTopicError(f"topic {args.topic_name!r} is not in the graph of domain "
                                    f"{node.domain_id} (see `warp-buffer topic list`)")
    for type_name in sorted(types):
        print(type_name)
    return 0
