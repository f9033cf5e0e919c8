"""Record topics of the graph into a new rosbag2 bag (MCAP or sqlite3).

Name topics, or give -a for every topic of the domain (those that appear later too). Named
topics must have a publisher within --discovery-timeout, else nothing is created. Ctrl-C
(SIGINT), SIGTERM or --duration ends the recording: the bag is finalized and readable. Buffer
fields are stored as ordinary CDR bytes, copied to the host once here. Messages wait for the disk
in a cache of --max-cache-size bytes; what does not fit is dropped and counted, and the report
on stdout says how many (also those lost in transport). The domain is ROS_DOMAIN_ID's (0 if
unset), as for every node.
"""

from __future__ import annotations

import argparse
import datetime
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .._arguments import absolute_topic_name, number
from .errors import BagWriteError, UnknownTopicError
from .progress import Progress, size_text
from .qos import latched, offered_profiles

__all__ = ["DEFAULT_MAX_CACHE_BYTES", "Recorder", "TopicRecord", "add_arguments", "run"]

_log = logging.getLogger(__name__)

#: Bytes of serialized messages that may wait for the disk (32 frames of 16 MiB).
DEFAULT_MAX_CACHE_BYTES = 512 << 20
#: Keep-last depth of the recorder's subscriptions: room for a callback falling briefly behind.
SUBSCRIPTION_DEPTH = 100
#: How often -a looks for topics that appeared.
TOPIC_POLL_S = 0.5
STORAGES = ("mcap", "sqlite3")


@dataclass
class TopicRecord:
    """What was recorded of one topic and type."""

    topic: str
    type_name: str
    messages: int = 0  # written to the bag
    nbytes: int = 0  # CDR bytes written
    dropped: int = 0  # refused by the full cache: the disk could not keep up
    lost: int = 0  # lost or dropped before the recorder's callback (transport, keep-last queue)


