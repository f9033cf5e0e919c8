"""Print a node's subscribers, publishers, service servers and clients and action servers and
clients with their types, as ``ros2 node info`` does: hidden names (a part starting with ``_``)
only with ``--include-hidden``. Services are other nodes' (this transport has none of its own);
actions are found as rcl_action finds them, by their ``<action>/_action/feedback`` topics."""

from __future__ import annotations

import argparse

from .._graph import GraphCommandError, add_graph_options, graph_node, hidden_name

#: rcl_action's marks of an action: its feedback topic and that topic's type suffix
ACTION_FEEDBACK = "/_action/feedback"
FEEDBACK_TYPE_SUFFIX = "_FeedbackMessage"

NamesAndTypes = list[tuple[str, list[str]]]


class UnknownNodeError(GraphCommandError, LookupError):
    """No node of the domain has this name."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("node_name", help="the node's full name, e.g. /camera or /ns/camera")
    add_graph_options(parser)


def actions(topics: NamesAndTypes) -> NamesAndTypes:
    """The actions among a node's topics (published: it serves them; subscribed: it calls
    them), named and typed as ``rcl_action_get_*_names_and_types_by_node``."""
    return [(name[:-len(ACTION_FEEDBACK)],
             [t[:-len(FEEDBACK_TYPE_SUFFIX)] if t.endswith(FEEDBACK_TYPE_SUFFIX) else t
              for t in types])
            for name, types in topics if name.endswith(ACTION_FEEDBACK)]


def run(args: argparse.Namespace) -> int:
    full = args.node_name if args.node_name.startswith("/") else "/" + args.node_name
    namespace, _, name = full.rpartition("/")
    namespace = namespace or "/"
    with graph_node(args) as node:
        if full not in {n.full_name for n in node.get_nodes()}:
            raise UnknownNodeError(f"node {full!r} is not in the graph of domain "
                                   f"{node.domain_id} (see `warp-buffer node list`)")
        subscribed = node.get_subscriber_names_and_types_by_node(name, namespace)
        published = node.get_publisher_names_and_types_by_node(name, namespace)
        servers = node.get_service_names_and_types_by_node(name, namespace)
        clients = node.get_client_names_and_types_by_node(name, namespace)
    print(full)
    for title, names_and_types in (("Subscribers", subscribed), ("Publishers", published),
                                   ("Service Servers", servers), ("Service Clients", clients),
                                   ("Action Servers", actions(published)),
                                   ("Action Clients", actions(subscribed))):
        print(f"  {title}:")
        for entity, types in names_and_types:
            if not hidden_name(entity, args):
                print(f"    {entity}: {', '.join(types)}")
    return 0
