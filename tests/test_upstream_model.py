"""The independent model of rmw_zenoh 0.10.5 / 0.12.0 (tests/upstream_model) against values
worked out by hand from upstream's sources (liveliness_utils.cpp, qos.cpp, graph_cache.cpp,
attachment_helpers.cpp, buffer_serialization.hpp, rmw_subscription_data.cpp), and two
process-level checks of the model talking to itself."""

from __future__ import annotations

import hashlib
import json
import pathlib
import struct
import subprocess
import sys

import numpy as np
import pytest
import xxhash
from rosbags.typesys import get_types_from_msg

from tests.upstream_model import attachment, cdr, liveliness, messages
from tests.upstream_model import qos as qos_model
from tests.upstream_model.backends import FakeBackend
from tests.upstream_model.graph import GraphCache
from tests.upstream_model.peer import BackendNotInstalled, _acceptable_backends

ROOT = pathlib.Path(__file__).resolve().parent.parent
ZID = "f0e1d2c3b4a5968778695a4b3c2d1e0f"
IMAGE_HASH = "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47"
IMAGE_DDS = "sensor_msgs::msg::dds_::Image_"
# Endpoint prefix of node "talker" (namespace "/", enclave "/") on domain 0, node id 0.
PREFIX = f"@ros2_lv/0/{ZID}/0"
IMAGE_TAIL = f"%camera%image/{IMAGE_DDS}/{IMAGE_HASH}"
# keep_last 10, everything else rmw_zenoh's default: only the depth is written.
QOS_DEPTH_10 = "::,10:,:,:,,"


@pytest.fixture(scope="module")
def store():
    return messages.make_typestore()


def image_publisher(backends: dict[str, str] | None, *, legacy: bool = False
                    ) -> liveliness.Entity:
    topic = liveliness.TopicInfo(domain_id=0, name="/camera/image", type=IMAGE_DDS,
                                 type_hash=IMAGE_HASH, qos=qos_model.adapt(qos_model.QoS()),
                                 backend_metadata=backends)
    node = liveliness.NodeInfo(domain_id=0, namespace="/", name="talker", enclave="/")
    return liveliness.Entity(zid=ZID, nid="0", id="1", kind=liveliness.PUBLISHER, node=node,
                             topic=topic, legacy=legacy)


# ------------------------------------------------------------------------------ tokens
def test_publisher_token_with_backends_is_upstreams_layout() -> None:
    entity = image_publisher({"cuda": "dev=0;x:y/z", "cpu": ""})
    assert entity.keyexpr == (f"{PREFIX}/1/MP/%/%/talker/{IMAGE_TAIL}/{QOS_DEPTH_10}/"
                              "backends:cpu:;cuda:dev=0%3Bx%3Ay%2Fz")
    assert entity.topic.topic_keyexpr == f"0/camera/image/{IMAGE_DDS}/{IMAGE_HASH}"


def test_token_without_backends_has_13_segments_and_legacy_never_writes_a_14th() -> None:
    expected = f"{PREFIX}/1/MP/%/%/talker/{IMAGE_TAIL}/{QOS_DEPTH_10}"
    assert image_publisher(None).keyexpr == expected
    assert image_publisher({}).keyexpr == expected  # an empty map writes nothing
    assert image_publisher({"cpu": ""}, legacy=True).keyexpr == expected


def test_node_token() -> None:
    node = liveliness.Entity(zid=ZID, nid="3", id="3", kind=liveliness.NODE,
                             node=liveliness.NodeInfo(0, "/robot1", "cam", "/"))
    assert node.keyexpr == f"@ros2_lv/0/{ZID}/3/3/NN/%/%robot1/cam"


def test_backends_segment_sorts_by_bytes_and_escapes_only_four_characters() -> None:
    segment = liveliness.backends_segment({"b": "", "B": "1", "a_": "50%", "x%y": "k=v#?"})
    assert segment == "backends:B:1;a_:50%25;b:;x%25y:k=v#?"