class Recorder:
    """Subscribes to topics and writes their messages to a new bag at ``path``.

    ``backend`` is what the subscriptions accept for buffer fields: ``"warp"`` (a same-host
    publisher's warp buffer arrives zero-copy and is copied to the host once, here) or
    ``"cpu"`` (the publisher serializes CDR bytes for us). The bag is created by
    :meth:`create` or the first :meth:`add`; :meth:`close` stops the subscriptions, writes what the cache holds and
    finalizes the bag (also after an error).
    """

    def __init__(self, path: str | os.PathLike[str], *, storage: str = "mcap",
                 backend: str = "warp", max_cache_bytes: int = DEFAULT_MAX_CACHE_BYTES,
                 domain_id: int | None = None, node_name: str = "warp_buffer_recorder") -> None:
        from buffer_pubsub import Node

        from .cache import WriteCache

        if storage not in STORAGES:
            raise BagWriteError(f"storage must be one of {STORAGES}, got {storage!r}")
        self.path = Path(path)
        try:
            exists = self.path.exists()
        except OSError as exc:  # a parent it may not search (mode 000)
            raise BagWriteError(f"cannot create the bag {self.path}: {exc.strerror}") from None
        if exists:
            raise BagWriteError(f"{self.path} exists already: a bag is recorded into a new "
                                "directory")
        self.storage = storage
        self.backend = backend
        self.records: dict[tuple[str, str], TopicRecord] = {}
        self.write_error: BaseException | None = None
        self.started: float | None = None  # when the bag was created: the recording began
        self.stopped: float | None = None  # when close was asked (its teardown not counted)
        self.cache = WriteCache(max_cache_bytes)
        self._writer: Any = None
        self._thread: threading.Thread | None = None
        self._subscriptions: dict[tuple[str, str], Any] = {}
        self._closed = False
        self.node = Node(node_name, domain_id=domain_id)

    # -- topics ----------------------------------------------------------------------------
    def graph_topics(self) -> dict[str, list[str]]:
        """Topics of the domain with their types, as discovered so far."""
        return dict(self.node.get_topic_names_and_types())

    def wait_for_topics(self, topics: list[str], timeout: float,
                        stop: threading.Event | None = None,
                        waiting: Callable[[list[str]], None] | None = None
                        ) -> dict[str, list[str]]:
        """The types of ``topics`` once each was discovered; :class:`UnknownTopicError` naming
        those still unknown after ``timeout`` seconds; ``{}`` if ``stop`` is set first.
        ``waiting(missing)`` is called once if some are still unknown after a second (and more
        than a second is left)."""
        start = time.monotonic()
        deadline = start + timeout
        stop = stop or threading.Event()
        while True:
            found = self.graph_topics()
            missing = [t for t in topics if not found.get(t)]
            if not missing:
                return {t: found[t] for t in topics}
            now = time.monotonic()
            if waiting is not None and now - start > 1.0 and deadline - now > 1.0:
                waiting(missing)
                waiting = None
            if stop.wait(0.05):
                return {}
            if time.monotonic() >= deadline:
                raise UnknownTopicError(
                    f"unknown topic{'s' if len(missing) > 1 else ''} {', '.join(missing)}: "
                    f"nothing in domain {self.node.domain_id} publishes "
                    f"{'them' if len(missing) > 1 else 'it'} after {timeout:g} s")

    def add(self, topic: str, type_name: str) -> TopicRecord:
        """Record ``topic`` of ``type_name`` from now on (once per topic and type). Raises
        :class:`~rosidl_buffer.errors.UnknownMessageTypeError` for a type this process does not
        know, before anything is created for it."""
        from rosidl_buffer.messages import get_message_type, get_typestore

        key = (topic, type_name)
        if key in self.records:
            return self.records[key]
        cls = get_message_type(type_name)
        self.create()
        profiles = offered_profiles(self.node.get_publishers_info_by_topic(topic))

        def add_connection() -> Any:
            try:
                return self._writer.add_connection(
                    topic, cls.__msgtype__, typestore=get_typestore(),
                    offered_qos_profiles=profiles)
            except Exception as exc:  # rosbags' own errors: one line for the user
                raise BagWriteError(f"cannot add {topic} to {self.path}: {exc}") from exc

        connection = self._in_writer_thread(add_connection)
        record = self.records[key] = TopicRecord(topic, cls.__msgtype__)
        latching = latched(profiles)  # then what its publishers kept is recorded too (CPU bytes)
        self._subscriptions[key] = self.node.create_subscription(
            cls, topic, self._callback(connection, record), depth=SUBSCRIPTION_DEPTH,
            acceptable_buffer_backends="cpu" if latching else self.backend, with_info=True,
            durability="transient_local" if latching else "volatile")
        return record

    def create(self) -> None:
        """Create the bag now (idempotent; :meth:`add` does it too): a recording that gets no
        topic or no message still ends as a valid empty bag, as ``ros2 bag record``'s does.
        The recording's time counts from here."""
        if self._writer is None:
            self._writer = self._in_writer_thread(self._create_writer)
            self.started = time.monotonic()

    def duration(self) -> float:
        """Seconds from the bag's creation to the stop (to now while it records); 0 before."""
        if self.started is None:
            return 0.0
        return (self.stopped or time.monotonic()) - self.started

    def _in_writer_thread(self, call: Callable[[], Any]) -> Any:
        """``call()`` run by the writer thread, after the messages queued before it: rosbags'
        writer is used by that one thread (sqlite3 objects belong to the thread that made them).
        Its result, or its exception raised here."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._write_loop, name="bag-writer",
                                            daemon=True)
            self._thread.start()
        done = threading.Event()
        outcome: dict[str, Any] = {}
        self.cache.put_always(("call", call, outcome, done))
        done.wait()
        if "error" in outcome:
            raise outcome["error"]
        return outcome.get("value")

    def _create_writer(self) -> Any:
        from rosbags.rosbag2 import StoragePlugin

        from .writer import BagWriter

        plugin = StoragePlugin.MCAP if self.storage == "mcap" else StoragePlugin.SQLITE3
        try:
            writer = BagWriter(self.path, version=BagWriter.VERSION_LATEST, storage_plugin=plugin)
            writer.open()
        except Exception as exc:
            raise BagWriteError(f"cannot create the bag {self.path}: {exc}") from exc
        return writer

    def _callback(self, connection: Any, record: TopicRecord) -> Callable[[Any, Any], None]:
        from rosidl_buffer.messages import release_buffers, serialize_message, serialized_size

        cache = self.cache

        def on_message(msg: Any, info: Any) -> None:
            # A message the full cache would refuse is not serialized at all: the copy would
            # only take time from the writer, which is behind.
            data = serialize_message(msg) if cache.has_room(serialized_size(msg)) else None
            if info.route != "intra":  # (an in-process message's buffers are its publisher's)
                release_buffers(msg)  # the publisher may reuse its block now, not at GC
            if data is None or not cache.put(
                    ("message", connection, info.received_timestamp_ns, data, record), len(data)):
                record.dropped += 1

        return on_message

    def _write_loop(self) -> None:
        from . import writer as bag_writer  # (rosbags is imported only by a recording)

        while True:
            try:
                item = self.cache.get(timeout=bag_writer.COMMIT_S)
            except TimeoutError:  # nothing came: what was written must not wait for more
                self._flush_if_due()
                continue
            if item is None:
                return
            if item[0] == "call":
                _, call, outcome, done = item
                try:
                    outcome["value"] = call()
                except BaseException as exc:  # handed to the caller's thread
                    outcome["error"] = exc
                done.set()
                continue
            _, connection, timestamp, data, record = item
            if self.write_error is not None:
                record.dropped += 1  # the bag cannot take it: counted, not written
                continue
            try:
                self._writer.write(connection, timestamp, data)
            except Exception as exc:  # a full disk, say: stop writing, keep the bag readable
                self.write_error = exc
                record.dropped += 1
                continue
            record.messages += 1
            record.nbytes += len(data)

    def _flush_if_due(self) -> None:
        if self._writer is None or self.write_error is not None:
            return
        try:
            self._writer.flush_if_due()
        except Exception as exc:  # as a failed write: stop writing, keep the bag readable
            self.write_error = exc

    def _finalize(self) -> None:
        try:
            self._writer.close()
        except Exception as exc:
            raise BagWriteError(f"cannot finalize the bag {self.path}: {exc}") from exc

    # -- counts and end --------------------------------------------------------------------
    def totals(self) -> tuple[int, int, int]:
        """Messages and bytes written so far, and messages dropped (cache, transport)."""
        self._count_lost()
        records = self.records.values()
        return (sum(r.messages for r in records), sum(r.nbytes for r in records),
                sum(r.dropped + r.lost for r in records))

    def _count_lost(self) -> None:
        for key, sub in self._subscriptions.items():
            counters = sub.counters
            self.records[key].lost = counters.lost + counters.dropped + counters.errors

    def close(self) -> None:
        """Stop recording; write what waits in the cache and finalize the bag (idempotent).
        Raises :class:`BagWriteError` if a write failed (the bag still holds what was written
        before)."""
        if self._closed:
            return
        self._closed = True
        self.stopped = time.monotonic()  # (the node's teardown below is no recording time)
        self.node.close()  # no callback runs after this
        self._count_lost()
        try:
            if self._writer is not None:  # after the messages the cache holds
                self._in_writer_thread(self._finalize)
        finally:
            self.cache.close()
            if self._thread is not None:
                self._thread.join()
        if self.write_error is not None:
            raise BagWriteError(f"writing {self.path} failed, recording stopped: "
                                f"{self.write_error}") from self.write_error

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc_info: Any) -> None:
        self.close()


# --------------------------------------------------------------------------- command line
def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Register the options of ``warp-buffer bag record``."""
    parser.add_argument("topics", nargs="*", type=absolute_topic_name, metavar="TOPIC",
                        help="topics to record (or -a)")
    parser.add_argument("-a", "--all", action="store_true",
                        help="record every topic of the domain, also those that appear later")
    parser.add_argument("-o", "--output", metavar="DIR",
                        help="bag directory to create (default: rosbag2_YYYY_MM_DD-HH_MM_SS, as "
                             "ros2 bag names it)")
    parser.add_argument("-s", "--storage", choices=STORAGES, default="mcap",
                        help="storage format (default: mcap)")
    parser.add_argument("--duration", type=number(float, 0, inclusive=False, high=1e9), metavar="S",
                        help="stop after S seconds (default: until Ctrl-C or SIGTERM)")
    parser.add_argument("--backend", choices=("warp", "cpu"), default="warp",
                        help="how buffer fields reach the recorder: warp (zero-copy from a "
                             "same-host publisher, then one copy to the host; the faster, see "
                             "benchmarks/bag_record.py) or cpu (CDR bytes) (default: warp)")
    parser.add_argument("--max-cache-size", type=number(int, 1), metavar="BYTES",
                        default=DEFAULT_MAX_CACHE_BYTES,
                        help="bytes of messages that may wait for the disk; messages beyond are "
                             f"dropped and counted (default: {DEFAULT_MAX_CACHE_BYTES})")
    parser.add_argument("--discovery-timeout", type=number(float, 0, inclusive=False, high=86_400.0),
                        default=10.0, metavar="S",
                        help="seconds to wait for the named topics' publishers (default: 10)")


