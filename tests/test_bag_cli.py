"""``warp-buffer bag`` with real processes: a publisher in one process, ``bag record`` in another,
``bag play`` into a listener in a third; the bag read back with rosbags' own reader."""

from __future__ import annotations

import json
import os
import pathlib
import pty
import signal
import subprocess
import sys
import time
from typing import Any

import numpy as np
import pytest

from tests._bag_helpers import CUSTOM, CUSTOM_DEFINITION, STRING, TENSOR, expected_messages
from tests._bag_helpers import frame_bytes
from tests._pubsub_helpers import child_env

ROOT = pathlib.Path(__file__).resolve().parent.parent
pytestmark = pytest.mark.multiprocess
SIZE = 64 * 1024
COUNT = 12


# --------------------------------------------------------------------------- processes
class Proc:
    """A child process whose stdout lines are read on demand; always reaped by :meth:`close`."""

    def __init__(self, argv: list[str], domain: int, **popen: Any) -> None:
        env = dict(child_env(), ROS_DOMAIN_ID=str(domain))
        env.pop("WARP_BUFFER_VERBOSE", None)
        self.proc = subprocess.Popen(argv, cwd=ROOT, env=env, stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, **popen)
        self.lines: list[str] = []

    def read_until(self, prefix: str, timeout: float = 60.0) -> str:
        """The first stdout line starting with ``prefix`` (lines before it are kept)."""
        import selectors

        deadline = time.monotonic() + timeout
        with selectors.DefaultSelector() as selector:
            selector.register(self.proc.stdout, selectors.EVENT_READ)
            while time.monotonic() < deadline:
                if selector.select(timeout=0.2):
                    line = self.proc.stdout.readline()
                    if not line:
                        break
                    self.lines.append(line.rstrip("\n"))
                    if line.startswith(prefix):
                        return line.rstrip("\n")
        raise AssertionError(f"no {prefix!r} line from {self.proc.args}: {self.lines}")

    def tell(self, text: str) -> None:
        try:
            self.proc.stdin.write(text + "\n")
            self.proc.stdin.flush()
        except (BrokenPipeError, OSError):
            pass

    def finish(self, timeout: float = 60.0) -> tuple[int, str]:
        """Wait for the exit: its status and the rest of stdout."""
        out, _ = self.proc.communicate(timeout=timeout)
        self.lines += out.splitlines()
        return self.proc.returncode, out

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.communicate()


def helper(role: str, domain: int, topic: str, *options: str) -> Proc:
    return Proc([sys.executable, "-m", "tests._bag_helpers", role, "--domain", str(domain),
                 "--topic", topic, *options], domain)


def bag_cli(domain: int, *argv: str, **popen: Any) -> Proc:
    return Proc([sys.executable, "-m", "warp_buffer_cli.main", "bag", *argv], domain, **popen)


def run_bag(domain: int, *argv: str) -> subprocess.CompletedProcess[str]:
    env = dict(child_env(), ROS_DOMAIN_ID=str(domain))
    return subprocess.run([sys.executable, "-m", "warp_buffer_cli.main", "bag", *argv],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)


def record(tmp_path: pathlib.Path, domain: int, topic: str, *, publish: str, accept: str,
           storage: str = "mcap", count: int = COUNT) -> tuple[pathlib.Path, list[str]]:
    """Record ``count`` frames (and texts) of a publisher with ``publish`` storage into a new
    bag, the recorder accepting ``accept``; the bag's path and the recorder's report."""
    bag = tmp_path / f"bag_{storage}_{accept}"
    # The publisher first (the recorder looks its topics up), publishing once it is matched.
    publisher = helper("publish", domain, topic, "--count", str(count), "--size", str(SIZE),
                       "--backend", publish)
    recorder = None
    try:
        publisher.read_until("READY")
        recorder = bag_cli(domain, "record", topic, topic + "_text", "-o", str(bag), "-s",
                           storage, "--backend", accept)
        published = json.loads(publisher.read_until("RESULT ")[len("RESULT "):])
        assert published == {"published": count, "matched": True, "backend": publish}
        time.sleep(2.0)  # the last messages reach the recorder (it reports at the end)
        recorder.proc.send_signal(signal.SIGINT)
        code, _ = recorder.finish()
        assert code == 0, recorder.lines
    finally:
        if recorder is not None:
            recorder.close()
        publisher.tell("stop")
        publisher.close()
    return bag, recorder.lines


def metadata(bag: pathlib.Path) -> dict[str, Any]:
    """The bag's ``metadata.yaml`` (what ``ros2 bag info`` reads), parsed as rosbags does."""
    from ruamel.yaml import YAML

    return YAML(typ="safe").load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]


def read_bag(bag: pathlib.Path) -> dict[str, list[tuple[int, bytes]]]:
    """Every message of the bag by topic, with rosbags' reader: (timestamp, raw CDR)."""
    from rosbags.rosbag2 import Reader

    found: dict[str, list[tuple[int, bytes]]] = {}
    with Reader(bag) as reader:
        for connection, timestamp, raw in reader.messages():
            found.setdefault(connection.topic, []).append((timestamp, bytes(raw)))
    return found


def listened(listener: Proc) -> list[dict[str, Any]]:
    return json.loads(listener.read_until("RESULT ")[len("RESULT "):])["messages"]


# --------------------------------------------------------------------------- round trip
@pytest.mark.parametrize("publish,accept,storage", [("warp", "warp", "mcap"),
                                                    ("cpu", "cpu", "sqlite3")])