def test_gid_is_xxh3_128_of_the_token_low_then_high_little_endian() -> None:
    entity = image_publisher({"cuda": "dev=0;x:y/z", "cpu": ""})
    text = (f"{PREFIX}/1/MP/%/%/talker/{IMAGE_TAIL}/{QOS_DEPTH_10}/"
            "backends:cpu:;cuda:dev=0%3Bx%3Ay%2Fz")
    value = xxhash.xxh3_128_intdigest(text.encode())
    expected = struct.pack("<QQ", value & (2**64 - 1), value >> 64)
    assert entity.gid == expected
    assert entity.gid_hex == expected.hex() and len(entity.gid_hex) == 32
    # The canonical XXH3 digest is big endian (high first): the gid is its byte reversal.
    assert entity.gid == xxhash.xxh3_128_digest(text.encode())[::-1]


def test_parse_rebuilds_canonically() -> None:
    explicit = "1:2:1,42:9223372036,854775807:9223372036,854775807:1,9223372036,854775807"
    token = f"@ros2_lv/007/{ZID}/0/1/MS/%/%/talker/{IMAGE_TAIL}/{explicit}/backends:cuda"
    entity = liveliness.parse(token)
    assert entity is not None
    assert entity.keyexpr == (f"@ros2_lv/7/{ZID}/0/1/MS/%/%/talker/{IMAGE_TAIL}/::,:,:,:,,/"
                              "backends:cuda:")
    assert entity.topic.name == "/camera/image"
    assert entity.topic.backend_metadata == {"cuda": ""}
    assert entity.gid == liveliness.gid_of(entity.keyexpr) != liveliness.gid_of(token)


@pytest.mark.parametrize("extra, rebuilt", [
    ("/backends:", ""),                          # nothing after the prefix: no map
    ("/backends:;;", ""),                        # no entry: no map
    ("/notbackends:cpu:", ""),                   # a 14th segment that is not backends: dropped
    ("/backends:cpu:/more/segments", "/backends:cpu:"),  # after the 14th: dropped
    ("/backends:cuda:%3a%2f;cpu:", "/backends:cpu:;cuda:%3A%2F"),  # lower-case hex decoded
    ("/backends:cuda:%zz%4", "/backends:cuda:%25zz%254"),  # not an escape: kept, re-escaped
    ("/backends:cuda:1;cuda:2", "/backends:cuda:2"),  # a repeated name keeps the last
    ("/backends::meta;cpu:", "/backends:cpu:"),  # an empty name is skipped
])
def test_parse_of_the_14th_segment(extra: str, rebuilt: str) -> None:
    base = f"{PREFIX}/1/MS/%/%/talker/{IMAGE_TAIL}/{QOS_DEPTH_10}"
    entity = liveliness.parse(base + extra)
    assert entity is not None and entity.keyexpr == base + rebuilt


def test_legacy_reader_drops_the_backends_segment_and_so_sees_another_gid() -> None:
    token = image_publisher({"cpu": ""}).keyexpr
    legacy = liveliness.parse(token, legacy=True)
    assert legacy.keyexpr == token.rsplit("/", 1)[0]
    assert legacy.gid != liveliness.parse(token).gid == liveliness.gid_of(token)


@pytest.mark.parametrize("token", [
    f"{PREFIX}/1/MP/%/%/talker/{IMAGE_TAIL}//backends:cpu:",           # empty part
    f"{PREFIX}/1/MP/%/%/talker/{IMAGE_TAIL}/{QOS_DEPTH_10}/",          # empty last part
    f"{PREFIX}/1/MP/%/%/talker/{IMAGE_TAIL}/1:2",                      # too few QoS fields
    f"{PREFIX}/1/MP/%/%/talker/{IMAGE_TAIL}/9::,:,:,:,,",              # no such reliability
    f"{PREFIX}/1/MP/%/%/talker/{IMAGE_TAIL}/01::,:,:,:,,",             # not the canonical text
    f"{PREFIX}/1/MP/%/%/talker/{IMAGE_TAIL}/::,x:,:,:,,",              # depth not a number
    f"{PREFIX}/1/MP/%/%/talker/{IMAGE_TAIL}/::,-1:,:,:,,",             # negative depth
    f"{PREFIX}/1/MP/%/%/talker/{IMAGE_TAIL}/::,10 :,:,:,,",            # junk after the number
    f"{PREFIX}/1/MP/%/%/talker/{IMAGE_TAIL}/::,:,:,:2,,",              # MANUAL_BY_NODE
    f"{PREFIX}/1/MP/%/%/talker/{IMAGE_TAIL}/::,:,:,:,",                # liveliness needs 3
    f"{PREFIX}/1/MP/%/%/talker/%camera%image/{IMAGE_DDS}",              # 12 parts
    f"{PREFIX}/1/XX/%/%/talker/{IMAGE_TAIL}/{QOS_DEPTH_10}",           # unknown entity kind
    f"@ros2_lx/0/{ZID}/0/1/MP/%/%/talker/{IMAGE_TAIL}/{QOS_DEPTH_10}",  # admin space
    f"@ros2_lv/zero/{ZID}/0/1/MP/%/%/talker/{IMAGE_TAIL}/{QOS_DEPTH_10}",  # stoul throws
    f"@ros2_lv/0/{ZID}/0/0/NN/%/%",                                     # 8 parts
])
def test_parse_rejects_what_upstream_rejects(token: str) -> None:
    assert liveliness.parse(token) is None