def _default_output() -> str:
    return datetime.datetime.now().strftime("rosbag2_%Y_%m_%d-%H_%M_%S")


def run(args: argparse.Namespace) -> int:
    """Run ``warp-buffer bag record``; its exit status."""
    if bool(args.topics) == bool(args.all):
        print(f"{args.command_name}: error: name the topics to record, or give -a "
              "(not both)", file=sys.stderr)
        return 2
    stop = threading.Event()
    previous = {signum: signal.signal(signum, lambda *_: stop.set())
                for signum in (signal.SIGINT, signal.SIGTERM)}
    try:
        return _record(args, stop)
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


def _record(args: argparse.Namespace, stop: threading.Event) -> int:
    recorder = Recorder(args.output or _default_output(), storage=args.storage,
                        backend=args.backend, max_cache_bytes=args.max_cache_size)
    try:
        if args.topics:
            found = recorder.wait_for_topics(
                args.topics, args.discovery_timeout, stop,
                lambda missing: print(f"{args.command_name}: waiting up to "
                                      f"{args.discovery_timeout:g} s for {', '.join(missing)} "
                                      "to be published", file=sys.stderr, flush=True))
            _check_types(found)  # all known before the bag is created
            for topic, types in found.items():
                for type_name in types:
                    _announce(recorder.add(topic, type_name), recorder)
            if not found:  # Ctrl-C before the topics were found: no bag was created
                recorder.close()
                print(f"{args.command_name}: interrupted", file=sys.stderr)
                return 130
        else:
            recorder.create()  # -a: the bag exists from the start, if empty
            _add_new_topics(recorder, skipped=set())
        _run_until_stopped(recorder, args, stop)
    except BaseException:
        _close_quietly(recorder)
        raise
    recorder.close()
    _report(recorder)
    return 0


