"""Describe a bag as ``ros2 bag info`` does: files, size, storage, duration, start and end,
message count, and every topic with its type, count and serialization format (--json: the same
as JSON, QoS profiles and type hashes included). An MCAP file damaged inside is reported as
:class:`~.errors.BagDamagedError` (:mod:`.damage`: record heads against the index)."""

from __future__ import annotations

import argparse
import datetime
import json
import os
from pathlib import Path
from typing import Any

from .play import open_bag
from .progress import size_text

__all__ = ["add_arguments", "describe", "run"]


def describe(path: str | os.PathLike[str]) -> dict[str, Any]:
    """What ``bag info`` reports of the bag at ``path``, as plain data."""
    reader = open_bag(path)
    try:
        root = Path(path)
        files = sorted(p for p in (root.iterdir() if root.is_dir() else [root])
                       if p.name != "metadata.yaml")
        connections = reader.connections
        count = reader.message_count
        duration = max(0, reader.duration - 1) if count else 0
        start = reader.start_time if count else 0
        return {
            "files": [p.name for p in files],
            "size_bytes": sum(p.stat().st_size for p in files) + (
                (root / "metadata.yaml").stat().st_size if (root / "metadata.yaml").exists()
                else 0),
            "storage": _storage_id(reader),
            "ros_distro": reader.ros_distro,
            # metadata.yaml's duration, and end = start + duration, as ros2 bag info shows
            # them (rosbags' duration and end count one past the last message's stamp)
            "duration_ns": duration,
            "start_ns": start,
            "end_ns": start + duration,
            "messages": reader.message_count,
            "topics": [{
                "name": c.topic,
                "type": c.msgtype,
                "count": c.msgcount,
                "serialization_format": getattr(c.ext, "serialization_format", "cdr"),
                "type_description_hash": c.digest,
                "offered_qos_profiles": [_qos(q) for q in getattr(c.ext, "offered_qos_profiles",
                                                                  [])],
            } for c in connections],
        }
    finally:
        reader.close()


def _storage_id(reader: Any) -> str:
    """The storage plugin's name, as metadata.yaml's ``storage_identifier`` (a compressed file's
    suffix is its compression's)."""
    from rosbags.rosbag2.storage_mcap import McapReader

    storages = getattr(reader.storage, "storages", [reader.storage])  # (a directory's files)
    if not storages:
        return ""
    return "mcap" if isinstance(storages[0], McapReader) else "sqlite3"


def _qos(profile: Any) -> dict[str, Any]:
    return {"history": profile.history.name.lower(), "depth": profile.depth,
            "reliability": profile.reliability.name.lower(),
            "durability": profile.durability.name.lower()}


def _stamp(ns: int) -> str:
    when = datetime.datetime.fromtimestamp(ns / 1e9)
    return f"{when:%b %d %Y %H:%M:%S}.{ns % 10**9:09d} ({ns // 10**9}.{ns % 10**9:09d})"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Register the options of ``warp-buffer bag info``."""
    parser.add_argument("bag", metavar="DIR", help="the bag directory (or its .mcap/.db3 file)")
    parser.add_argument("--json", action="store_true", help="print machine-readable JSON")


def run(args: argparse.Namespace) -> int:
    """Run ``warp-buffer bag info``; its exit status."""
    report = describe(args.bag)
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    label = "{:<19}".format
    print(label("Files:") + "\n".ljust(20).join(report["files"]))
    print(label("Bag size:") + size_text(report["size_bytes"]))
    print(label("Storage id:") + report["storage"])
    print(label("ROS Distro:") + (report["ros_distro"] or ""))  # (a bare file has none)
    print(label("Duration:") + f"{report['duration_ns'] / 1e9:.9f}s")
    print(label("Start:") + _stamp(report["start_ns"]))
    print(label("End:") + _stamp(report["end_ns"]))
    print(label("Messages:") + str(report["messages"]))
    topics = [f"Topic: {t['name']} | Type: {t['type']} | Count: {t['count']} | "
              f"Serialization Format: {t['serialization_format']}" for t in report["topics"]]
    print(label("Topic information:") + "\n".ljust(20).join(topics or ["(none)"]))
    return 0
