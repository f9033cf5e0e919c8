"""Republish a bag's messages with their recorded timing (scaled by --rate).

Every topic of the bag, or those given with --topics, is published by a node of this process
with the QoS history its publishers offered. --backend warp puts each buffer field in Warp memory
(--device) before publishing, so same-host subscriptions that accept warp get it zero-copy;
cpu (the default) publishes the bytes as stored. Types this process does not know are built from
the definitions the bag carries; a topic whose type cannot be built is skipped (named in
``unplayable``), the others play, as ``ros2 bag play`` does. Messages are read from the storage
files' own topics (:mod:`.storage_messages`), and a pass that read fewer messages of a topic than
the bag counts is :class:`BagDamagedError`, never a silent short playback. Before the first
message the player waits up to
--wait-for-subscribers seconds for each topic to have a subscription (discovery takes a moment:
without the wait the first messages reach nobody). Ctrl-C or SIGTERM stops it.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Iterator
from typing import Any

from .._arguments import absolute_topic_name, number
from .errors import BagDamagedError, BagError, BagReadError, UnknownTopicError
from .progress import Progress, size_text
from .qos import latched, publisher_history, publisher_reliability
from .storage_messages import bag_messages

__all__ = ["PlayTopic", "Player", "add_arguments", "open_bag", "run"]

BACKENDS = ("cpu", "warp")
STORAGE_SUFFIXES = (".mcap", ".db3")  # rosbag2's storage files: MCAP, sqlite3


def open_bag(path: str | os.PathLike[str]) -> Any:
    """An open rosbags ``Reader`` of the bag at ``path``; :class:`BagReadError` (one line)
    when it is missing, no bag, damaged, or not this user's to read."""
    try:
        reader = _open_reader(Path(path))
    except PermissionError as exc:  # a bag or a file of it this user may not read
        raise BagReadError(f"cannot read the bag at {path}: {exc.strerror}: "
                           f"{exc.filename}") from None
    try:
        _check_storages(reader)
    except BaseException:
        reader.close()
        raise
    return reader


def _open_reader(where: Path) -> Any:
    """The open rosbags Reader of ``where``; BagReadError for what is no readable bag."""
    from rosbags.rosbag2 import Reader

    check_regular_files(where)
    try:
        reader = Reader(where)
        reader.open()
    except FileNotFoundError:
        why = ("it does not exist" if not where.exists() else
               _no_metadata(where) if where.is_dir() else
               "not a rosbag2 bag")
        raise BagReadError(f"no bag at {where}: {why}") from None
    except PermissionError:
        raise
    except Exception as exc:  # rosbags' ReaderError, YAML and storage errors: all unreadable
        # A storage file alone (its recorder killed) is what reindex mends; not any file.
        hint = (f" (a recording that never ended? `warp-buffer bag reindex {where.parent}` "
                "rebuilds it)" if where.is_file() and where.suffix in STORAGE_SUFFIXES
                and not (where.parent / "metadata.yaml").exists() else "")
        raise BagReadError(f"cannot read the bag at {where}: {exc}{hint}") from exc
    return reader


def check_regular_files(path: Path) -> None:
    """:class:`BagReadError` for a storage file that is not a regular file: reading a FIFO
    there blocked for ever."""
    candidates = ([p for p in path.iterdir() if p.name != "metadata.yaml"] if path.is_dir()
                  else [path])
    for candidate in candidates:
        if candidate.exists() and not (candidate.is_file() or candidate.is_dir()):
            raise BagReadError(f"cannot read the bag at {path}: {candidate.name} is not a "
                               "regular file")


def _check_storages(reader: Any) -> None:
    """:class:`BagDamagedError` when an MCAP file of the open ``reader`` is damaged inside
    (:mod:`.damage`: its record heads against its index, no payload read)."""
    from rosbags.rosbag2.storage_mcap import McapReader

    from .damage import check_mcap

    for storage in getattr(reader.storage, "storages", []):  # (a directory's files)
        if isinstance(storage, McapReader):
            check_mcap(storage)


def _no_metadata(directory: Path) -> str:
    from .lock import BagBusyError, locked_bag

    if not any(p.suffix in STORAGE_SUFFIXES for p in directory.iterdir()):
        return "no metadata.yaml in it: not a rosbag2 bag"
    try:
        with locked_bag(directory):
            pass
    except BagBusyError:
        return ("it is being recorded (its metadata.yaml is written when the recording "
                "ends)")
    return (f"no metadata.yaml beside its storage file: a recording that never ended? "
            f"`warp-buffer bag reindex {directory}` rebuilds it")


