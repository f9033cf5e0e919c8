"""``warp-buffer node``: the nodes of a domain, ours and ROS 2 nodes' (rmw_zenoh), as
``ros2 node`` shows them."""

from __future__ import annotations

import argparse

from .._groups import add_subcommands

COMMANDS = {
    "list": ("warp_buffer_cli.node.list", "list the nodes of the domain"),
    "info": ("warp_buffer_cli.node.info", "print a node's publishers and subscriptions"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_subcommands(parser, COMMANDS)