def test_record_then_play_round_trips_every_message_byte_identically(
        tmp_path, domain, topic, publish, accept, storage):
    from rosidl_buffer.messages import get_typestore, serialize_message

    bag, report = record(tmp_path, domain, topic, publish=publish, accept=accept,
                         storage=storage)
    assert report[-1].startswith("dropped 0: 0 because"), report
    stored = read_bag(bag)
    # Every message, in order, byte for byte what the publisher published (as CPU CDR).
    for index in range(COUNT):
        tensor, text = expected_messages(index, SIZE)
        assert stored[topic][index][1] == bytes(serialize_message(tensor))
        assert stored[topic + "_text"][index][1] == bytes(serialize_message(text))
    # rosbags' own deserializer reads it (the bag is no private format).
    decoded = get_typestore().deserialize_cdr(stored[topic][3][1], TENSOR)
    assert np.array_equal(decoded.data, frame_bytes(3, SIZE)) and list(decoded.shape) == [SIZE]

    # Play into a listener in another process: the same bytes, by the backend asked for.
    listener = helper("listen", domain, topic, "--count", str(COUNT), "--accept", accept)
    try:
        listener.read_until("READY")
        played = run_bag(domain, "play", str(bag), "--backend", accept,
                         "--wait-for-subscribers", "10")
        assert played.returncode == 0, played.stderr
        assert played.stdout.startswith(f"played {2 * COUNT} messages"), played.stdout
        got = listened(listener)
    finally:
        listener.tell("stop")
        listener.close()
    for name in (topic, topic + "_text"):
        received = [m for m in got if m["topic"] == name]
        assert [bytes.fromhex(m["cdr"]) for m in received] == [raw for _, raw in stored[name]]
    assert {m["backend"] for m in got if m["topic"] == topic} == {accept}
    _assert_timing([m["t"] for m in got if m["topic"] == topic],
                   [stamp for stamp, _ in stored[topic]], rate=1.0)


def _assert_timing(arrivals: list[float], stamps: list[int], rate: float) -> None:
    """The player's publish times follow the recorded ones (scaled by ``rate``) within
    tolerance (publish times: a subscriber's first import of a warp frame may take longer than
    a frame period, which is no part of the player's timing)."""
    assert (stamps[-1] - stamps[0]) / 1e9 > 0.3, stamps  # 20 Hz: a span to compare against
    played = np.asarray(arrivals) - arrivals[0]
    recorded = (np.asarray(stamps) - stamps[0]) / 1e9 / rate
    span = recorded[-1]
    assert abs(played[-1] - span) < 0.2 * span + 0.05, (played, recorded)
    assert np.max(np.abs(played - recorded)) < 0.25, (played, recorded)


@pytest.fixture(scope="module")
def recorded_bag(tmp_path_factory) -> pathlib.Path:
    """One bag (mcap, warp frames recorded through the warp backend) for the tests below."""
    domain = 900 + os.getpid() % 90
    bag, _ = record(tmp_path_factory.mktemp("bag"), domain, f"/test_bag_cli/m_{os.getpid()}",
                    publish="warp", accept="warp")
    return bag


def test_play_follows_the_rate(recorded_bag, domain):
    topic = read_bag_topics(recorded_bag)[0]
    listener = helper("listen", domain, topic, "--count", str(COUNT))
    try:
        listener.read_until("READY")
        played = run_bag(domain, "play", str(recorded_bag), "--rate", "2",
                         "--wait-for-subscribers", "10")
        assert played.returncode == 0, played.stderr
        got = listened(listener)
    finally:
        listener.tell("stop")
        listener.close()
    stored = read_bag(recorded_bag)
    _assert_timing([m["t"] for m in got if m["topic"] == topic],
                   [stamp for stamp, _ in stored[topic]], rate=2.0)


def read_bag_topics(bag: pathlib.Path) -> list[str]:
    return sorted(read_bag(bag))


def test_the_bag_carries_what_ros2_bag_info_and_play_need(recorded_bag):
    from rosidl_buffer.messages import get_type_hash

    bag = metadata(recorded_bag)
    assert bag["version"] >= 8 and bag["storage_identifier"] == "mcap"
    assert bag["message_count"] == 2 * COUNT
    assert [f["path"] for f in bag["files"]] == bag["relative_file_paths"]
    assert all((recorded_bag / name).is_file() for name in bag["relative_file_paths"])
    assert bag["duration"]["nanoseconds"] > 0 and bag["starting_time"]["nanoseconds_since_epoch"]
    topics = {t["topic_metadata"]["name"]: t for t in bag["topics_with_message_count"]}
    assert sorted(t["message_count"] for t in topics.values()) == [COUNT, COUNT]
    for entry in topics.values():
        meta = entry["topic_metadata"]
        assert meta["type"] in (TENSOR, STRING) and meta["serialization_format"] == "cdr"
        assert meta["type_description_hash"] == get_type_hash(meta["type"])
        if bag["storage_identifier"] == "mcap":  # where rosbag2's MCAP storage reads them
            channel = _mcap_channels(recorded_bag)[meta["name"]]
            assert channel["topic_type_hash"] == meta["type_description_hash"]
            assert "offered_qos_profiles" in channel
        # the publisher's own profile, from the graph (the test publishers keep all, depth COUNT)
        (qos,) = meta["offered_qos_profiles"]
        assert (qos["reliability"], qos["durability"], qos["history"], qos["depth"]) == (
            "reliable", "volatile", "keep_all", COUNT)

    done = run_bag(0, "info", str(recorded_bag))
    assert done.returncode == 0 and done.stderr == "", done.stderr
    lines = done.stdout.splitlines()
    assert lines[0].startswith("Files:") and "Storage id:        mcap" in lines
    assert f"Messages:          {2 * COUNT}" in lines
    assert sum(f"| Count: {COUNT} | Serialization Format: cdr" in line for line in lines) == 2
    as_json = json.loads(run_bag(0, "info", "--json", str(recorded_bag)).stdout)
    assert {t["type_description_hash"] for t in as_json["topics"]} == {
        get_type_hash(TENSOR), get_type_hash(STRING)}


# --------------------------------------------------------------------------- ending a recording
@pytest.mark.parametrize("how", ["SIGINT to the group", "SIGTERM", "--duration"])
def test_a_recording_ended_mid_stream_leaves_a_finalized_readable_bag(tmp_path, domain, topic,
                                                                      how):
    bag = tmp_path / "bag"
    extra = ["--duration", "2.5"] if how == "--duration" else []
    publisher = helper("publish", domain, topic, "--count", "400", "--rate", "50",
                       "--size", str(SIZE))
    recorder = None
    try:
        publisher.read_until("READY")
        # Its own session, as a terminal's foreground job: Ctrl-C goes to the whole group.
        recorder = bag_cli(domain, "record", topic, topic + "_text", "-o", str(bag), *extra,
                           start_new_session=True)
        recorder.read_until(f"recording {topic}_text")
        if how != "--duration":
            time.sleep(2.0)  # mid-stream
            os.killpg(recorder.proc.pid, signal.SIGINT) if how.startswith("SIGINT") else (
                recorder.proc.send_signal(signal.SIGTERM))
        code, out = recorder.finish()
    finally:
        if recorder is not None:
            recorder.close()
        publisher.tell("stop")
        publisher.close()
    assert code == 0, recorder.lines
    summary = next(line for line in recorder.lines if line.startswith("recorded "))
    recorded = int(summary.split()[1])
    stored = read_bag(bag)  # finalized: metadata.yaml written, storage closed
    assert 0 < len(stored[topic]) < 400
    assert len(stored[topic]) + len(stored[topic + "_text"]) == recorded
    assert metadata(bag)["message_count"] == recorded


