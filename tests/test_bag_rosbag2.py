"""``bag info`` / ``bag play`` of bags shaped as rosbag2 itself writes them, not as rosbags does.

Each bag is built here with Foxglove's ``mcap`` writer after rosbag2's sources: its MCAP storage
(mcap_storage.cpp: a schema and a channel per topic, the channel's ``offered_qos_profiles`` YAML,
the ``fastwrite`` preset writing no chunks) and its metadata (yaml.hpp, qos.cpp: Foxy's bags store
deadline 0 in ``metadata.yaml`` and rmw's "infinite" 2147483647 s 4294967295 ns in the file).
"""

from __future__ import annotations

import io
import pathlib
import struct
import subprocess
import sys

import pytest

from tests._pubsub_helpers import child_env

ROOT = pathlib.Path(__file__).resolve().parent.parent
STRING = "std_msgs/msg/String"
STRING_SCHEMA = "# comment kept, as rosbag2 stores the .msg file\nstring data\n"
FOXY_INFINITE = {"sec": 2147483647, "nsec": 4294967295}  # RMW_*_FOXY_INFINITE (qos.cpp)
T0 = 1_585_866_235_000_000_000


def _qos(*, reliability: int | str = 1, durability: int | str = 2, deadline: dict | None = None,
         history: int | str = 3, depth: int = 0) -> dict:
    """One offered profile as rosbag2 writes it (Foxy: enums as rmw's numbers, reliable=1,
    best-effort=2, volatile=2; version 9: their names)."""
    unset = {"sec": 0, "nsec": 0}
    return {"history": history, "depth": depth, "reliability": reliability,
            "durability": durability, "deadline": deadline or unset, "lifespan": unset,
            "liveliness": 1, "liveliness_lease_duration": deadline or unset,
            "avoid_ros_namespace_conventions": False}


def _yaml(data: object) -> str:
    from ruamel.yaml import YAML

    out = io.StringIO()
    yaml = YAML(typ="safe")
    yaml.default_flow_style = False
    yaml.dump(data, out)
    return out.getvalue()


def _cdr_string(text: str) -> bytes:
    raw = text.encode() + b"\0"
    return b"\x00\x01\x00\x00" + struct.pack("<I", len(raw)) + raw


def write_bag(path: pathlib.Path, topics: list[dict], *, chunked: bool = True,
              version: int = 4, order: list[int] | None = None) -> None:
    """A rosbag2-shaped MCAP bag. Each topic: name, type, schema (``ros2msg`` text), ``file``
    and ``yaml`` profiles (the storage's and metadata.yaml's), ``count`` messages (CDR strings
    unless ``payload`` says), ``in_file`` (False: listed in metadata.yaml only). Messages take
    turns 1 ms apart; ``order`` permutes their write order (the log times stay)."""
    from mcap.writer import CompressionType, Writer

    path.mkdir()
    name = f"{path.name}_0.mcap"
    messages = []
    with open(path / name, "wb") as file:
        writer = Writer(file, compression=CompressionType.NONE, use_chunking=chunked,
                        enable_crcs=chunked)
        writer.start(profile="ros2", library="libmcap cpp v1.4.0")
        for topic in topics:
            if not topic.get("in_file", True):
                continue
            schema = writer.register_schema(topic["type"], "ros2msg", topic["schema"].encode())
            channel = writer.register_channel(topic["name"], "cdr", schema,
                                              {"offered_qos_profiles": _yaml(topic["file"])})
            payload = topic.get("payload", _cdr_string)
            messages += [(channel, i, payload(f"{topic['name']} {i}"))
                         for i in range(topic["count"])]
        messages.sort(key=lambda m: (m[1], m[0]))
        stamped = [(channel, T0 + k * 1_000_000, data)
                   for k, (channel, _, data) in enumerate(messages)]
        for k in (order or range(len(stamped))):
            channel, stamp, data = stamped[k]
            writer.add_message(channel, log_time=stamp, publish_time=stamp, data=data)
        writer.finish()
    duration = len(stamped) and (len(stamped) - 1) * 1_000_000
    entries = [{"topic_metadata": {"name": t["name"], "type": t["type"],
                                   "serialization_format": "cdr",
                                   "offered_qos_profiles": _yaml(t["yaml"])},
                "message_count": t["count"]} for t in topics]
    meta = {"version": version, "storage_identifier": "mcap", "relative_file_paths": [name],
            "duration": {"nanoseconds": duration},
            "starting_time": {"nanoseconds_since_epoch": T0},
            "message_count": sum(t["count"] for t in topics if t.get("in_file", True)),
            "topics_with_message_count": entries,
            "compression_format": "", "compression_mode": ""}
    (path / "metadata.yaml").write_text(_yaml({"rosbag2_bagfile_information": meta}))