def test_parse_accepts_what_strtoull_accepts() -> None:
    entity = liveliness.parse(f"{PREFIX}/1/MP/%/%/talker/{IMAGE_TAIL}/::, +10:,:,:,,:extra")
    assert entity is not None and entity.topic.qos.depth == 10
    assert entity.keyexpr.endswith(f"/{QOS_DEPTH_10}")


# ------------------------------------------------------------------------------ QoS
def test_qos_keyexpr_both_ways() -> None:
    assert qos_model.to_keyexpr(qos_model.adapt(qos_model.QoS())) == QOS_DEPTH_10
    odd = qos_model.QoS(history=qos_model.History.KEEP_ALL, depth=0,
                        reliability=qos_model.Reliability.BEST_EFFORT,
                        durability=qos_model.Durability.TRANSIENT_LOCAL, deadline=(1, 500),
                        liveliness=qos_model.Liveliness.MANUAL_BY_TOPIC, lease=(0, 7))
    text = qos_model.to_keyexpr(qos_model.adapt(odd))
    assert text == "2:1:2,:1,500:,:3,0,7"  # depth 0 -> 42 (the default): empty
    assert qos_model.from_keyexpr(text) == qos_model.adapt(odd)
    assert qos_model.from_keyexpr("::,:,:,:,,") == qos_model.DEFAULT_QOS


def test_str_to_size_t() -> None:
    assert qos_model.str_to_size_t("", 42) == 42
    assert qos_model.str_to_size_t(" 7", 0) == 7
    assert qos_model.str_to_size_t("+7", 0) == 7
    assert qos_model.str_to_size_t(" -7", 0) == 2**64 - 7  # strtoull wraps; only text[0] is checked
    for bad in ("-7", "7 ", "0x10", "+", "18446744073709551616"):
        assert qos_model.str_to_size_t(bad, None) is None


# ------------------------------------------------------------------------------ attachment
def test_attachment_is_33_bytes() -> None:
    gid = bytes(range(16))
    data = attachment.pack(1, 2, gid)
    assert data == b"\x01" + bytes(7) + b"\x02" + bytes(7) + b"\x10" + gid
    assert attachment.unpack(data + b"tail") == attachment.Attachment(1, 2, gid)
    assert attachment.unpack(data[:32]) is None
    assert attachment.unpack(data[:16] + b"\x0f" + gid) is None


# ------------------------------------------------------------------------------ CDR framing
PROBE = "upstream_model_probe/msg/Probe"


@pytest.fixture(scope="module")
def probe_store(store):
    store.register(get_types_from_msg("uint8 a\nuint8[] data\nfloat64 after\n", PROBE))
    return store


def test_buffer_fields_are_top_level_unbounded_uint8_sequences(store) -> None:
    assert messages.buffer_fields(store, "sensor_msgs/msg/Image") == ["data"]
    assert messages.buffer_fields(store, "sensor_msgs/msg/PointCloud2") == ["data"]
    assert messages.buffer_fields(store, "std_msgs/msg/UInt8MultiArray") == ["data"]
    assert messages.buffer_fields(store, "std_msgs/msg/String") == []
    assert messages.buffer_fields(store, "stereo_msgs/msg/DisparityImage") == []  # nested Image
    store.register(get_types_from_msg("uint8[<=8] small\nint8[] signed\n",
                                      "upstream_model_probe/msg/NotBuffers"))
    assert messages.buffer_fields(store, "upstream_model_probe/msg/NotBuffers") == []
    if messages.TENSOR_MSG_FILE.exists():
        assert messages.buffer_fields(store, messages.TENSOR) == ["data"]


