"""Make a bag whose recording never ended readable again, as ``ros2 bag reindex`` does.

A recorder killed without a chance to close (SIGKILL, a power cut, a full disk) leaves its bag
without ``metadata.yaml``, and its MCAP file without the summary and footer a reader looks for,
so ``bag info`` and ``bag play`` (and ``ros2 bag``) cannot open it. ``bag reindex DIR`` ends an
MCAP file as its writer would have (:mod:`.mcap_end`: cut after its last complete chunk, then
the summary and the footer; a message the crash cut short is lost) and writes ``metadata.yaml``
from the storage file. A sqlite3 bag keeps what its recorder committed (each second). A bag
that ended well is left as it is; a bag still being recorded (its recorder holds the directory)
is refused, and so is a closed MCAP file damaged inside (:class:`BagDamagedError`: a new index
would not mend it).
"""

from __future__ import annotations

import argparse
import os
import sqlite3
from io import StringIO
from pathlib import Path
from typing import Any

from .damage import check_mcap
from .errors import BagDamagedError, BagReadError
from .lock import BagBusyError, locked_bag
from .mcap_end import McapContents, channel_metadata, end_mcap, is_closed
from .play import STORAGE_SUFFIXES, check_regular_files

__all__ = ["add_arguments", "reindex", "run"]

METADATA = "metadata.yaml"
BAG_VERSION = 9  # what the recorder writes (rosbags' latest)


