"""What the introspection commands (``warp-buffer topic ...``, ``warp-buffer node ...``) share:
options to reach a domain, a short-lived node that watches the graph, and their typed errors.

The node is named ``_warp_buffer_cli_<pid>``: a leading underscore hides it from ``node list``
and ``topic info`` (as ros2cli hides its ``_ros2cli_`` nodes) unless ``--include-hidden`` is given,
as topics and services with a part of their name starting with one are.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time
from collections.abc import Iterator
from typing import Any

from rosidl_buffer.errors import RosidlBufferError

__all__ = ["GraphCommandError", "UnknownTopicError", "add_graph_options", "graph_node",
           "hidden", "hidden_name", "latched_durability", "print_names", "resolve_topic",
           "routes_by_publisher", "unknown_topic", "wait_for_topic"]

#: How long a command watches the graph before it reports (peers answer in ~0.1-0.5 s here).
DEFAULT_SPIN_TIME = 1.0
HIDDEN_PREFIX = "_"


class GraphCommandError(RosidlBufferError):
    """An introspection command cannot do what was asked (printed as one line, exit 1)."""


class UnknownTopicError(GraphCommandError, LookupError):
    """No endpoint of the graph has this topic."""


def add_graph_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--domain", type=int, default=None,
                        help="ROS domain id (default: env ROS_DOMAIN_ID, else 0)")
    parser.add_argument("--router", default=None,
                        help="a Zenoh router to connect to, e.g. tcp/host:7447 (default: env "
                             "WARP_BUFFER_ZENOH_ROUTER, else loopback peers)")
    parser.add_argument("--spin-time", type=float, default=DEFAULT_SPIN_TIME, metavar="S",
                        help=f"seconds to watch the graph before answering "
                             f"(default {DEFAULT_SPIN_TIME})")
    parser.add_argument("--include-hidden", action="store_true",
                        help="also show hidden nodes, topics and services (a name, or a "
                             "part of one, starting with '_')")


@contextlib.contextmanager
def graph_node(args: argparse.Namespace, wait: bool = True) -> Iterator[Any]:
    """A node of its own in the asked domain, after ``--spin-time`` seconds of discovery."""
    from buffer_pubsub import Node

    if args.spin_time < 0 or args.spin_time != args.spin_time:
        raise GraphCommandError(f"--spin-time must be a number of seconds >= 0, not "
                                f"{args.spin_time}")
    with Node(f"{HIDDEN_PREFIX}warp_buffer_cli_{os.getpid()}", domain_id=args.domain,
              router=args.router) as node:
        if wait:
            time.sleep(args.spin_time)
        yield node


def print_names(names: list[str], count_only: bool) -> int:
    """Print ``names`` one per line, or (``count_only``: ros2's ``-c``) only how many; 0."""
    if count_only:
        print(len(names))
    else:
        for name in names:
            print(name)
    return 0


def hidden(node_name: str, args: argparse.Namespace) -> bool:
    return node_name.startswith(HIDDEN_PREFIX) and not args.include_hidden


def hidden_name(name: str, args: argparse.Namespace) -> bool:
    """A topic or service name that ROS 2's tools hide, unless ``--include-hidden``: one with a
    part starting with ``_`` (rclpy's ``topic_or_service_is_hidden``: an action's
    ``/_action/feedback``, a private ``/ns/_debug``)."""
    return not args.include_hidden and any(part.startswith(HIDDEN_PREFIX)
                                           for part in name.split("/"))


def resolve_topic(node: Any, topic: str) -> tuple[str, str]:
    """The fully qualified ``topic`` and its type (UnknownTopicError when nobody has it, a
    GraphCommandError when it has several types)."""
    name = topic if topic.startswith("/") else "/" + topic
    types = dict(node.get_topic_names_and_types()).get(name)
    if not types:
        raise unknown_topic(node, name)
    if len(types) > 1:
        raise GraphCommandError(f"topic {name!r} has several types: {', '.join(types)}")
    return name, types[0]


def unknown_topic(node: Any, name: str) -> UnknownTopicError:
    """The error for topic ``name``, which no endpoint in ``node``'s graph has."""
    return UnknownTopicError(f"topic {name!r} is not in the graph of domain {node.domain_id} "
                             "(see `warp-buffer topic list`)")


def wait_for_topic(node: Any, topic: str) -> tuple[str, str]:
    """:func:`resolve_topic`, waiting for a topic nobody has yet (as ``ros2 topic echo / hz /
    bw`` do: a monitor may start before its publisher), with one warning on stderr; Ctrl-C
    ends the wait."""
    warned = False
    while True:
        try:
            return resolve_topic(node, topic)
        except UnknownTopicError:
            if not warned:
                name = topic if topic.startswith("/") else "/" + topic
                print(f"WARNING: topic [{name}] does not appear to be published yet; waiting "
                      f"for it in domain {node.domain_id} (Ctrl-C to stop)", file=sys.stderr,
                      flush=True)
                warned = True
            time.sleep(0.1)


def latched_durability(node: Any, topic: str) -> str:
    """The durability a monitor of ``topic`` subscribes with, as ``ros2 topic echo`` chooses
    it: transient-local when every publisher seen is (a latched topic: what they published
    before the monitor started is shown too), else volatile."""
    publishers = node.get_publishers_info_by_topic(topic)
    latched = bool(publishers) and all(p.qos_profile.transient_local for p in publishers)
    return "transient_local" if latched else "volatile"


def routes_by_publisher(node: Any, timeout: float = 2.0) -> dict[str, list[dict[str, Any]]]:
    """What our nodes in the domain answer on their routes key: publisher gid (hex) -> its
    routes (``Publisher.routes``). Nodes of other implementations do not answer."""
    import zenoh

    from buffer_pubsub import wire

    routes: dict[str, list[dict[str, Any]]] = {}
    # every node answers (the default target asks only the best-matching one)
    for reply in node.session.get(wire.routes_selector(node.domain_id), timeout=timeout,
                                  target=zenoh.QueryTarget.ALL,
                                  consolidation=zenoh.ConsolidationMode.NONE):
        try:
            answer = json.loads(reply.ok.payload.to_bytes())
        except (AttributeError, ValueError, TypeError):  # an error reply, or not JSON
            continue
        for publisher in answer.get("publishers", []):
            routes[publisher["publisher"]] = publisher["routes"]
    return routes
