"""Print a topic's type and how many publishers and subscriptions it has, as ``ros2 topic info``
does; ``-v`` lists every endpoint: node, type and hash, gid, QoS, the buffer backends it
advertises ("Buffer backends:", as rmw_zenoh 0.10.5 advertises them) and, for publishers of
ours, the route each subscription takes now and why (in process, the same-host lane,
descriptors on Zenoh, CPU bytes)."""

from __future__ import annotations

import argparse
from typing import Any

from .._arguments import absolute_topic_name
from .._graph import add_graph_options, graph_node, hidden, resolve_topic, routes_by_publisher


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("topic_name", type=absolute_topic_name,
                        help="the topic, e.g. /camera/image")
    parser.add_argument("-v", "--verbose", action="store_true", dest="detailed",
                        help="every endpoint with its QoS, backends and routes")
    add_graph_options(parser)


def format_gid(gid: bytes) -> str:
    """rclpy's spelling: dot-separated hex bytes."""
    return ".".join(f"{b:02x}" for b in gid)


def _duration(value: tuple[int, int]) -> str:
    from buffer_pubsub.wire import INFINITE

    return "Infinite" if tuple(value) == INFINITE else f"{value[0] * 10**9 + value[1]} nanoseconds"


_RELIABILITY = {0: "SYSTEM_DEFAULT", 1: "RELIABLE", 2: "BEST_EFFORT", 3: "UNKNOWN",
                4: "BEST_AVAILABLE"}
_DURABILITY = {0: "SYSTEM_DEFAULT", 1: "TRANSIENT_LOCAL", 2: "VOLATILE", 3: "UNKNOWN",
               4: "BEST_AVAILABLE"}
_HISTORY = {0: "SYSTEM_DEFAULT", 1: "KEEP_LAST", 2: "KEEP_ALL", 3: "UNKNOWN"}
_LIVELINESS = {0: "SYSTEM_DEFAULT", 1: "AUTOMATIC", 3: "MANUAL_BY_TOPIC", 4: "UNKNOWN",
               5: "BEST_AVAILABLE"}


def describe(info: Any, names: dict[str, str], routes: dict[str, list[dict[str, Any]]]
             ) -> list[str]:
    """The lines ``-v`` prints for one endpoint."""
    qos = info.qos_profile
    backends = ("(none advertised)" if info.backends is None else
                ", ".join(f"{name} ({meta})" if meta else name
                          for name, meta in sorted(info.backends.items())))
    lines = [
        f"Node name: {info.node_name}",
        f"Node namespace: {info.node_namespace}",
        f"Topic type: {info.topic_type}",
        f"Topic type hash: {info.topic_type_hash}",
        f"Endpoint type: {info.endpoint_type.value}",
        f"GID: {format_gid(info.endpoint_gid)}",
        "QoS profile:",
        f"  Reliability: {_RELIABILITY.get(qos.reliability, qos.reliability)}",
        f"  History (Depth): {_HISTORY.get(qos.history, qos.history)} ({qos.depth})",
        f"  Durability: {_DURABILITY.get(qos.durability, qos.durability)}",
        f"  Lifespan: {_duration(qos.lifespan)}",
        f"  Deadline: {_duration(qos.deadline)}",
        f"  Liveliness: {_LIVELINESS.get(qos.liveliness, qos.liveliness)}",
        f"  Liveliness lease duration: {_duration(qos.liveliness_lease)}",
        f"Buffer backends: {backends}",
    ]
    if info.locality is not None:
        lines.append(f"Implementation: warp-buffer (host {info.locality.host_id}, "
                     f"pid {info.locality.process_id})")
    else:
        lines.append("Implementation: another ROS 2 node (rmw_zenoh)")
    own = routes.get(info.endpoint_gid.hex())
    if own is not None:
        lines.append("Routes:" if own else "Routes: (no subscription matched)")
        for route in own:
            to = names.get(route["subscription"], route["subscription"])
            lines.append(f"  -> {to}: {route['route']} ({route['via']}): {route['reason']}")
    return lines


def run(args: argparse.Namespace) -> int:
    with graph_node(args) as node:
        topic, type_name = resolve_topic(node, args.topic_name)
        publishers = [i for i in node.get_publishers_info_by_topic(topic)
                      if not hidden(i.node_name, args)]
        subscriptions = [i for i in node.get_subscriptions_info_by_topic(topic)
                         if not hidden(i.node_name, args)]
        routes = routes_by_publisher(node) if args.detailed else {}
    print(f"Type: {type_name}")
    if not args.detailed:
        print(f"Publisher count: {len(publishers)}")
        print(f"Subscription count: {len(subscriptions)}")
        return 0
    names = {i.endpoint_gid.hex(): f"{i.node_namespace.rstrip('/')}/{i.node_name} "
             f"({format_gid(i.endpoint_gid)[:11]})" for i in subscriptions}
    for title, endpoints in (("Publisher", publishers), ("Subscription", subscriptions)):
        print(f"\n{title} count: {len(endpoints)}\n")
        for info in endpoints:
            print("\n".join(describe(info, names, routes)))
            print()
    return 0