def foxy_topic(name: str, count: int, **more: object) -> dict:
    """A topic as Foxy's rosbag2 stored it: deadline 0 in metadata.yaml, infinite in the file."""
    return {"name": name, "type": STRING, "schema": STRING_SCHEMA, "count": count,
            "file": [_qos(deadline=FOXY_INFINITE)], "yaml": [_qos()], **more}


def play(bag: pathlib.Path, domain: int) -> dict[str, int]:
    """Play the whole bag fast; messages published by topic."""
    from warp_buffer_cli.bag.play import Player

    with Player(bag, domain_id=domain, rate=1000.0) as player:
        player.play()
        return {t.topic: t.messages for t in player.topics.values()}


def run_bag(domain: int, *argv: str) -> subprocess.CompletedProcess[str]:
    env = dict(child_env(), ROS_DOMAIN_ID=str(domain))
    return subprocess.run([sys.executable, "-m", "warp_buffer_cli.main", "bag", *argv],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)


# --------------------------------------------------------------------------- tests
def test_a_foxy_bag_whose_file_says_infinite_where_its_metadata_says_0_plays_every_message(
        tmp_path, domain):
    """Audit: rosbag2_py's talker test bags played 0 of 20 messages and exited 0 (rosbags paired
    the file's topics with metadata.yaml's only on equal QoS)."""
    bag = tmp_path / "talker"
    write_bag(bag, [foxy_topic("/talker_a", 4), foxy_topic("/talker_b", 3),
                    foxy_topic("/talker_none", 0)])
    assert play(bag, domain) == {"/talker_a": 4, "/talker_b": 3, "/talker_none": 0}


def test_a_topic_the_storage_does_not_give_is_a_typed_error_not_a_short_playback(tmp_path,
                                                                                  domain):
    from warp_buffer_cli.bag.errors import BagDamagedError

    bag = tmp_path / "short"
    write_bag(bag, [foxy_topic("/kept", 3), foxy_topic("/gone", 2, in_file=False)])
    with pytest.raises(BagDamagedError, match=r"/gone \(std_msgs/msg/String\) 0 of 2"):
        play(bag, domain)


def test_an_unchunked_mcap_file_is_described_and_played_in_time_order(tmp_path, domain):
    """rosbag2's fastwrite preset (mcap_storage.cpp: noChunking) writes messages as they come,
    outside any chunk: not damage, and a reader gives them in log-time order."""
    from rosidl_buffer.messages import deserialize_message

    from warp_buffer_cli.bag.info import describe
    from warp_buffer_cli.bag.play import Player

    bag = tmp_path / "fastwrite"
    topics = [dict(foxy_topic("/fast_a", 3), file=[_qos()]), dict(foxy_topic("/fast_b", 3),
                                                                   file=[_qos()])]
    write_bag(bag, topics, chunked=False, order=[1, 0, 2, 3, 5, 4])  # two swapped pairs
    assert describe(bag)["messages"] == 6
    with Player(bag, domain_id=domain, rate=1000.0) as player:
        seen = [(c.topic, stamp, deserialize_message(data, STRING).data)
                for c, stamp, data in player._messages()]
        player.play()
        assert player.totals()[0] == 6
    assert [s for _, s, _ in seen] == sorted(s for _, s, _ in seen)
    assert [text for _, _, text in seen] == ["/fast_a 0", "/fast_b 0", "/fast_a 1",
                                            "/fast_b 1", "/fast_a 2", "/fast_b 2"]


