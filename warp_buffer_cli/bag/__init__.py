"""``warp-buffer bag``: record topics to a rosbag2 bag, play one back, describe one.

Bags are rosbag2 directories (``metadata.yaml`` beside one MCAP or sqlite3 file) written by
rosbags, which ``ros2 bag info`` / ``ros2 bag play`` and any rosbags reader open. Buffer fields
are stored as ordinary CDR bytes: a warp buffer is copied to the host once, at the recorder.
"""

from __future__ import annotations

import argparse

from .._groups import add_subcommands

COMMANDS = {
    "record": ("warp_buffer_cli.bag.record", "record topics of the graph into a new bag"),
    "play": ("warp_buffer_cli.bag.play", "republish a bag's messages with their recorded timing"),
    "info": ("warp_buffer_cli.bag.info", "describe a bag: files, duration, topics and counts"),
    "reindex": ("warp_buffer_cli.bag.reindex",
                "rebuild the metadata of a bag whose recording never ended (killed)"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_subcommands(parser, COMMANDS)
