"""Our token rules against values written out by hand from rmw_zenoh 0.10.5's sources
(``liveliness_utils.cpp``: ``qos_to_keyexpr``, ``keyexpr_to_qos``, ``Entity`` constructor and
``Entity::make``, ``escape_backend_field`` / ``unescape_backend_field``). (The sequence and
duplicate rules: tests/test_streams_native.py.)

Every expected string below is what the C++ code produces for the input, worked out by reading it;
none is computed with our functions.
"""

from __future__ import annotations

import xxhash
import pytest

from buffer_pubsub import wire

HASH = "RIHS01_" + "ab" * 32
PREFIX = ("@ros2_lv/3/z1/7/9/MP/%/%/cam/%image/sensor_msgs::msg::dds_::Image_/" + HASH)


def gid_of(text: str) -> bytes:
    digest = xxhash.xxh3_128_intdigest(text.encode())
    return (digest & (2**64 - 1)).to_bytes(8, "little") + (digest >> 64).to_bytes(8, "little")


@pytest.mark.parametrize("qos, text", [
    (wire.QoSProfile(depth=10), "::,10:,:,:,,"),
    (wire.QoSProfile(history=wire.HISTORY_KEEP_ALL, depth=5), "::2,5:,:,:,,"),
    (wire.QoSProfile(reliability=wire.RELIABILITY_BEST_EFFORT, depth=1), "2::,1:,:,:,,"),
    (wire.QoSProfile(durability=wire.DURABILITY_TRANSIENT_LOCAL, depth=1), ":1:,1:,:,:,,"),
    (wire.QoSProfile(deadline=(1, 500), lifespan=(0, 0)), "::,:1,500:0,0:,,"),
    (wire.QoSProfile(liveliness=3, liveliness_lease=(2, 854775807)), "::,:,:,:3,2,"),
])
def test_qos_keyexpr_both_ways(qos, text):
    assert qos.to_keyexpr() == text
    assert wire.QoSProfile.from_keyexpr(text) == qos


def test_default_qos_is_six_empty_fields():
    # R : D : H,depth : Ds,Dns : Ls,Lns : Liv,LivS,LivNs
    assert wire.QoSProfile().to_keyexpr() == "::,:,:,:,,"


def test_a_token_is_rebuilt_canonically_before_it_is_hashed():
    """Explicit default QoS values, a lower-case escape and unsorted backends: rmw_zenoh parses
    the token and rebuilds the key (defaults left out, names sorted, upper-case escapes), then
    hashes that."""
    sent = PREFIX + "/1:2:1,10:,:,:1,,/backends:warp:a%3bb;cpu:"
    rebuilt = PREFIX + "/::,10:,:,:,,/backends:cpu:;warp:a%3Bb"
    token = wire.parse_token(sent)
    assert token.canonical_key() == rebuilt
    assert token.gid == gid_of(rebuilt)
    assert token.backends == {"warp": "a;b", "cpu": ""}


@pytest.mark.parametrize("segment, backends", [
    ("backends:cpu:", {"cpu": ""}),
    ("backends:", None),  # names nothing: the key is rebuilt without it
    ("backends:;;", None),
    ("backends::meta", None),  # an empty name is skipped
    ("backends:cuda", {"cuda": ""}),  # no ':' -> empty metadata
    ("backends:x:1;x:2", {"x": "2"}),  # a repeated name: the last wins
    ("backends:a:b:c", {"a": "b:c"}),  # the first ':' splits name from metadata
    ("backends:a:%zz%4", {"a": "%zz%4"}),  # not two hex digits: kept as is
    ("backends:a:%41%2f", {"a": "A/"}),  # either case of hex
    ("Backends:cpu:", None),  # only "backends:" is a backends segment
])
def test_backends_segment_parsing(segment, backends):
    token = wire.parse_token(PREFIX + "/::,10:,:,:,,/" + segment)
    assert token.backends == backends
    expected = PREFIX + "/::,10:,:,:,,"
    if backends is not None:
        expected += "/backends:" + ";".join(
            f"{n.replace('%', '%25').replace(';', '%3B').replace(':', '%3A').replace('/', '%2F')}:"
            f"{m.replace('%', '%25').replace(';', '%3B').replace(':', '%3A').replace('/', '%2F')}"
            for n, m in sorted(backends.items()))
    assert token.gid == gid_of(expected)


def test_segments_after_the_backends_are_dropped_from_the_gid():
    base = PREFIX + "/::,10:,:,:,,"
    with_backends = base + "/backends:cpu:"
    assert wire.parse_token(with_backends + "/anything").gid == gid_of(with_backends)
    assert wire.parse_token(base + "/not-backends/x").gid == gid_of(base)
    ours = wire.parse_token(with_backends + "/wbloc:h%3Ax:12:1000")
    assert ours.locality == wire.Locality("h:x", 12, 1000) and ours.gid == gid_of(with_backends)


@pytest.mark.parametrize("key", [
    PREFIX.replace("cam", "") + "/::,10:,:,:,,",  # an empty segment
    PREFIX,  # 12 segments: no QoS
    PREFIX + "/::,10:,:",  # too few QoS parts
    PREFIX + "/9::,10:,:,:,,",  # unknown reliability
    PREFIX.replace("/MP/", "/XX/") + "/::,10:,:,:,,",  # unknown entity
    "@ros2_lv/x/z1/7/7/NN/%/%/cam",  # non-numeric domain
])
def test_tokens_rmw_zenoh_rejects_are_refused(key):
    with pytest.raises(wire.WireFormatError):
        wire.parse_token(key)


def test_node_token_layout():
    token = wire.NodeToken(3, "z1", 7, "/robot1", "cam")
    assert token.key() == "@ros2_lv/3/z1/7/7/NN/%/%robot1/cam"
    assert wire.parse_token(token.key()) == token