def _check_types(found: dict[str, list[str]]) -> None:
    from rosidl_buffer.errors import UnknownMessageTypeError
    from rosidl_buffer.messages import get_message_type

    for topic, types in found.items():
        for type_name in types:
            try:
                get_message_type(type_name)
            except UnknownMessageTypeError as exc:
                raise UnknownMessageTypeError(f"cannot record {topic}: {exc}") from None


def _announce(record: TopicRecord, recorder: Recorder) -> None:
    print(f"recording {record.topic} ({record.type_name}) to {recorder.path}", flush=True)


def _add_new_topics(recorder: Recorder, skipped: set[tuple[str, str]]) -> None:
    """-a: subscribe to what appeared in the graph; a type unknown here is skipped, said once."""
    from rosidl_buffer.errors import UnknownMessageTypeError

    for topic, types in recorder.graph_topics().items():
        for type_name in types:
            if (topic, type_name) in recorder.records or (topic, type_name) in skipped:
                continue
            try:
                _announce(recorder.add(topic, type_name), recorder)
            except UnknownMessageTypeError as exc:
                skipped.add((topic, type_name))
                print(f"warp-buffer bag record: skipping {topic}: {exc}", file=sys.stderr)


def _run_until_stopped(recorder: Recorder, args: argparse.Namespace,
                       stop: threading.Event) -> None:
    progress = Progress("recorded")
    deadline = None if args.duration is None else time.monotonic() + args.duration
    skipped: set[tuple[str, str]] = set()
    next_poll = time.monotonic() + TOPIC_POLL_S
    try:
        while not stop.is_set() and recorder.write_error is None:
            now = time.monotonic()
            if deadline is not None and now >= deadline:
                break
            if args.all and now >= next_poll:
                _add_new_topics(recorder, skipped)
                next_poll = now + TOPIC_POLL_S
            messages, nbytes, dropped = recorder.totals()
            progress.update(messages, nbytes, dropped)
            stop.wait(0.05 if deadline is None else min(0.05, max(0.0, deadline - now)))
    finally:
        progress.close()


def _close_quietly(recorder: Recorder) -> None:
    try:
        recorder.close()
    except Exception as exc:  # the error in flight is the one to report
        _log.debug("closing the bag after an error: %s", exc)


def _report(recorder: Recorder) -> None:
    """The summary on stdout: totals, then one line per topic."""
    elapsed = recorder.duration()
    messages, nbytes, _ = recorder.totals()
    records = list(recorder.records.values())
    dropped = sum(r.dropped for r in records)
    lost = sum(r.lost for r in records)
    print(f"recorded {messages} messages, {size_text(nbytes)}, in {elapsed:.2f} s "
          f"({nbytes / (1 << 20) / max(elapsed, 1e-9):.1f} MiB/s) to {recorder.path} "
          f"({recorder.storage})")
    for r in records:
        print(f"  {r.topic}  {r.type_name}  {r.messages} messages  {size_text(r.nbytes)}  "
              f"dropped {r.dropped}  lost {r.lost}")
    print(f"dropped {dropped + lost}: {dropped} because the disk could not keep up (cache of "
          f"{size_text(recorder.cache.max_bytes)} full, peak "
          f"{size_text(recorder.cache.peak_bytes)}), "
          f"{lost} lost before the recorder (transport, keep-last queue)")