def test_cpu_form_is_ordinary_cdr(probe_store) -> None:
    msg = messages.default_message(probe_store, PROBE, a=7, after=1.5,
                                   data=np.frombuffer(b"abc", np.uint8))
    expected = (b"\x00\x01\x00\x00" + b"\x07\x00\x00\x00" + b"\x03\x00\x00\x00abc"
                + bytes(5) + struct.pack("<d", 1.5))
    assert cdr.serialize(probe_store, msg, PROBE) == expected
    decoded = cdr.deserialize(probe_store, expected, PROBE, endpoint_aware=False)
    assert decoded.frames["data"] == cdr.FieldFrame(form="cpu", data=b"abc")
    assert decoded.message.after == 1.5
    image = messages.sample_message(probe_store, "sensor_msgs/msg/Image", 3, 13)
    assert cdr.serialize(probe_store, image, "sensor_msgs/msg/Image") == bytes(
        probe_store.serialize_cdr(image, "sensor_msgs/msg/Image"))


def test_backend_form_aligns_from_the_stream_origin(probe_store) -> None:
    descriptor = messages.default_message(probe_store, messages.FAKE_DESCRIPTOR, version=1,
                                          size=3, origin="m",
                                          data=np.frombuffer(b"abc", np.uint8))
    msg = messages.default_message(probe_store, PROBE, a=7, after=1.5,
                                   data=np.frombuffer(b"abc", np.uint8))
    form = cdr.BackendForm("cuda", descriptor, messages.FAKE_DESCRIPTOR)
    payload = cdr.serialize(probe_store, msg, PROBE, {"data": form})
    expected = (b"\x00\x01\x00\x00"
                + b"\x07\x00\x00\x00"                # a, padding to 4
                + b"\xff\xff\xff\xff" + b"\x32\x53\x4f\x52"  # 0xFFFFFFFF, 0x524F5332
                + b"\x05\x00\x00\x00cuda\x00"        # offsets 12..21
                + b"\x01\x00\x00"                    # version at 21, padding to 24
                + struct.pack("<Q", 3)               # size at 24
                + b"\x02\x00\x00\x00m\x00"           # origin at 32..38
                + b"\x00\x00" + b"\x03\x00\x00\x00abc"  # data at 40..47
                + b"\x00" + struct.pack("<d", 1.5))  # after at 48
    assert payload == expected
    decoded = cdr.deserialize(probe_store, payload, PROBE, endpoint_aware=True,
                              descriptor_types={"cuda": messages.FAKE_DESCRIPTOR})
    frame = decoded.frames["data"]
    assert (frame.form, frame.backend, frame.descriptor.size, frame.descriptor.origin) == (
        "backend", "cuda", 3, "m")
    assert FakeBackend.from_descriptor(frame.descriptor) == b"abc"
    assert decoded.message.a == 7 and decoded.message.after == 1.5
    with pytest.raises(cdr.CdrError, match="plain route"):
        cdr.deserialize(probe_store, payload, PROBE, endpoint_aware=False)
    with pytest.raises(cdr.CdrError, match="not available"):
        cdr.deserialize(probe_store, payload, PROBE, endpoint_aware=True)


def test_a_first_word_of_ones_without_the_second_marker_is_a_cpu_length(probe_store) -> None:
    payload = b"\x00\x01\x00\x00" + b"\x07\x00\x00\x00" + b"\xff\xff\xff\xff" + b"ROS3" + bytes(8)
    with pytest.raises(cdr.CdrError, match="ends inside field data"):
        cdr.deserialize(probe_store, payload, PROBE, endpoint_aware=True,
                        descriptor_types={"cuda": messages.FAKE_DESCRIPTOR})