def test_subscription_channels_follow_rmw_zenoh():
    def sub(backends):
        return wire.EndpointToken(3, "z1", 7, 9, wire.SUBSCRIPTION_KIND, "", "n", "/t",
                                  "sensor_msgs/msg/Image", HASH, wire.QoSProfile.of(10),
                                  backends=backends)

    assert wire.subscription_channel(sub({"cpu": ""})) == wire.SubscriptionChannel.CPU
    assert wire.subscription_channel(sub({"cpu": "x"})) == wire.SubscriptionChannel.CPU
    assert wire.subscription_channel(sub({"cuda": ""})) == wire.SubscriptionChannel.OWN
    assert wire.subscription_channel(sub({"cuda": "", "cpu": ""})) == wire.SubscriptionChannel.OWN
    assert wire.subscription_channel(sub(None)) == wire.SubscriptionChannel.BASE
    assert wire.buffer_channel_key("0/t/T/H", bytes(range(16))) == \
        "0/t/T/H/_buf/000102030405060708090a0b0c0d0e0f"
    assert wire.cpu_channel_key("0/t/T/H") == "0/t/T/H/_buf_cpu"


@pytest.mark.parametrize("value", [" 7", "+7", "\t+12", " -7", "-7", "7 ", "0x10", "+", " ",
                                   "18446744073709551616", "\u0663", "00"])
def test_qos_numbers_parse_as_upstreams_str_to_size_t(value):
    # the independent model of liveliness_utils.cpp (tests/upstream_model/qos.py) decides
    from tests.upstream_model import qos as qos_model

    expected = qos_model.str_to_size_t(value, 42)
    text = f"::,{value}:,:,:,,"
    if expected is None:
        with pytest.raises(wire.WireFormatError):
            wire.QoSProfile.from_keyexpr(text)
    else:
        assert wire.QoSProfile.from_keyexpr(text).depth == expected


def test_a_malformed_locality_of_ours_leaves_the_token_valid_and_foreign():
    """rmw_zenoh never reads past the 14th segment: a token whose last segment is a broken
    ``wbloc:`` is still a publisher (judged foreign: no same-host lane). ``--5`` passed the
    digit check and raised a raw ValueError in Zenoh's callback on every PUT and DELETE."""
    base = PREFIX + "/::,10:,:,:,,/backends:cpu:"
    for segment in ("wbloc:h:--5:0", "wbloc:h:-:1", "wbloc:h:\u0663:1", "wbloc:h:5",
                    "wbloc:h:5:1:nan", "wbloc:h:5:1:-2"):
        token = wire.parse_token(base + "/" + segment)
        assert token.locality is None and token.topic == "/image", segment
        assert token.gid == gid_of(base)
    assert wire.parse_token(base + "/wbloc:h:-5:7").locality == wire.Locality("h", -5, 7)


_KEY_CHARS = "0123456789-%:/,._~@ab\u0663\u00b2\x00"


@pytest.mark.parametrize("seed", range(3))
def test_mutated_tokens_parse_or_are_refused_with_the_typed_error(seed):
    """Any key a peer can declare: a token, None (a kind we do not route) or WireFormatError /
    another RosidlBufferError, never a raw exception out of the parser (Zenoh's callback)."""
    import random

    from rosidl_buffer.errors import RosidlBufferError

    rng = random.Random(seed)
    valid = [PREFIX + "/::,10:,:,:,,/backends:cpu:;warp:v=2/wbloc:h%3Ax:12:1000",
             PREFIX.replace("/MP/", "/MS/") + "/2:1:2,5:,1,1:,:,1,2",
             wire.NodeToken(3, "z1", 7, "/robot1", "cam").key()]
    for _ in range(3000):
        key = list(rng.choice(valid))
        for _ in range(rng.randint(1, 4)):
            at = rng.randrange(len(key) + 1)
            action = rng.random()
            if action < 0.4 and at < len(key):
                key[at] = rng.choice(_KEY_CHARS)
            elif action < 0.7:
                key.insert(at, rng.choice(_KEY_CHARS))
            elif at < len(key):
                del key[at]
        text = "".join(key)
        try:
            token = wire.parse_token(text)
            if isinstance(token, wire.EndpointToken):
                token.gid
        except RosidlBufferError:
            pass


def test_service_and_client_tokens_are_read_for_the_graph():
    """``SS`` / ``SC`` keys have an endpoint's layout (``Entity`` constructor); the graph keeps
    them apart from topics and forgets them on DELETE."""
    import threading

    from buffer_pubsub.graph import Graph

    key = ("@ros2_lv/3/z1/7/12/SS/%/%robot1/cam/%robot1%cam%get_parameters/"
           "rcl_interfaces::srv::dds_::GetParameters_/" + HASH + "/::,10:,:,:,,")
    server = wire.parse_token(key)
    assert server.is_service and server.kind == "SS" and not server.is_publisher
    assert (server.namespace, server.node_name, server.topic, server.type_name) == (
        "/robot1", "cam", "/robot1/cam/get_parameters", "rcl_interfaces/srv/GetParameters")
    client_key = key.replace("/SS/", "/SC/").replace("/12/", "/13/")
    assert wire.parse_token(client_key).is_service
    with pytest.raises(wire.WireFormatError):  # no QoS segment: rmw_zenoh refuses it too
        wire.parse_token(key.rsplit("/", 1)[0])
    graph = Graph(threading.RLock())
    assert graph.put(key, server) == []
    assert graph.put(client_key, wire.parse_token(client_key)) == []
    assert len(graph.services()) == 2 and graph.endpoints() == []
    assert graph.delete(key) == [] and [t.kind for t in graph.services()] == ["SC"]