def message_class(type_name: str, definition: Any = None) -> Any:
    """The message class of ``type_name``; a type this process does not know is registered from
    the bag's ``.msg`` definition (``definition``: a rosbags ``MessageDefinition``)."""
    from rosidl_buffer.errors import UnknownMessageTypeError
    from rosidl_buffer.messages import get_message_type, register_message_definitions

    try:
        return get_message_type(type_name)
    except UnknownMessageTypeError:
        text = getattr(definition, "data", "") or ""
        if getattr(getattr(definition, "format", None), "name", "") != "MSG" or not text.strip():
            raise UnknownMessageTypeError(
                f"type {type_name} is not known here and the bag carries no .msg definition "
                "of it") from None
    try:
        register_message_definitions({type_name: text})
        return get_message_type(type_name)
    except Exception as exc:  # rosbags' parse or clash errors, our schema's refusals
        raise UnknownMessageTypeError(
            f"type {type_name}: the bag's definition cannot be used: {exc}") from None


@dataclass
class PlayTopic:
    """One topic and type of the bag, as played."""

    topic: str
    type_name: str
    messages: int = 0
    nbytes: int = 0
    skipped: int = 0  # undecodable: counted and not published
    first_skip: tuple[int, str] | None = None  # the first one's bag timestamp (ns) and why