# ------------------------------------------------------------------------------ graph cache
def endpoint(kind: str, eid: str, ros_type: str = IMAGE_DDS, *, zid: str = ZID,
             reliability: int = qos_model.Reliability.RELIABLE) -> str:
    topic = liveliness.TopicInfo(0, "/camera/image", ros_type, IMAGE_HASH,
                                 qos_model.adapt(qos_model.QoS(reliability=reliability)))
    return liveliness.Entity(zid=zid, nid="0", id=eid, kind=kind,
                             node=liveliness.NodeInfo(0, "/", "n", "/"), topic=topic).keyexpr


def test_discovery_callback_fires_only_once_topic_and_type_are_known() -> None:
    graph = GraphCache(ZID)
    seen: list[str] = []
    graph.register_subscriber_discovery("/camera/image", b"pub", lambda e: seen.append(e.id))
    graph.parse_put(endpoint(liveliness.SUBSCRIPTION, "2"))  # first of the topic: nothing
    assert seen == []
    graph.parse_put(endpoint(liveliness.PUBLISHER, "1"))     # a publisher: not this callback
    graph.parse_put(endpoint(liveliness.SUBSCRIPTION, "3"))  # topic and type known: fires
    assert seen == ["3"]
    graph.parse_put(endpoint(liveliness.SUBSCRIPTION, "4", "other::msg::dds_::T_"))  # new type
    graph.parse_put(endpoint(liveliness.SUBSCRIPTION, "5", "other::msg::dds_::T_"))  # fires
    assert seen == ["3", "5"]
    # A new registration replays every known subscription of the topic name, of any type.
    replayed: list[str] = []
    graph.register_subscriber_discovery("/camera/image", b"pub2", lambda e: replayed.append(e.id))
    assert sorted(replayed) == ["2", "3", "4", "5"]


def test_matched_subscriptions_count_same_type_and_compatible_qos() -> None:
    graph = GraphCache(ZID)
    best_effort = qos_model.Reliability.BEST_EFFORT
    for eid, reliability in (("1", best_effort), ("2", qos_model.Reliability.RELIABLE)):
        graph.parse_put(endpoint(liveliness.SUBSCRIPTION, eid, reliability=reliability))
    graph.parse_put(endpoint(liveliness.SUBSCRIPTION, "3", "other::msg::dds_::T_"))
    reliable_pub = liveliness.parse(endpoint(liveliness.PUBLISHER, "9")).topic
    best_effort_pub = liveliness.parse(endpoint(liveliness.PUBLISHER, "9",
                                                reliability=best_effort)).topic
    assert graph.count_matched_subscriptions(reliable_pub) == 2
    assert graph.count_matched_subscriptions(best_effort_pub) == 1
    graph.parse_del(endpoint(liveliness.SUBSCRIPTION, "2"))
    assert graph.count_matched_subscriptions(reliable_pub) == 1


# ------------------------------------------------------------------------------ subscriptions
def test_acceptable_buffer_backends(store) -> None:
    installed = {"cuda": FakeBackend("cuda", "dev=0", store)}
    cpu_only = (["cpu"], {"cpu": ""})
    assert _acceptable_backends(None, installed) == cpu_only
    assert _acceptable_backends("", installed) == cpu_only
    assert _acceptable_backends(" cpu ,\tcpu,", installed) == cpu_only
    assert _acceptable_backends("cpu, any", installed) == (["cuda"], {"cuda": "dev=0"})
    assert _acceptable_backends("any", {}) == ([], {})  # advertises nothing: no 14th segment
    assert _acceptable_backends("cpu,cuda", installed) == (["cuda"], {"cuda": "dev=0"})
    with pytest.raises(BackendNotInstalled, match="'rocm'.*Available backends: cuda"):
        _acceptable_backends("cuda,rocm", installed)


# ------------------------------------------------------------------------------ processes
def start_model(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "tests.upstream_model", *args], cwd=ROOT,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def wait_ready(proc: subprocess.Popen) -> None:
    line = proc.stdout.readline()
    assert line == "READY\n", f"{line!r} {proc.stderr.read() if proc.poll() is not None else ''}"


def finish(proc: subprocess.Popen, timeout: float = 30) -> dict:
    """Close stdin, collect stdout, and return the RESULT json (the only other line)."""
    out, _ = proc.communicate(timeout=timeout)
    lines = out.splitlines()
    assert all(line == "READY" or line.startswith("RESULT ") for line in lines), lines
    return json.loads(lines[-1][len("RESULT "):])