def test_messages_the_disk_cannot_take_are_dropped_and_counted(tmp_path, domain, topic):
    """The writer stalls (as on a disk that blocks): the cache fills, what does not fit is
    dropped and counted, what fitted is written once the writer resumes."""
    import threading

    from buffer_pubsub import Node
    from rosidl_buffer.messages import deserialize_message, get_message_type

    from warp_buffer_cli.bag.record import Recorder

    size, sent = 10_000, 10
    recorder = Recorder(tmp_path / "bag", max_cache_bytes=3 * size + 500, domain_id=domain,
                        backend="cpu")
    try:
        record = recorder.add(topic, STRING)
        disk = threading.Event()
        write = recorder._writer.write
        recorder._writer.write = lambda *a: (disk.wait(30), write(*a))
        with Node("stalled_disk_publisher", domain_id=domain) as node:
            pub = node.create_publisher(STRING, topic, depth=sent)
            assert pub.wait_for_subscriptions(1, timeout=10)
            for index in range(sent):
                pub.publish(get_message_type(STRING)(data=f"{index:05d}" + "x" * size))
            deadline = time.monotonic() + 10
            while record.dropped + 4 < sent and time.monotonic() < deadline:
                time.sleep(0.02)
            assert record.dropped > 0 and record.messages == 0
            disk.set()
    finally:
        recorder.close()
    assert record.messages + record.dropped == sent and record.lost == 0
    assert record.messages >= 3  # what fitted in the cache (and the one being written)
    texts = [raw for _, raw in read_bag(tmp_path / "bag")[topic]]
    assert len(texts) == record.messages
    numbers = [int(deserialize_message(raw, STRING).data[:5]) for raw in texts]
    assert numbers == sorted(numbers) and numbers[0] == 0  # the oldest kept, in order


def test_the_write_cache_refuses_what_does_not_fit_and_drains_after_close():
    from warp_buffer_cli.bag.cache import WriteCache

    cache = WriteCache(max_bytes=100)
    assert cache.put("a", 60) and not cache.put("b", 60) and cache.put("c", 40)
    assert cache.queued_bytes == 100 == cache.peak_bytes
    assert cache.get() == "a" and cache.put("d", 50)
    cache.close()
    assert not cache.put("e", 1)
    assert [cache.get(), cache.get(), cache.get()] == ["c", "d", None]
    big = WriteCache(max_bytes=10)
    assert big.put("huge", 1000)  # alone it fits: a large message is never refused for good
    assert not big.put("next", 1)
    assert big.get(timeout=0.01) == "huge"
    with pytest.raises(TimeoutError):  # (the writer then flushes what it wrote)
        big.get(timeout=0.01)
    big.close()
    assert big.get(timeout=0.01) is None


# --------------------------------------------------------------------------- bad input, help
def _one_line_error(done: subprocess.CompletedProcess[str], *words: str) -> None:
    assert done.returncode == 1, (done.stdout, done.stderr)
    assert done.stdout == "" and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert "Traceback" not in done.stderr
    for word in words:
        assert word in done.stderr, done.stderr


def test_info_and_play_of_a_missing_or_damaged_bag_fail_in_one_line(tmp_path, domain):
    missing = tmp_path / "nothing"
    _one_line_error(run_bag(domain, "info", str(missing)), "BagReadError", str(missing))
    _one_line_error(run_bag(domain, "play", str(missing)), "BagReadError")
    damaged = tmp_path / "damaged"
    damaged.mkdir()
    (damaged / "metadata.yaml").write_text("rosbag2_bagfile_information: [1, 2\n")
    _one_line_error(run_bag(domain, "info", str(damaged)), "BagReadError", str(damaged))
    _one_line_error(run_bag(domain, "play", str(damaged)), "BagReadError")
    empty = tmp_path / "empty"  # a directory that exists is not said not to
    empty.mkdir()
    _one_line_error(run_bag(domain, "info", str(empty)), "BagReadError", "no metadata.yaml",
                    "not a rosbag2 bag")


def test_play_of_a_topic_the_bag_lacks_fails_in_one_line(recorded_bag, domain):
    done = run_bag(domain, "play", str(recorded_bag), "--topics", "/not_there")
    _one_line_error(done, "UnknownTopicError", "/not_there", read_bag_topics(recorded_bag)[0])


def test_record_of_an_unknown_topic_fails_in_one_line_and_creates_nothing(tmp_path, domain):
    bag = tmp_path / "bag"
    done = run_bag(domain, "record", "/nobody_publishes", "-o", str(bag),
                   "--discovery-timeout", "1")
    _one_line_error(done, "UnknownTopicError", "/nobody_publishes")
    assert not bag.exists()


def test_record_of_a_type_not_known_here_fails_in_one_line(tmp_path, domain, topic):
    bag = tmp_path / "bag"
    publisher = helper("publish", domain, topic, "--custom", "--count", "1")
    try:
        publisher.read_until("READY")
        done = run_bag(domain, "record", topic, "-o", str(bag))
    finally:
        publisher.tell("stop")
        publisher.close()
    _one_line_error(done, "UnknownMessageTypeError", CUSTOM, topic)
    assert not bag.exists()