class Player:
    """Publishes the messages of the bag at ``path`` with their recorded timing.

    ``topics``: only these (every one must be in the bag, else :class:`UnknownTopicError`);
    ``rate``: time scale (2.0 plays twice as fast); ``backend``: ``"cpu"`` publishes buffers as
    the stored bytes, ``"warp"`` copies each into a warp buffer on ``device`` first.
    """

    def __init__(self, path: str | os.PathLike[str], *, topics: list[str] | None = None,
                 rate: float = 1.0, backend: str = "cpu", device: str | None = None,
                 domain_id: int | None = None, node_name: str = "warp_buffer_player") -> None:
        if backend not in BACKENDS:
            raise BagError(f"backend must be one of {BACKENDS}, got {backend!r}")
        self.path = Path(path)
        self.rate = rate
        self.backend = backend
        self.device = device
        self.reader = open_bag(path)
        try:
            self.connections = self._select(topics)
            self._classes, self.unplayable = _classes(self.connections)
            self.connections = [c for c in self.connections if c.id in self._classes]
            if backend == "warp":
                self._check_device()
            from buffer_pubsub import Node

            self.node = Node(node_name, domain_id=domain_id)
        except BaseException:
            self.reader.close()
            raise
        self.topics = {c.id: PlayTopic(c.topic, c.msgtype) for c in self.connections}
        self._publishers: dict[int, Any] = {}
        for c in self.connections:
            profiles = getattr(c.ext, "offered_qos_profiles", [])
            history, depth = publisher_history(profiles)
            self._publishers[c.id] = self.node.create_publisher(
                self._classes[c.id], c.topic, depth=depth, history=history,
                reliability=publisher_reliability(profiles),
                durability="transient_local" if latched(profiles) else "volatile")

    def _select(self, topics: list[str] | None) -> list[Any]:
        connections = list(self.reader.connections)
        if not topics:
            return connections
        present = {c.topic for c in connections}
        missing = [t for t in topics if t not in present]
        if missing:
            raise UnknownTopicError(
                f"not in the bag {self.path}: {', '.join(missing)} (it holds "
                f"{', '.join(sorted(present)) or 'no topic'})")
        return [c for c in connections if c.topic in topics]

    def _check_device(self) -> None:
        import warp_buffer

        if self.device is None:
            self.device = str(warp_buffer.init_warp().get_preferred_device().alias)
        warp_buffer.allocate_buffer(1, device=self.device)  # DeviceUnavailableError now, typed

    def wait_for_subscribers(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s until every topic has a subscription; whether all have."""
        deadline = time.monotonic() + timeout
        for publisher in self._publishers.values():
            if not publisher.wait_for_subscriptions(1, timeout=max(0.0, deadline - time.monotonic())):
                return False
        return True

    def play(self, stop: threading.Event | None = None, loop: bool = False,
             progress: Progress | None = None) -> None:
        """Publish every message at its recorded time from now (scaled by ``rate``); once, or
        until ``stop`` is set with ``loop``."""
        stop = stop or threading.Event()
        while not stop.is_set():
            self._play_once(stop, progress)
            if not loop:
                return

    def _play_once(self, stop: threading.Event, progress: Progress | None) -> None:
        from rosidl_buffer.errors import DeserializationError
        from rosidl_buffer.messages import deserialize_message

        started = time.monotonic()
        first: int | None = None
        read: dict[int, int] = dict.fromkeys(self.topics, 0)  # this pass's, by connection
        for connection, timestamp, data in self._messages():
            first = timestamp if first is None else first
            due = started + (timestamp - first) / 1e9 / self.rate
            if stop.wait(max(0.0, due - time.monotonic())):
                return
            read[connection.id] += 1
            try:
                msg = deserialize_message(data, self._classes[connection.id])  # buffers alias
            except DeserializationError as exc:  # one bad message must not end the playback
                skipped = self.topics[connection.id]
                skipped.skipped += 1
                skipped.first_skip = skipped.first_skip or (timestamp, str(exc))
                continue
            if self.backend == "warp":
                _buffers_to_warp(msg, self.device)
            self._publishers[connection.id].publish(msg)
            played = self.topics[connection.id]
            played.messages += 1
            played.nbytes += len(data)
            if progress is not None:
                progress.update(*self.totals())
        self._check_complete(read)

    def _check_complete(self, read: dict[int, int]) -> None:
        """:class:`BagDamagedError` when a whole pass read fewer messages of a topic than the
        bag counts (its metadata, or its file's statistics): a topic dropped on the way."""
        short = [(c, read[c.id]) for c in self.connections if read[c.id] < c.msgcount]
        if short:
            raise BagDamagedError(
                f"the bag {self.path} is damaged: its storage gave fewer messages than it "
                "counts: " + ", ".join(f"{c.topic} ({c.msgtype}) {n} of {c.msgcount}"
                                       for c, n in short))

    def _messages(self) -> Iterator[tuple[Any, int, Any]]:
        """The bag's messages; what rosbags (or its storage) raises while reading them, past
        the check at open (a checksum, a sqlite3 page, a compressed chunk), is
        :class:`BagDamagedError` naming the file and how far it was read."""
        messages = bag_messages(self.reader, self.connections)
        read = 0
        while True:
            try:
                item = next(messages)
            except StopIteration:
                return
            except BagDamagedError:
                raise
            except Exception as exc:  # any reader's or storage's class: the file is damaged
                raise BagDamagedError(
                    f"the bag {self.path} is damaged: reading it failed after {read} "
                    f"message{'' if read == 1 else 's'}: {type(exc).__name__}: {exc}") from exc
            read += 1
            yield item

    def skipped(self) -> list[PlayTopic]:
        """The topics with undecodable messages (skipped, not published)."""
        return [t for t in self.topics.values() if t.skipped]

    def totals(self) -> tuple[int, int]:
        """Messages and bytes published so far."""
        return (sum(t.messages for t in self.topics.values()),
                sum(t.nbytes for t in self.topics.values()))

    def close(self) -> None:
        """Undeclare the publishers and close the bag."""
        self.node.close()
        if self.reader.is_open:
            self.reader.close()

    def __enter__(self) -> Player:
        return self

    def __exit__(self, *exc_info: Any) -> None:
        self.close()


def _classes(connections: list[Any]) -> tuple[dict[int, Any], list[tuple[str, str, str]]]:
    """The message class of each connection whose type can be built, and (topic, type, why)
    of those whose cannot: rosbag2's player warns and skips such a topic (a service event's
    ``.srv`` schema, a type without definition), playing the rest. None playable: the first
    one's :class:`UnknownMessageTypeError`."""
    from rosidl_buffer.errors import UnknownMessageTypeError

    classes: dict[int, Any] = {}
    unplayable: list[tuple[str, str, str]] = []
    first: Exception | None = None
    for c in connections:
        try:
            classes[c.id] = message_class(c.msgtype, c.msgdef)
        except UnknownMessageTypeError as exc:
            first = first or exc
            why = " ".join(str(exc).split())  # (a parse error quotes the whole definition)
            unplayable.append((c.topic, c.msgtype, why if len(why) <= 160 else why[:159] + "…"))
    if first is not None and not classes:
        raise first
    return classes, unplayable


def _buffers_to_warp(msg: Any, device: str | None) -> None:
    """Replace every non-empty buffer field of ``msg`` (nested messages too) by a warp buffer
    holding the same bytes (a pooled block: steady-state playback allocates nothing)."""
    import warp_buffer
    from rosidl_buffer.messages import get_schema

    for spec in get_schema(msg.__msgtype__).fields:
        value = getattr(msg, spec.name)
        if spec.is_buffer:
            if value.size():
                buffer = warp_buffer.allocate_buffer(value.size(), device=device)
                with warp_buffer.from_output_buffer(buffer) as out:
                    warp_buffer.to_buffer(value.numpy(writable=False), out)
                setattr(msg, spec.name, buffer)
        elif spec.kind.value == "message":
            for child in (value if spec.is_collection else [value]):
                _buffers_to_warp(child, device)


# --------------------------------------------------------------------------- command line
def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Register the options of ``warp-buffer bag play``."""
    parser.add_argument("bag", metavar="DIR", help="the bag directory (or its .mcap/.db3 file)")
    parser.add_argument("-r", "--rate", type=number(float, 0, inclusive=False, high=1e6), default=1.0,
                        help="time scale: 2 plays twice as fast (default: 1)")
    parser.add_argument("-l", "--loop", action="store_true",
                        help="play again from the start until Ctrl-C")
    parser.add_argument("--backend", choices=BACKENDS, default="cpu",
                        help="where buffer fields are published from: cpu (the stored bytes) "
                             "or warp (copied into Warp memory first) (default: cpu)")
    parser.add_argument("--device", default=None,
                        help="Warp device of --backend warp (default: Warp's preferred one)")
    parser.add_argument("--topics", nargs="+", metavar="TOPIC", type=absolute_topic_name,
                        help="play only these topics (default: every topic of the bag)")
    parser.add_argument("--wait-for-subscribers", type=number(float, 0, high=86_400.0),
                        default=1.0, metavar="S",
                        help="before the first message, wait up to S seconds for a subscription "
                             "on every topic (default: 1)")


def run(args: argparse.Namespace) -> int:
    """Run ``warp-buffer bag play``; its exit status."""
    stop = threading.Event()
    previous = {signum: signal.signal(signum, lambda *_: stop.set())
                for signum in (signal.SIGINT, signal.SIGTERM)}
    name = getattr(args, "command_name", "warp-buffer bag play")
    try:
        with Player(args.bag, topics=args.topics, rate=args.rate, backend=args.backend,
                    device=args.device) as player:
            for topic, type_name, why in player.unplayable:  # (before the playback: seen early)
                print(f"{name}: warning: not playing {topic} ({type_name}): {why}",
                      file=sys.stderr)
            player.wait_for_subscribers(args.wait_for_subscribers)
            started = time.monotonic()
            progress = Progress("played")
            try:
                player.play(stop, loop=args.loop, progress=progress)
            finally:
                progress.close()
            _report(player, time.monotonic() - started)
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    return _report_skipped(player, name)


def _report(player: Player, elapsed: float) -> None:
    messages, nbytes = player.totals()
    print(f"played {messages} message{'' if messages == 1 else 's'}, {size_text(nbytes)}, in "
          f"{elapsed:.2f} s from {player.path} "
          f"(bag duration {player.reader.duration / 1e9:.2f} s, rate {player.rate:g})")
    for t in player.topics.values():
        skipped = f"  skipped {t.skipped} undecodable" if t.skipped else ""
        print(f"  {t.topic}  {t.type_name}  {t.messages} messages  {size_text(t.nbytes)}"
              f"{skipped}")
    for topic, type_name, _ in player.unplayable:
        print(f"  {topic}  {type_name}  not played: its type cannot be built")
    sys.stdout.flush()


def _report_skipped(player: Player, name: str) -> int:
    """One line on stderr per topic with undecodable messages; the exit status (1 if any)."""
    for t in player.skipped():
        stamp, why = t.first_skip or (0, "")
        print(f"{name}: DeserializationError: skipped {t.skipped} undecodable message"
              f"{'' if t.skipped == 1 else 's'} of {t.topic} ({t.type_name}), the first at "
              f"{stamp // 10**9}.{stamp % 10**9:09d} s: {' '.join(why.split())}",
              file=sys.stderr)
    return 1 if player.skipped() else 0