@pytest.fixture
def children():
    procs: list[subprocess.Popen] = []
    yield procs
    for proc in procs:
        if proc.poll() is None:
            proc.kill()
        proc.communicate()


@pytest.mark.multiprocess
def test_model_pub_to_model_sub_delivers_every_image_once(domain, topic, children) -> None:
    common = ["--domain", str(domain), "--topic", topic, "--type", "sensor_msgs/msg/Image"]
    sub = start_model("sub", *common)
    children.append(sub)
    wait_ready(sub)
    pub = start_model("pub", *common, "--wait-subs", "1", "--count", "20", "--rate", "100",
                      "--size", "3000", "--no-stdin")
    children.append(pub)
    sent = finish(pub)
    assert pub.returncode == 0 and sent["error"] is None
    got = finish(sub)
    assert sub.returncode == 0
    puts = sent["puts"]
    assert [p["route"] for p in puts] == ["_buf_cpu"] * 20  # one CPU-only subscription
    assert [p["seq"] for p in puts] == list(range(1, 21))
    assert [s["seq"] for s in got["samples"]] == list(range(1, 21))
    assert [s["sha256"] for s in got["samples"]] == [p["sha256"] for p in puts]
    for index, sample in enumerate(got["samples"]):
        assert sample["gid"] == sent["gid"] and sample["route"] == "_buf_cpu"
        data = sample["decoded"]["buffers"]["data"]
        assert data == {"form": "cpu", "size": 3000,
                        "sha256": hashlib.sha256(messages.payload_pattern(index, 3000)).hexdigest()}
        assert sample["decoded"]["fields"]["header.frame_id"] == f"model/{index}"
    assert got["lost"] == 0
    assert sent["discovered_subscriptions"][0]["gid"] == got["gid"]
    assert liveliness.parse(got["token"]).gid_hex == got["gid"]


@pytest.mark.multiprocess
def test_model_routes_like_upstream(domain, topic, children) -> None:
    """One publish reaches a CUDA subscription on its own key in backend form, a CPU-only one on
    _buf_cpu, and nothing reaches a pre-buffer subscription; each put takes a sequence number,
    so each subscription counts the others' puts as lost."""
    common = ["--domain", str(domain), "--topic", topic, "--type", "sensor_msgs/msg/Image"]
    cuda = start_model("sub", *common, "--backend", "cuda=dev=0",
                       "--acceptable-buffer-backends", "cuda")
    cpu = start_model("sub", *common)
    legacy = start_model("legacy-sub", *common)
    children.extend([cuda, cpu, legacy])
    for proc in (cuda, cpu, legacy):
        wait_ready(proc)
    pub = start_model("pub", *common, "--backend", "cuda=dev=0", "--buffer-backend", "cuda",
                      "--wait-subs", "3", "--count", "3", "--rate", "100", "--size", "64",
                      "--no-stdin")
    children.append(pub)
    sent = finish(pub)
    assert sent["advertised_backends"] == {"cpu": "", "cuda": "dev=0"}
    got = {name: finish(proc) for name, proc in
           (("cuda", cuda), ("cpu", cpu), ("legacy", legacy))}
    assert got["legacy"]["samples"] == []
    assert [s["route"] for s in got["cpu"]["samples"]] == ["_buf_cpu"] * 3
    accelerated = got["cuda"]["samples"]
    assert [s["route"] for s in accelerated] == [f"_buf/{got['cuda']['gid']}"] * 3
    assert all(s["decoded"]["buffers"]["data"]["form"] == "backend" for s in accelerated)
    assert all(s["publisher_known"] for s in accelerated)
    assert [p["seq"] for p in sent["puts"]] == list(range(1, 10))  # 3 puts per publish
    assert got["cpu"]["lost"] == got["cuda"]["lost"] == 4          # gaps of 3, twice each


@pytest.mark.multiprocess
def test_cli_reports_a_backend_that_is_not_installed(domain, topic, children) -> None:
    proc = start_model("sub", "--domain", str(domain), "--topic", topic, "--type",
                       "sensor_msgs/msg/Image", "--acceptable-buffer-backends", "cuda")
    children.append(proc)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 2
    assert out.startswith("RESULT ") and "not installed" in json.loads(out[7:])["error"]
    assert len(err.strip().splitlines()) == 1