def reindex(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Rebuild the ``metadata.yaml`` of the bag directory ``path`` from its one storage file
    (``.mcap`` or ``.db3``); returns what it found: ``file``, ``messages``, ``topics``,
    ``cut_bytes`` (the unfinished record cut off an MCAP file) and ``unchanged`` (a bag its
    recorder closed, left as it is). :class:`BagReadError` when
    ``path`` holds no such file or it is not one, or this user may not read or write it."""
    try:
        return _reindex(Path(path))
    except PermissionError as exc:
        raise BagReadError(f"cannot reindex {path}: {exc.strerror}: {exc.filename}") from None


def _reindex(root: Path) -> dict[str, Any]:
    if not root.is_dir():
        raise BagReadError(f"no bag directory at {root}" + (
            ": it does not exist" if not root.exists() else
            f": it is a file; give the bag's directory ({root.parent})"))
    check_regular_files(root)
    files = sorted(p for p in root.iterdir() if p.suffix in STORAGE_SUFFIXES)
    if len(files) != 1:
        raise BagReadError(f"{root} holds {len(files)} .mcap / .db3 files; reindex needs one")
    storage = files[0]
    cut = 0
    try:
        with locked_bag(root):  # never a bag its recorder still writes
            ended = _ended_well(root, storage)
            if ended is not None:
                return {"file": storage.name, "messages": ended[0], "topics": ended[1],
                        "cut_bytes": 0, "unchanged": True}
            if storage.suffix == ".mcap":
                cut, info = _end_mcap(storage)
            else:
                info = _sqlite_info(storage)
            _write_metadata(root / METADATA, _metadata_text(storage, info))
    except BagBusyError as exc:
        raise BagReadError(f"cannot reindex {root}: {exc}") from None
    return {"file": storage.name, "messages": info["message_count"],
            "topics": len(info["topics"]), "cut_bytes": cut, "unchanged": False}


def _ended_well(root: Path, storage: Path) -> tuple[int, int] | None:
    """Messages and topics of a bag its recorder closed (its ``metadata.yaml`` written, which
    holds what the storage cannot: the types' hashes), which reindex leaves as it is; None for
    one that needs reindexing."""
    from .play import open_bag

    if not (root / METADATA).exists():
        return None
    if storage.suffix == ".mcap":
        with storage.open("rb") as file:
            if not is_closed(file, os.fstat(file.fileno()).st_size):
                recorded = _recorded_messages(root / METADATA)
                if recorded:  # a recorder that never ended writes no metadata.yaml
                    raise BagDamagedError(
                        f"cannot reindex {root}: its {METADATA} records {recorded} messages of "
                        f"a recording that ended, but {storage.name} does not end as a closed "
                        "MCAP file does (cut short since?); reindex ends recordings that never "
                        f"ended, and rewriting {METADATA} would lose that record")
                return None
    try:
        reader = open_bag(root)
    except BagDamagedError as exc:  # closed, then changed: nothing a new index would mend
        raise BagDamagedError(f"cannot reindex {root}: {exc} (reindex ends a recording that "
                              "never ended; it does not repair a closed file)") from None
    except BagReadError:
        return None  # a damaged metadata.yaml: rebuilt
    try:
        return reader.message_count, len(reader.connections)
    finally:
        reader.close()


def _recorded_messages(metadata: Path) -> int | None:
    """The message count a readable ``metadata.yaml`` records (None: unreadable)."""
    from ruamel.yaml import YAML

    try:
        info = YAML(typ="safe").load(metadata.read_text(encoding="utf-8"))
        count = info["rosbag2_bagfile_information"]["message_count"]
    except Exception:  # any damage: the file is rebuilt as a lost one would be
        return None
    return count if type(count) is int else None


def _end_mcap(path: Path) -> tuple[int, dict[str, Any]]:
    """End the MCAP file ``path`` unless its writer did; the bytes cut off, and its metadata."""
    with path.open("rb") as file:
        closed = is_closed(file, os.fstat(file.fileno()).st_size)
    if closed:  # (its metadata.yaml lost: what rosbags reads of the file)
        return 0, _mcap_info(path)
    cut, contents = end_mcap(path, lambda contents: _metadata_text(path, _contents_info(
        contents)))
    _mcap_info(path)  # the ended file opens
    return cut, _contents_info(contents)


def _contents_info(contents: McapContents) -> dict[str, Any]:
    """The metadata of what an MCAP file's data section holds."""
    from rosbags.rosbag2.metadata import parse_qos

    counts = contents.message_counts()
    first, last = contents.time_span()
    topics = []
    for c in contents.channels.values():
        metadata = channel_metadata(c.metadata)
        qos = metadata.get("offered_qos_profiles")
        topics.append(_topic(c.topic, c.schema, c.message_encoding,
                             parse_qos(qos) if qos else [],
                             metadata.get("topic_type_hash", ""), counts[c.id]))
    count = sum(counts.values())
    return {"message_count": count, "start": first if count else 0,
            "duration": last - first if count else 0, "topics": topics}


def _topic(name: str, type_name: str, serialization: str, qos: Any, digest: str,
           count: int) -> dict[str, Any]:
    from rosbags.rosbag2.metadata import dump_qos_v9

    return {"topic_metadata": {"name": name, "type": type_name,
                               "serialization_format": serialization,
                               "offered_qos_profiles": dump_qos_v9(qos),
                               "type_description_hash": digest},
            "message_count": count}


def _mcap_info(path: Path) -> dict[str, Any]:
    from rosbags.rosbag2.storage_mcap import McapReader

    reader = McapReader(path)
    try:
        reader.open()  # (closes itself when it fails)
    except Exception as exc:  # rosbags' ReaderError and the like: the file is damaged inside
        raise BagReadError(f"cannot read {path}: {exc}") from exc
    try:  # (close clears them)
        check_mcap(reader)  # a closed file damaged inside: refused, not indexed as it is
        connections, meta = list(reader.connections), reader.metadata
        hashes = {key: channel_metadata(c.metadata).get("topic_type_hash", "")
                  for key, c in reader.channels.items()}
    finally:
        reader.close()
    count = meta.message_count
    # (rosbags reads no hash from a channel; the recorder writes one, as rosbag2 does)
    topics = [_topic(c.topic, c.msgtype, c.ext.serialization_format,
                     c.ext.offered_qos_profiles, hashes.get(c.id) or c.digest, c.msgcount)
              for c in connections]
    # (the reader's end and duration count one past the last stamp)
    return {"message_count": count, "start": meta.start_time if count else 0,
            "duration": max(0, meta.duration - 1) if count else 0, "topics": topics}


def _sqlite_info(path: Path) -> dict[str, Any]:
    from ruamel.yaml import YAML

    try:
        # Read-write: opening rolls back what the recorder had not committed (its journal).
        connection = sqlite3.connect(f"file:{path}?mode=rw", uri=True)
        try:
            rows = connection.execute(
                "SELECT id, name, type, serialization_format, offered_qos_profiles, "
                "type_description_hash FROM topics ORDER BY id").fetchall()
            stats = {topic: (count, first, last) for topic, count, first, last in
                     connection.execute("SELECT topic_id, COUNT(*), MIN(timestamp), "
                                        "MAX(timestamp) FROM messages GROUP BY topic_id")}
        finally:
            connection.close()
    except sqlite3.Error as exc:
        raise BagReadError(f"cannot read {path}: {exc}") from exc
    # Opening rolled a live journal back and removed it; one still there is stale (its header
    # zeroed when the killed recorder had committed) and would be listed as a bag file.
    Path(f"{path}-journal").unlink(missing_ok=True)
    yaml = YAML(typ="safe")
    topics = [{
        "topic_metadata": {
            "name": name, "type": type_name, "serialization_format": serialization,
            "offered_qos_profiles": yaml.load(qos) if qos else [],
            "type_description_hash": digest or "",
        },
        "message_count": stats.get(topic_id, (0, 0, 0))[0],
    } for topic_id, name, type_name, serialization, qos, digest in rows]
    count = sum(s[0] for s in stats.values())
    start = min((s[1] for s in stats.values()), default=0)
    end = max((s[2] for s in stats.values()), default=0)
    return {"message_count": count, "start": start, "duration": end - start,
            "topics": topics}


def _write_metadata(target: Path, text: str) -> None:
    """``metadata.yaml``, written atomically."""
    temporary = target.with_suffix(".yaml.tmp")
    temporary.write_text(text, "utf8")
    temporary.replace(target)


def _metadata_text(storage: Path, info: dict[str, Any]) -> str:
    """``metadata.yaml`` as rosbags' writer makes it (version 9)."""
    from ruamel.yaml import YAML

    span = {"starting_time": {"nanoseconds_since_epoch": info["start"]},
            "duration": {"nanoseconds": info["duration"]}}
    metadata = {"rosbag2_bagfile_information": {
        "version": BAG_VERSION,
        "storage_identifier": "mcap" if storage.suffix == ".mcap" else "sqlite3",
        "relative_file_paths": [storage.name],
        "duration": span["duration"],
        "starting_time": span["starting_time"],
        "message_count": info["message_count"],
        "topics_with_message_count": info["topics"],
        "compression_format": "",
        "compression_mode": "",
        "files": [{"path": storage.name, **span, "message_count": info["message_count"]}],
        "custom_data": None,
        "ros_distro": "rosbags",
    }}
    yaml = YAML(typ="safe")
    yaml.default_flow_style = False
    text = StringIO()
    yaml.dump(metadata, text)
    return text.getvalue()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", metavar="DIR", help="the bag directory")


def run(args: argparse.Namespace) -> int:
    report = reindex(args.bag)
    if report["unchanged"]:
        print(f"{args.bag} ended well (its recorder closed it): left as it is, "
              f"{_count(report['topics'], 'topic')}, {_count(report['messages'], 'message')}")
        return 0
    cut = (f"; cut {report['cut_bytes']} bytes of a record the recording did not finish"
           if report["cut_bytes"] else "")
    print(f"reindexed {args.bag}: {report['file']}, {_count(report['topics'], 'topic')}, "
          f"{_count(report['messages'], 'message')}{cut}")
    return 0


def _count(number: int, noun: str) -> str:
    return f"{number} {noun}{'' if number == 1 else 's'}"
