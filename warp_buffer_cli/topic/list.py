"""List the topics of the domain, one per line (``-t``: with their types), as ``ros2 topic list``
does; ``-v``: published and subscribed topics apart, with their endpoint counts and the buffer
backends those endpoints advertise. Hidden topics (a part of the name starting with ``_``) and
the topics of hidden nodes only with ``--include-hidden``, as ``ros2 topic list``."""

from __future__ import annotations

import argparse

from .._graph import add_graph_options, graph_node, hidden, hidden_name


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-t", "--show-types", action="store_true",
                        help="also print each topic's type")
    parser.add_argument("-c", "--count-topics", action="store_true",
                        help="print only the number of topics")
    parser.add_argument("-v", "--verbose", action="store_true", dest="detailed",
                        help="published and subscribed topics, with counts and backends")
    add_graph_options(parser)


def topics(node, args: argparse.Namespace) -> dict[str, set[str]]:
    """Topic -> types, from the endpoints of visible nodes."""
    found: dict[str, set[str]] = {}
    for topic, _types in node.get_topic_names_and_types():
        if hidden_name(topic, args):
            continue
        for info in (*node.get_publishers_info_by_topic(topic),
                     *node.get_subscriptions_info_by_topic(topic)):
            if not hidden(info.node_name, args):
                found.setdefault(topic, set()).add(info.topic_type)
    return found


def _verbose(node, args: argparse.Namespace) -> list[str]:
    lines = []
    for title, get, noun in (("Published topics:", node.get_publishers_info_by_topic,
                              "publisher"),
                             ("Subscribed topics:", node.get_subscriptions_info_by_topic,
                              "subscriber")):
        lines.append(title)
        for topic, types in node.get_topic_names_and_types():
            if hidden_name(topic, args):
                continue
            infos = [i for i in get(topic) if not hidden(i.node_name, args)]
            if not infos:
                continue
            backends = sorted({name for i in infos for name in (i.backends or {})})
            plural = "s" if len(infos) > 1 else ""
            lines.append(f" * {topic} [{', '.join(types)}] {len(infos)} {noun}{plural}"
                         + (f" (backends: {', '.join(backends)})" if backends else ""))
        lines.append("")
    return lines


def run(args: argparse.Namespace) -> int:
    with graph_node(args) as node:
        found = topics(node, args)
        if args.detailed and not args.count_topics:
            print("\n".join(_verbose(node, args)))
            return 0
    if args.count_topics:
        print(len(found))
        return 0
    for topic in sorted(found):
        print(f"{topic} [{', '.join(sorted(found[topic]))}]" if args.show_types else topic)
    return 0
