"""List the nodes of the domain by full name, one per line, as ``ros2 node list`` does."""

from __future__ import annotations

import argparse
import sys

from .._graph import add_graph_options, graph_node, hidden, print_names


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-c", "--count-nodes", action="store_true",
                        help="print only the number of nodes")
    add_graph_options(parser)


def run(args: argparse.Namespace) -> int:
    with graph_node(args) as node:
        names = sorted(n.full_name for n in node.get_nodes() if not hidden(n.name, args))
    if len(set(names)) < len(names):  # (ros2 node list's warning, on stderr)
        print("WARNING: Be aware that there are nodes in the graph that share an exact name, "
              "which can have unintended side effects.", file=sys.stderr)
    return print_names(names, args.count_nodes)
