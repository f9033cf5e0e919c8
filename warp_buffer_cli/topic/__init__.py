"""``warp-buffer topic``: the topics of a domain, as ``ros2 topic`` shows them: every endpoint,
ours and those of ROS 2 nodes (rmw_zenoh), with the buffer backends each advertises and, for our
publishers, the route each subscription takes."""

from __future__ import annotations

import argparse

from .._groups import add_subcommands

COMMANDS = {
    "list": ("warp_buffer_cli.topic.list", "list the topics of the domain"),
    "type": ("warp_buffer_cli.topic.type", "print a topic's type"),
    "find": ("warp_buffer_cli.topic.find", "print the topics of a message type"),
    "info": ("warp_buffer_cli.topic.info",
             "print a topic's type and endpoints (-v: QoS, backends and routes)"),
    "echo": ("warp_buffer_cli.topic.echo", "print the messages of a topic"),
    "hz": ("warp_buffer_cli.topic.hz", "print the publishing rate of a topic"),
    "bw": ("warp_buffer_cli.topic.bw", "print the bandwidth a topic uses"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_subcommands(parser, COMMANDS)
