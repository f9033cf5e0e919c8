"""Print a node's subscriptions and publishers with their types, as ``ros2 node info`` does
(services and actions: none, this transport has no services)."""

from __future__ import annotations

import argparse

from .._graph import GraphCommandError, add_graph_options, graph_node


class UnknownNodeError(GraphCommandError, LookupError):
    """No node of the domain has this name."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("node_name", help="the node's full name, e.g. /camera or /ns/camera")
    add_graph_options(parser)


def run(args: argparse.Namespace) -> int:
    full = args.node_name if args.node_name.startswith("/") else "/" + args.node_name
    namespace, _, name = full.rpartition("/")
    with graph_node(args) as node:
        if full not in {n.full_name for n in node.get_nodes()}:
            raise UnknownNodeError(f"node {full!r} is not in the graph of domain "
                                   f"{node.domain_id} (see `warp-buffer node list`)")
        endpoints = node.get_endpoints_by_node(name, namespace or "/")
    print(full)
    for title, kind in (("Subscribers", "SUBSCRIPTION"), ("Publishers", "PUBLISHER")):
        print(f"  {title}:")
        lines = sorted({f"    {e.topic_name}: {e.topic_type}" for e in endpoints
                        if e.endpoint_type.value == kind})
        for line in lines:
            print(line)
    for title in ("Service Servers", "Service Clients", "Action Servers", "Action Clients"):
        print(f"  {title}:")
    return 0