def _write_custom_bag(path: pathlib.Path, definition: str) -> None:
    """A bag of a type this process does not know, written by rosbags alone."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(CUSTOM_DEFINITION, CUSTOM))
    msg = store.types[CUSTOM](value=7, label="seven")
    with Writer(path, version=9) as writer:
        connection = writer.add_connection("/custom", CUSTOM, msgdef=definition,
                                           rihs01=store.hash_rihs01(CUSTOM))
        for index in range(3):
            writer.write(connection, 1_000_000_000 + index * 10_000_000,
                         store.serialize_cdr(msg, CUSTOM))


def test_play_builds_types_it_does_not_know_from_the_bags_definitions(tmp_path, domain):
    bag = tmp_path / "custom"
    _write_custom_bag(bag, CUSTOM_DEFINITION)
    done = run_bag(domain, "play", str(bag), "--wait-for-subscribers", "0")
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("played 3 messages")
    bare = tmp_path / "bare"
    _write_custom_bag(bare, "")
    _one_line_error(run_bag(domain, "play", str(bare), "--wait-for-subscribers", "0"),
                    "UnknownMessageTypeError", CUSTOM)


@pytest.mark.parametrize("argv", [["record"], ["record", "-a", "/x"], ["play"],
                                  ["play", "b", "--rate", "0"], ["record", "/x", "-s", "zip"],
                                  ["record", "bad topic!"], []])
def test_bad_usage_exits_2_with_a_usage_line(argv):
    done = run_bag(0, *argv)
    assert done.returncode == 2 and done.stdout == "", (done.stdout, done.stderr)
    assert "usage:" in done.stderr or "error:" in done.stderr


@pytest.mark.parametrize("argv", [[], ["record"], ["play"], ["info"]])
def test_help_everywhere(argv):
    done = run_bag(0, *argv, "--help")
    assert done.returncode == 0 and done.stdout.startswith("usage: warp-buffer bag"), done.stderr


# --------------------------------------------------------------------------- progress
def test_progress_goes_to_a_terminal_only(recorded_bag, domain):
    env = dict(child_env(), ROS_DOMAIN_ID=str(domain))
    argv = [sys.executable, "-m", "warp_buffer_cli.main", "bag", "play", str(recorded_bag),
            "--wait-for-subscribers", "0"]
    piped = subprocess.run(argv, cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert piped.returncode == 0 and piped.stderr == "", piped.stderr
    master, slave = pty.openpty()
    try:
        done = subprocess.run(argv, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=slave,
                              text=True, timeout=120)
        os.close(slave)
        slave = -1
        seen = b""
        while True:
            try:
                chunk = os.read(master, 4096)
            except OSError:  # the terminal closed: all read
                break
            if not chunk:
                break
            seen += chunk
    finally:
        if slave >= 0:
            os.close(slave)
        os.close(master)
    assert done.returncode == 0
    assert b"played " in seen and b"msg/s" in seen and b"MiB" in seen, seen
    assert done.stdout.startswith("played ") and "msg/s" not in done.stdout


# --------------------------------------------------------------------------- the benchmark
def test_the_record_benchmark_runs_and_reports_both_backends(tmp_path):
    """``python -m benchmarks.bag_record`` (figures are not judged here: speed lives there)."""
    out = tmp_path / "figures.json"
    done = subprocess.run(
        [sys.executable, "-m", "benchmarks.bag_record", "--seconds", "0.5", "--size", "64K",
         "--rate", "20", "--rounds", "1", "--dir", str(tmp_path), "--json", str(out)],
        cwd=ROOT, env=child_env(), capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "warp median" in done.stdout and "cpu median" in done.stdout
    rows = json.loads(out.read_text())["rows"]
    assert {r["backend"] for r in rows} == {"warp", "cpu"}
    for r in rows:
        assert r["published"] == 10 and 0 < r["recorded"] <= 10
        assert r["recorded"] + r["dropped"] + r["lost"] == r["published"]
    assert [p.name for p in tmp_path.iterdir()] == ["figures.json"]  # bags deleted


# --------------------------------------------------------------------------- reindex
def _frame_index(raw: bytes, size: int) -> int | None:
    """Which frame a stored tensor CDR is (None: none of the published ones)."""
    from rosidl_buffer.messages import deserialize_message

    data = deserialize_message(raw, TENSOR).data.to_numpy()
    for index in range(400):
        if np.array_equal(data, frame_bytes(index, size)):
            return index
    return None


def _kill_a_recording(bag: pathlib.Path, domain: int, topic: str, storage: str,
                      publish: list[str], wait: Any) -> None:
    """Record ``topic`` (and its text topic) of a publisher run with ``publish`` options into
    ``bag``; SIGKILL the recorder once ``wait(publisher, recorder)`` returns."""
    publisher = helper("publish", domain, topic, *publish)
    recorder = None
    try:
        publisher.read_until("READY")
        recorder = bag_cli(domain, "record", topic, topic + "_text", "-o", str(bag), "-s",
                           storage)
        wait(publisher, recorder)
        recorder.proc.kill()  # no chance to close: no metadata.yaml, no MCAP footer
        recorder.proc.wait(timeout=30)
    finally:
        if recorder is not None:
            recorder.close()
        publisher.tell("stop")
        publisher.close()


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_a_killed_recording_is_made_readable_by_reindex(tmp_path, domain, topic, storage):
    bag = tmp_path / "killed"

    def mid_stream(publisher: Proc, recorder: Proc) -> None:
        recorder.read_until(f"recording {topic}_text")
        time.sleep(3.0)  # mid-stream, past a sqlite3 commit

    _kill_a_recording(bag, domain, topic, storage,
                      ["--count", "400", "--rate", "50", "--size", str(SIZE)], mid_stream)
    assert not (bag / "metadata.yaml").exists()
    _one_line_error(run_bag(domain, "info", str(bag)), "BagReadError", "bag reindex")
    done = run_bag(domain, "reindex", str(bag))
    assert done.returncode == 0 and done.stderr == "", done.stderr
    assert done.stdout.startswith(f"reindexed {bag}: ")
    suffix = {"mcap": "mcap", "sqlite3": "db3"}[storage]
    assert sorted(p.name for p in bag.iterdir()) == [f"killed.{suffix}", "metadata.yaml"]
    stored = read_bag(bag)
    frames = stored[topic]
    assert len(frames) > 10  # at 50/s for 3 s, what reached the disk
    indexes = [_frame_index(raw, SIZE) for _, raw in frames]
    assert None not in indexes and indexes == sorted(set(indexes))  # intact, in order, once
    assert metadata(bag)["message_count"] == len(frames) + len(stored.get(topic + "_text", []))
    hashes = {t["topic_metadata"]["name"]: t["topic_metadata"]["type_description_hash"]
              for t in metadata(bag)["topics_with_message_count"]}
    from rosidl_buffer.messages import get_type_hash

    assert hashes[topic] == get_type_hash(TENSOR)  # (MCAP channels carry it)
    info = run_bag(domain, "info", "--json", str(bag))
    assert info.returncode == 0 and json.loads(info.stdout)["messages"] == len(frames) + len(
        stored.get(topic + "_text", []))
    again = run_bag(domain, "reindex", str(bag))  # a readable bag is left as it is
    assert again.returncode == 0 and read_bag(bag) == stored


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_a_recording_killed_while_idle_keeps_every_small_message(tmp_path, domain, topic,
                                                                  storage):
    """Small messages (far below rosbags' 1 MiB MCAP chunk) reach the file within a second of
    their write even when no later message comes to push them out."""
    bag = tmp_path / "idle"
    count, size = 12, 1024

    def idle_after_the_last(publisher: Proc, recorder: Proc) -> None:
        published = json.loads(publisher.read_until("RESULT ")[len("RESULT "):])
        assert published["published"] == count and published["matched"]
        time.sleep(3.0)  # the last messages reach the recorder, then past the flush

    _kill_a_recording(bag, domain, topic, storage, ["--count", str(count), "--size", str(size)],
                      idle_after_the_last)
    done = run_bag(domain, "reindex", str(bag))
    assert done.returncode == 0, done.stderr
    stored = read_bag(bag)
    assert [_frame_index(raw, size) for _, raw in stored[topic]] == list(range(count))
    assert len(stored[topic + "_text"]) == count


def _closed_mcap_bag(path: pathlib.Path, count: int) -> list[bytes]:
    """A closed MCAP bag of ``count`` large tensor messages (a chunk each); their CDR."""
    from rosbags.rosbag2 import StoragePlugin

    from rosidl_buffer.messages import get_typestore, serialize_message
    from warp_buffer_cli.bag.writer import DIRECT_BYTES, BagWriter

    payloads = [bytes(serialize_message(expected_messages(i, DIRECT_BYTES)[0]))
                for i in range(count)]
    writer = BagWriter(path, version=BagWriter.VERSION_LATEST, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    connection = writer.add_connection("/frames", TENSOR, typestore=get_typestore())
    for i, payload in enumerate(payloads):
        writer.write(connection, 1_000 + i, payload)
    writer.close()
    return payloads


def _record_offsets(path: pathlib.Path, opcode: int) -> list[int]:
    import struct

    data = path.read_bytes()
    offsets, at = [], 8
    while at + 9 <= len(data):
        op, length = struct.unpack_from("<BQ", data, at)
        if op == opcode:
            offsets.append(at)
        at += 9 + length
    return offsets


def _mcap_channels(bag: pathlib.Path) -> dict[str, dict[str, str]]:
    """Each channel's metadata by topic, read by the ``mcap`` library."""
    from mcap.reader import make_reader

    (path,) = bag.glob("*.mcap")
    with path.open("rb") as handle:
        summary = make_reader(handle).get_summary()
    return {c.topic: dict(c.metadata) for c in summary.channels.values()}


def _independent_read(path: pathlib.Path) -> tuple[Any, list[tuple[int, bytes]]]:
    """The summary and the (log time, data) of every message, read through the summary's
    indexes by the ``mcap`` library (the format's reference reader, not rosbags)."""
    from mcap.reader import make_reader

    with path.open("rb") as handle:
        reader = make_reader(handle)
        summary = reader.get_summary()
        messages = [(m.log_time, bytes(m.data)) for _, _, m in reader.iter_messages(
            log_time_order=False)]
    return summary, messages


@pytest.mark.parametrize("cut", ["inside the fourth chunk", "inside a record header",
                                 "right after the fourth chunk", "inside the fourth chunk's index",
                                 "after the data section"])
def test_reindex_ends_an_mcap_file_as_its_writer_would(tmp_path, domain, cut):
    from warp_buffer_cli.bag.reindex import reindex

    bag = tmp_path / "bag"
    payloads = _closed_mcap_bag(bag, 5)
    mcap = bag / "bag.mcap"
    chunks = _record_offsets(mcap, 0x06)[1:]  # (the first holds the schema and the channel)
    indexes = _record_offsets(mcap, 0x07)[-5:]  # (one after each message's chunk)
    assert len(chunks) == 5 and all(i > c for i, c in zip(indexes, chunks))
    at = {"inside the fourth chunk": chunks[3] + 1000, "inside a record header": chunks[3] + 4,
          "right after the fourth chunk": indexes[3],
          "inside the fourth chunk's index": indexes[3] + 12,
          "after the data section": _record_offsets(mcap, 0x0F)[0] + 3}[cut]
    with mcap.open("r+b") as file:
        file.truncate(at)
    (bag / "metadata.yaml").unlink()
    report = reindex(bag)
    kept = {"after the data section": 5, "right after the fourth chunk": 4,
            "inside the fourth chunk's index": 4}.get(cut, 3)
    assert report["messages"] == kept and report["topics"] == 1
    assert report["cut_bytes"] > 0 or cut == "right after the fourth chunk"
    assert [raw for _, raw in read_bag(bag)["/frames"]] == payloads[:kept]
    # Indexed as its writer would have left it: a summary with every chunk and message.
    summary, messages = _independent_read(mcap)
    assert len(summary.chunk_indexes) == kept + 1 and summary.statistics.message_count == kept
    assert [data for _, data in messages] == payloads[:kept]


@pytest.mark.parametrize("damage", ["last chunk", "zeroed tail", "chunk in the middle",
                                    "zeroes inside a chunk", "zeroes over a chunk's head"])
def test_reindex_cuts_a_damaged_end_and_refuses_damage_inside(tmp_path, damage):
    """A power cut can leave the last chunk's bytes wrong, or zeroed pages, at the end: cut off
    like a record cut short. Damage before intact records is refused, the file untouched."""
    from warp_buffer_cli.bag.errors import BagReadError
    from warp_buffer_cli.bag.reindex import reindex

    bag = tmp_path / "bag"
    payloads = _closed_mcap_bag(bag, 5)
    mcap = bag / "bag.mcap"
    chunks = _record_offsets(mcap, 0x06)[1:]
    indexes = _record_offsets(mcap, 0x07)[-5:]
    end = _record_offsets(mcap, 0x0F)[0] if damage == "zeroed tail" else indexes[4]
    with mcap.open("r+b") as file:
        file.truncate(end)  # (the last chunk's index lost with the summary)
        if damage == "zeroed tail":
            file.seek(end)
            file.write(bytes(8192))
        elif damage == "zeroes inside a chunk":  # over a message record's head, inside
            file.seek(chunks[2] + 9 + 40)
            file.write(bytes(200))
        elif damage == "zeroes over a chunk's head":
            file.seek(chunks[2])
            file.write(bytes(200))
        else:  # the chunk's compression name said to run past the chunk
            file.seek((chunks[4] if damage == "last chunk" else chunks[2]) + 9 + 28)
            file.write(b"\xff\xff\xff\xff")
    (bag / "metadata.yaml").unlink()
    if damage not in ("last chunk", "zeroed tail"):
        before = mcap.read_bytes()
        with pytest.raises(BagReadError, match="damaged record|zeroed bytes"):
            reindex(bag)
        assert mcap.read_bytes() == before
        return
    kept = 4 if damage == "last chunk" else 5
    assert reindex(bag)["messages"] == kept
    assert [raw for _, raw in read_bag(bag)["/frames"]] == payloads[:kept]


@pytest.mark.parametrize("kept", [0, 5, 8, 13, 20, 42])
def test_an_mcap_file_killed_before_its_header_was_whole_becomes_an_empty_bag(tmp_path, kept):
    """A recorder killed as it started leaves its file empty or its header cut short: nothing
    was recorded, and the bag says so (as an empty sqlite3 bag does), instead of an error that
    points back at reindex."""
    from warp_buffer_cli.bag.reindex import reindex

    bag = tmp_path / "bag"
    _closed_mcap_bag(bag, 1)
    mcap = bag / "bag.mcap"
    assert _record_offsets(mcap, 0x01) == [8]  # (the header: bytes 8-42 and a little more)
    with mcap.open("r+b") as file:
        file.truncate(kept)
    (bag / "metadata.yaml").unlink()
    report = reindex(bag)
    assert report["messages"] == 0 and report["topics"] == 0 and report["cut_bytes"] == kept
    assert read_bag(bag) == {} and metadata(bag)["message_count"] == 0
    summary, messages = _independent_read(mcap)
    assert summary.statistics.message_count == 0 and messages == []


def test_reindex_of_a_closed_mcap_file_without_metadata_keeps_the_type_hashes(tmp_path):
    from rosidl_buffer.messages import get_type_hash
    from warp_buffer_cli.bag.reindex import reindex

    bag = tmp_path / "bag"
    _closed_mcap_bag(bag, 1)
    (bag / "metadata.yaml").unlink()
    assert reindex(bag)["cut_bytes"] == 0
    (topic,) = metadata(bag)["topics_with_message_count"]
    assert topic["topic_metadata"]["type_description_hash"] == get_type_hash(TENSOR)


def test_reindex_leaves_a_bag_its_recorder_closed_as_it_is(tmp_path, domain):
    bag = tmp_path / "bag"
    _closed_mcap_bag(bag, 2)
    before = {p.name: p.read_bytes() for p in bag.iterdir()}
    done = run_bag(domain, "reindex", str(bag))
    assert done.returncode == 0 and "left as it is" in done.stdout, done.stdout
    assert {p.name: p.read_bytes() for p in bag.iterdir()} == before  # the hashes kept
    file = run_bag(domain, "reindex", str(bag / "bag.mcap"))
    _one_line_error(file, "BagReadError", "give the bag's directory")


def test_info_of_a_bag_being_recorded_says_so_instead_of_pointing_at_reindex(tmp_path, domain):
    from rosbags.rosbag2 import StoragePlugin

    from warp_buffer_cli.bag.writer import BagWriter

    bag = tmp_path / "bag"
    writer = BagWriter(bag, version=BagWriter.VERSION_LATEST, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    try:
        busy = run_bag(domain, "info", str(bag))
    finally:
        writer.close()
    _one_line_error(busy, "BagReadError", "being recorded")
    assert "reindex" not in busy.stderr


def test_a_reindexed_bag_reads_in_time_order_whatever_the_write_order(tmp_path):
    """A recorder writes messages of two topics as their callbacks hand them over, which can
    be out of time order by a little; a closed bag is read in time order through its index, and
    so is a reindexed one (a scan of an unindexed file refuses such a file)."""
    from rosbags.rosbag2 import StoragePlugin

    from rosidl_buffer.messages import get_typestore
    from warp_buffer_cli.bag.reindex import reindex
    from warp_buffer_cli.bag.writer import BagWriter

    bag = tmp_path / "bag"
    writer = BagWriter(bag, version=BagWriter.VERSION_LATEST, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    store = get_typestore()
    first = writer.add_connection("/a", "std_msgs/msg/String", typestore=store)
    second = writer.add_connection("/b", "std_msgs/msg/String", typestore=store)
    stamps = [(first, 30), (second, 10), (first, 20), (second, 50), (first, 40)]
    for connection, stamp in stamps:
        writer.write(connection, stamp, b"\x00\x01\x00\x00" + bytes([stamp, 0, 0, 0]))
    writer.close()
    mcap = bag / "bag.mcap"
    with mcap.open("r+b") as file:
        file.truncate(_record_offsets(mcap, 0x0F)[0])  # the summary, as a kill leaves it
    (bag / "metadata.yaml").unlink()
    assert reindex(bag)["messages"] == 5
    stored = read_bag(bag)
    assert [t for t, _ in stored["/a"]] == [20, 30, 40] and [t for t, _ in stored["/b"]] == [10, 50]
    summary, messages = _independent_read(mcap)
    assert summary.statistics.channel_message_counts == {1: 3, 2: 2}
    assert sorted(t for t, _ in messages) == [10, 20, 30, 40, 50]


def test_reindex_refuses_what_is_no_bag_in_one_line(tmp_path, domain):
    empty = tmp_path / "empty"
    empty.mkdir()
    _one_line_error(run_bag(domain, "reindex", str(empty)), "BagReadError", "reindex needs one")
    garbage = tmp_path / "garbage"
    garbage.mkdir()
    (garbage / "garbage.mcap").write_bytes(b"not an mcap file at all")
    _one_line_error(run_bag(domain, "reindex", str(garbage)), "BagReadError", "not an MCAP file")
    assert (garbage / "garbage.mcap").read_bytes() == b"not an mcap file at all"  # untouched
    _one_line_error(run_bag(domain, "reindex", str(tmp_path / "missing")), "BagReadError")


# --------------------------------------------------------------------------- damage, skips, empty
def _text_bag(path: pathlib.Path, payloads: dict[str, list[bytes]], crc: bool = False) -> None:
    """A closed MCAP bag of std_msgs/String topics, ``payloads`` as given (CDR or not), one
    message per 10 ms in turn; ``crc``: each chunk carries its checksum, as rosbag2's own
    MCAP writer puts there (rosbags writes none)."""
    import struct
    import zlib

    from rosbags.rosbag2 import StoragePlugin

    from rosidl_buffer.messages import get_typestore
    from warp_buffer_cli.bag.writer import BagWriter

    with BagWriter(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = {t: writer.add_connection(t, STRING, typestore=get_typestore())
                       for t in payloads}
        stamp = 1_000_000_000
        for index in range(max(len(p) for p in payloads.values())):
            for name, items in payloads.items():
                if index < len(items):
                    writer.write(connections[name], stamp, items[index])
                    stamp += 10_000_000
    if crc:
        mcap = next(path.glob("*.mcap"))
        data = bytearray(mcap.read_bytes())
        for at in _record_offsets(mcap, 0x06):
            size, = struct.unpack_from("<Q", data, at + 9 + 16)
            (name_length,) = struct.unpack_from("<I", data, at + 9 + 28)
            content = at + 9 + 32 + name_length + 8
            struct.pack_into("<I", data, at + 9 + 24, zlib.crc32(data[content:content + size]))
        mcap.write_bytes(bytes(data))


def _texts(count: int, prefix: str = "text") -> list[bytes]:
    from rosidl_buffer.messages import get_message_type, serialize_message

    return [bytes(serialize_message(get_message_type(STRING)(data=f"{prefix} {i:04d}")))
            for i in range(count)]


def test_a_closed_bag_damaged_mid_file_fails_info_play_and_reindex_in_one_line(tmp_path,
                                                                              domain):
    """A user trial: bytes overwritten inside a chunk of a recorded bag. play printed rosbags'
    OverflowError as a traceback, info said nothing, reindex left it 'as it is'."""
    bag = tmp_path / "bag"
    texts = _texts(200)
    _text_bag(bag, {"/t": texts})
    mcap = bag / "bag.mcap"
    data = bytearray(mcap.read_bytes())
    head = data.index(texts[100]) - 31  # message 100's record: its length overwritten
    data[head + 1:head + 9] = b"\xff" * 8
    mcap.write_bytes(bytes(data))
    for command in (["info"], ["play", "--wait-for-subscribers", "0"], ["reindex"]):
        _one_line_error(run_bag(domain, *command, str(bag)), "BagDamagedError", str(mcap),
                        "damaged")
    assert mcap.read_bytes() == data  # reindex changed nothing


def test_reindex_refuses_a_closed_bag_whose_file_was_cut_short_since(tmp_path, domain):
    """A bag trial: half of a closed bag's MCAP file cut off. reindex rewrote its
    metadata.yaml to 0 messages (its only record of 100) and said it succeeded."""
    bag = tmp_path / "bag"
    _text_bag(bag, {"/t": _texts(100)})
    mcap = bag / "bag.mcap"
    mcap.write_bytes(mcap.read_bytes()[:mcap.stat().st_size // 2])
    metadata = (bag / "metadata.yaml").read_bytes()
    _one_line_error(run_bag(domain, "reindex", str(bag)), "BagDamagedError",
                    "records 100 messages")
    assert (bag / "metadata.yaml").read_bytes() == metadata and mcap.stat().st_size > 0


def test_a_fifo_in_a_bag_is_an_error_not_a_hang(tmp_path, domain):
    """A named pipe in place of the storage file: info and reindex blocked for ever."""
    bag = tmp_path / "bag"
    _text_bag(bag, {"/t": _texts(3)})
    (bag / "bag.mcap").unlink()
    os.mkfifo(bag / "bag.mcap")
    for command in ("info", "reindex"):
        _one_line_error(run_bag(domain, command, str(bag)), "BagReadError",
                        "bag.mcap is not a regular file")


def test_info_names_the_storage_plugin_not_a_compressed_files_suffix(tmp_path, domain):
    """A file-compressed bag (bag.mcap.zstd) showed "Storage id: zstd"; a bare file's missing
    distro showed "None"."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

    from rosidl_buffer.messages import get_typestore

    for plugin, name in ((StoragePlugin.MCAP, "mcap"), (StoragePlugin.SQLITE3, "sqlite3")):
        bag = tmp_path / name
        writer = Writer(bag, version=9, storage_plugin=plugin)
        writer.set_compression(CompressionMode.FILE, CompressionFormat.ZSTD)
        with writer:
            connection = writer.add_connection("/t", STRING, typestore=get_typestore())
            writer.write(connection, 1_000, _texts(1)[0])
        assert any(p.suffix == ".zstd" for p in bag.iterdir())
        out = run_bag(domain, "info", str(bag)).stdout
        assert f"Storage id:        {name}\n" in out, out
    bare = tmp_path / "bare"
    _text_bag(bare, {"/t": _texts(2)})
    out = run_bag(domain, "info", str(bare / "bare.mcap")).stdout
    assert "ROS Distro:        \n" in out and "None" not in out, out


def test_play_of_a_bag_whose_checksum_fails_mid_file_fails_in_one_line(tmp_path, domain):
    """Damage the check at open cannot see (a payload byte; the chunk's checksum catches it as
    rosbags reads it) ends the playback with the typed error, not rosbags' traceback."""
    bag = tmp_path / "bag"
    texts = _texts(20)
    _text_bag(bag, {"/t": texts}, crc=True)
    mcap = bag / "bag.mcap"
    data = bytearray(mcap.read_bytes())
    data[data.index(texts[10]) + 9] ^= 0x01  # a letter of message 10's text
    mcap.write_bytes(bytes(data))
    assert run_bag(domain, "info", str(bag)).returncode == 0  # (no payload is read there)
    _one_line_error(run_bag(domain, "play", str(bag), "--wait-for-subscribers", "0"),
                    "BagDamagedError", str(bag), "checksum")


def test_play_skips_undecodable_messages_counts_them_and_exits_1(tmp_path, domain):
    bag = tmp_path / "bag"
    good = _texts(6)
    bad = b"\x00\x01\x00\x00\xff\xff\xff\x7fshort"  # a string longer than the message
    _text_bag(bag, {"/a": [good[0], bad, good[1], bad, good[2]], "/b": good[3:]})
    done = run_bag(domain, "play", str(bag), "--wait-for-subscribers", "0")
    assert done.returncode == 1 and "Traceback" not in done.stderr, done.stderr
    assert done.stdout.startswith("played 6 messages"), done.stdout  # the rest went out
    assert "  /a  std_msgs/msg/String  3 messages" in done.stdout
    assert "skipped 2 undecodable" in done.stdout
    (line,) = done.stderr.strip().splitlines()  # one line per topic with skips: /a only
    # /a's second message: the bag's third stamp (/a and /b take turns, 10 ms apart)
    for word in ("DeserializationError", "skipped 2 undecodable messages of /a", STRING,
                 "the first at 1.020000000 s", "truncated"):
        assert word in line, line


def test_record_with_nothing_published_leaves_an_empty_valid_bag(tmp_path, domain):
    """As ros2 bag record: the reported bag exists (it was reported and never created), and
    the reported time is the recording's, from its start to the stop."""
    from rosbags.rosbag2 import Reader

    bag = tmp_path / "bag"
    done = run_bag(domain, "record", "-a", "-o", str(bag), "--duration", "1")
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith(f"recorded 0 messages, 0 B, in 1.0"), done.stdout
    assert f"to {bag} (mcap)" in done.stdout
    assert sorted(p.name for p in bag.iterdir()) == ["bag.mcap", "metadata.yaml"]
    with Reader(bag) as reader:
        assert reader.message_count == 0 and list(reader.messages()) == []
    info = run_bag(domain, "info", str(bag))
    assert info.returncode == 0 and "Messages:          0" in info.stdout, info.stderr


def test_the_recording_time_ends_when_the_stop_is_asked_not_after_teardown(tmp_path, domain):
    from warp_buffer_cli.bag.record import Recorder

    recorder = Recorder(tmp_path / "bag", domain_id=domain, backend="cpu")
    teardown = recorder.node.close
    recorder.node.close = lambda: (time.sleep(1.0), teardown())[1]  # a slow Zenoh teardown
    try:
        recorder.create()
        time.sleep(0.3)
    finally:
        recorder.close()
    assert 0.3 <= recorder.duration() < 0.8
    assert metadata(tmp_path / "bag")["message_count"] == 0


def test_a_latched_topic_is_recorded_with_its_history_and_played_latched(tmp_path, domain, topic):
    """As rosbag2: when every publisher of a topic is transient-local, the recorder subscribes
    transient-local (a map published before the recording started is in the bag) and the
    player publishes it so (a subscriber that comes after the playback still gets it)."""
    from buffer_pubsub import Node
    from rosidl_buffer.messages import deserialize_message, get_message_type

    from warp_buffer_cli.bag.play import Player
    from warp_buffer_cli.bag.qos import latched
    from warp_buffer_cli.bag.record import Recorder
    from tests._reliability_helpers import wait_until

    string = get_message_type(STRING)
    bag = tmp_path / "bag"
    with Node("latched_source", domain_id=domain) as node:
        pub = node.create_publisher(STRING, topic, depth=1, durability="transient_local")
        pub.publish(string(data="the map"))
        recorder = Recorder(bag, domain_id=domain, backend="cpu")
        try:
            assert wait_until(lambda: recorder.node.count_publishers(topic) == 1, 10)
            record = recorder.add(topic, STRING)
            assert wait_until(lambda: record.messages == 1, 10)
        finally:
            recorder.close()
    assert [deserialize_message(raw, STRING).data for _, raw in read_bag(bag)[topic]] == \
        ["the map"]
    got = []
    with Player(bag, domain_id=domain) as player:
        assert all(latched(c.ext.offered_qos_profiles) for c in player.connections)
        player.play()
        with Node("late_reader", domain_id=domain) as node:
            node.create_subscription(STRING, topic, lambda m: got.append(m.data),
                                     durability="transient_local")
            assert wait_until(lambda: got, 10)
    assert got == ["the map"]


def _as_unprivileged(argv: list[str]) -> list[str]:
    """``argv`` run so that file modes apply: root (the CI's user) drops the capabilities
    that override them; anyone else meets them anyway."""
    if os.geteuid() != 0:
        return argv
    drop = "-dac_override,-dac_read_search"
    return ["setpriv", f"--bounding-set={drop}", f"--inh-caps={drop}", "--", *argv]


def test_a_bag_this_user_may_not_read_or_write_is_a_one_line_error(tmp_path, domain):
    """A mode-000 bag gave a PermissionError traceback from info, play and reindex, and so did
    record into a directory it may not search."""
    bag = tmp_path / "bag"
    _text_bag(bag, {"/t": _texts(3)})
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o000)
    env = dict(child_env(), ROS_DOMAIN_ID=str(domain))
    base = [sys.executable, "-m", "warp_buffer_cli.main", "bag"]
    try:
        bag.chmod(0o000)
        for command, error in (("info", "BagReadError"), ("play", "BagReadError"),
                               ("reindex", "BagReadError")):
            done = subprocess.run(_as_unprivileged([*base, command, str(bag)]), cwd=ROOT,
                                  env=env, capture_output=True, text=True, timeout=120)
            _one_line_error(done, error, "Permission denied")
        done = subprocess.run(
            _as_unprivileged([*base, "record", "/t", "-o", str(locked / "new"),
                              "--duration", "1"]),
            cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
        _one_line_error(done, "BagWriteError", "Permission denied")
    finally:
        bag.chmod(0o755)
        locked.chmod(0o755)


def test_a_file_that_is_no_bag_gets_no_reindex_hint(tmp_path, domain):
    """``bag info notes.py`` suggested ``bag reindex``, which then found no storage file."""
    notes = tmp_path / "notes.py"
    notes.write_text("print(1)\n")
    done = run_bag(domain, "info", str(notes))
    _one_line_error(done, "BagReadError", "notes.py")
    assert "reindex" not in done.stderr
    cut = tmp_path / "cut"
    _text_bag(cut, {"/t": _texts(3)})
    (cut / "metadata.yaml").unlink()
    storage = cut / "cut.mcap"
    storage.write_bytes(storage.read_bytes()[:100])
    _one_line_error(run_bag(domain, "info", str(storage)), "BagReadError",
                    f"warp-buffer bag reindex {cut}")