SERVICE_EVENT_SCHEMA = ("MSG: demo_srvs/srv/Ping_Event\nint32 value\n---\nint32 echoed\n")


def test_a_topic_of_a_type_that_cannot_be_built_is_skipped_with_one_warning(tmp_path, domain):
    """As rosbag2's player (player.cpp: "Ignoring a topic"): a service event topic that
    `ros2 bag record -a` captured, its schema a .srv text, is skipped; the rest plays."""
    bag = tmp_path / "events"
    event = {"name": "/ping/_service_event", "type": "demo_srvs/srv/Ping_Event",
             "schema": SERVICE_EVENT_SCHEMA, "count": 2, "file": [_qos()], "yaml": [_qos()],
             "payload": lambda _: b"\x00\x01\x00\x00" + struct.pack("<i", 7)}
    write_bag(bag, [event, dict(foxy_topic("/beside_events", 3), file=[_qos()])])
    done = run_bag(domain, "play", str(bag), "--rate", "1000", "--wait-for-subscribers", "0")
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
    assert done.stdout.startswith("played 3 messages"), done.stdout
    (line,) = done.stderr.strip().splitlines()
    for word in ("warning", "/ping/_service_event", "demo_srvs/srv/Ping_Event"):
        assert word in line, line


@pytest.mark.parametrize("recorded,played", [(["best_effort"], "best_effort"),
                                             (["best_effort", "best_effort"], "best_effort"),
                                             (["best_effort", "reliable"], "reliable"),
                                             (["reliable"], "reliable")])
def test_the_recorded_reliability_is_offered_again(tmp_path, domain, recorded, played):
    """qos.cpp adapt_offer_to_recorded_offers: the recorded profile when all publishers agree,
    rosbag2's reliable default when they differ."""
    from buffer_pubsub import wire

    from tests._reliability_helpers import wait_until
    from warp_buffer_cli.bag.play import Player

    profiles = [_qos(reliability=r, durability="volatile", history="keep_last", depth=5)
                for r in recorded]
    bag = tmp_path / "qos"
    write_bag(bag, [dict(foxy_topic("/qos_t", 1), file=profiles, yaml=profiles)], version=9)
    with Player(bag, domain_id=domain) as player:  # (its publisher as the graph shows it)
        assert wait_until(lambda: player.node.get_publishers_info_by_topic("/qos_t"), 10)
        (info,) = player.node.get_publishers_info_by_topic("/qos_t")
        best_effort = info.qos_profile.reliability == wire.RELIABILITY_BEST_EFFORT
    assert ("best_effort" if best_effort else "reliable") == played


def test_two_connections_of_a_topic_with_different_qos_stay_apart(tmp_path):
    """Pairing by topic and type must not merge what rosbags wrote as two connections."""
    from rosbags.rosbag2 import Writer

    from rosidl_buffer.messages import get_typestore
    from warp_buffer_cli.bag.play import open_bag
    from warp_buffer_cli.bag.qos import offered_profile
    from warp_buffer_cli.bag.storage_messages import bag_messages

    bag = tmp_path / "two"
    with Writer(bag, version=9) as writer:
        for index, best_effort in enumerate((False, True)):
            c = writer.add_connection("/two", STRING, typestore=get_typestore(),
                                      offered_qos_profiles=[offered_profile(
                                          best_effort=best_effort)])
            for k in range(index + 2):
                writer.write(c, T0 + k, _cdr_string(f"{index}"))
    reader = open_bag(bag)
    try:
        read = [c.id for c, _, _ in bag_messages(reader, reader.connections)]
        assert sorted(read) == [1, 1, 2, 2, 2]
    finally:
        reader.close()
