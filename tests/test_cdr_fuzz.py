"""Malformed CDR input raises typed errors only: truncation, bad lengths, bad strings, fuzzing.

The quick fuzz runs a few thousand examples. For a long run, either select the slow tests
(``pytest -m slow tests/test_cdr_fuzz.py``) or set ``HYPOTHESIS_PROFILE=long``, which also
scales up the quick tests.
"""

from __future__ import annotations

import os
import struct

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from plugins.fake_backend import FAKE_BACKEND, FakeBackend, FakeBufferImpl
from plugins.message_tools import MIXED_TYPE, message_strategy

from rosidl_buffer import (
    Buffer,
    DeserializationError,
    EndpointInfo,
    EndpointType,
    RosidlBufferError,
    local_host_id,
)
from rosidl_buffer.messages import (
    CDR_HEADER,
    deserialize_message,
    get_message_type,
    register_message_definitions,
    serialize_message,
)

BOUNDED_TYPE = "warp_buffer_test_msgs/msg/Bounded"
register_message_definitions({BOUNDED_TYPE: "int16[<=5] values\nstring<=4 tag\n"})

FUZZ_TYPES = [
    MIXED_TYPE,
    BOUNDED_TYPE,
    "sensor_msgs/msg/Image",
    "sensor_msgs/msg/JointState",
    "tensor_msgs/msg/ExperimentalTensor",
    "diagnostic_msgs/msg/DiagnosticArray",
    "visualization_msgs/msg/MarkerArray",
]

LONG_RUN = os.environ.get("HYPOTHESIS_PROFILE") == "long"
QUICK_EXAMPLES = 10_000 if LONG_RUN else 300
LONG_EXAMPLES = 10_000


def fuzz_settings(examples: int) -> settings:
    return settings(max_examples=examples, deadline=None, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


PUBLISHER = EndpointInfo(
    gid=bytes(range(16)), node_name="talker", node_namespace="/", topic_name="/fuzz",
    topic_type="sensor_msgs/msg/Image", endpoint_type=EndpointType.PUBLISHER,
    host_id=local_host_id(), process_id=os.getpid(), user_id=os.getuid(),
)
BACKEND = FakeBackend()


def decode(data: bytes, type_name: str):
    return deserialize_message(data, type_name, backends={FAKE_BACKEND: BACKEND},
                               endpoint_info=PUBLISHER)


def decode_or_typed_error(data: bytes, type_name: str) -> None:
    """Any input either decodes to a message of the type or raises a RosidlBufferError."""
    try:
        message = decode(data, type_name)
    except RosidlBufferError:
        return
    assert message.__msgtype__ == type_name


# ------------------------------------------------------------------------------- valid inputs
def mixed_wire(route=None) -> bytes:
    point = get_message_type("geometry_msgs/msg/Point")
    mixed = get_message_type(MIXED_TYPE)(
        first=b"\x01\x02\x03", values=[1.0, 2.0], ids=[3], bounded=[1, 2], name="né",
        names=["a", ""], short_name="s", points=[point(x=1.0)],
        last=Buffer(FakeBufferImpl(b"payload")))
    return bytes(serialize_message(mixed, route=route))


def fake_route(buffer):
    return FAKE_BACKEND, BACKEND.create_descriptor_with_endpoint(buffer.get_impl(), PUBLISHER)


VALID_WIRES = {
    "mixed-cpu": (MIXED_TYPE, mixed_wire()),
    "mixed-backend": (MIXED_TYPE, mixed_wire(route=fake_route)),
    "image": ("sensor_msgs/msg/Image", bytes(serialize_message(
        get_message_type("sensor_msgs/msg/Image")(encoding="mono8", data=b"\x05" * 9)))),
}


@pytest.mark.parametrize("case", sorted(VALID_WIRES))
def test_every_truncation_is_a_deserialization_error(case):
    type_name, wire = VALID_WIRES[case]
    assert decode(wire, type_name) is not None  # the whole message is valid
    for length in range(len(wire)):
        with pytest.raises(DeserializationError):
            decode(wire[:length], type_name)


def test_trailing_padding_is_ignored():
    type_name, wire = VALID_WIRES["image"]
    assert decode(wire + bytes(3), type_name) == decode(wire, type_name)


# ------------------------------------------------------------------------------- crafted inputs
def u32(value: int) -> bytes:
    return struct.pack("<I", value)


def cdr_string(text: bytes) -> bytes:
    return u32(len(text)) + text


# Hand-built fields (lengths chosen so that no padding is needed between them).
HEADER = u32(0) + u32(0) + cdr_string(b"map\x00")  # std_msgs/Header: stamp, frame_id
# sensor_msgs/Image up to its data: height, width, encoding, is_bigendian, step
IMAGE_SCALARS = u32(1) + u32(2) + cdr_string(b"mono16\x00") + b"\x00" + u32(2)

MALFORMED = {
    # encapsulation header
    "empty": (b"", "std_msgs/msg/String"),
    "short-header": (b"\x00\x01", "std_msgs/msg/String"),
    "big-endian": (b"\x00\x00\x00\x00" + cdr_string(b"a\x00"), "std_msgs/msg/String"),
    "unknown-encoding": (b"\x01\x07\x00\x00" + cdr_string(b"a\x00"), "std_msgs/msg/String"),
    # strings
    "string-length-zero": (CDR_HEADER + u32(0), "std_msgs/msg/String"),
    "string-missing-nul": (CDR_HEADER + cdr_string(b"abc"), "std_msgs/msg/String"),
    "string-bad-utf8": (CDR_HEADER + cdr_string(b"\xff\xfe\x00"), "std_msgs/msg/String"),
    "string-length-huge": (CDR_HEADER + u32(0x7FFFFFFF) + b"ab\x00", "std_msgs/msg/String"),
    "string-length-marker": (CDR_HEADER + u32(0xFFFFFFFF) + b"ab\x00", "std_msgs/msg/String"),
    "string-over-bound": (CDR_HEADER + u32(0) + cdr_string(b"toolong\x00"), BOUNDED_TYPE),
    # sequences
    "bounded-over-bound": (CDR_HEADER + u32(6) + bytes(12) + cdr_string(b"\x00"), BOUNDED_TYPE),
    "buffer-count-huge": (CDR_HEADER + HEADER + IMAGE_SCALARS + u32(0xFFFFFFFE) + b"ab",
                          "sensor_msgs/msg/Image"),
    "buffer-count-one-over": (CDR_HEADER + HEADER + IMAGE_SCALARS + u32(3) + b"ab",
                              "sensor_msgs/msg/Image"),
    "string-seq-count-huge": (CDR_HEADER + HEADER + u32(0xFFFFFFF0),
                              "sensor_msgs/msg/JointState"),
    "float-seq-count-huge": (CDR_HEADER + HEADER + u32(0) + u32(0x20000000) + bytes(16),
                             "sensor_msgs/msg/JointState"),
    "message-seq-count-huge": (CDR_HEADER + HEADER + u32(0x10000000) + bytes(64),
                               "diagnostic_msgs/msg/DiagnosticArray"),
    # backend form (two marker words, upstream's buffer_serialization.hpp)
    "backend-name-unknown": (CDR_HEADER + HEADER + IMAGE_SCALARS + u32(0xFFFFFFFF)
                             + u32(0x524F5332) + cdr_string(b"nope\x00") + bytes(32),
                             "sensor_msgs/msg/Image"),
    "backend-name-missing": (CDR_HEADER + HEADER + IMAGE_SCALARS + u32(0xFFFFFFFF)
                             + u32(0x524F5332), "sensor_msgs/msg/Image"),
    "backend-descriptor-missing": (CDR_HEADER + HEADER + IMAGE_SCALARS + u32(0xFFFFFFFF)
                                   + u32(0x524F5332) + cdr_string(b"fake\x00"),
                                   "sensor_msgs/msg/Image"),
    # a first marker word alone is the length of an ordinary sequence (far too long here)
    "backend-one-marker-only": (CDR_HEADER + HEADER + IMAGE_SCALARS + u32(0xFFFFFFFF)
                                + cdr_string(b"fake\x00") + bytes(32), "sensor_msgs/msg/Image"),
    "backend-second-marker-wrong": (CDR_HEADER + HEADER + IMAGE_SCALARS + u32(0xFFFFFFFF)
                                    + u32(0x324F5352) + cdr_string(b"fake\x00") + bytes(32),
                                    "sensor_msgs/msg/Image"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_input_is_a_deserialization_error(case):
    data, type_name = MALFORMED[case]
    with pytest.raises(DeserializationError) as excinfo:
        decode(data, type_name)
    assert isinstance(excinfo.value, RosidlBufferError) and isinstance(excinfo.value, ValueError)


CRAFTED_VALID = {
    "string": (CDR_HEADER + cdr_string(b"\xc3\xa9\x00"), "std_msgs/msg/String"),
    "bounded": (CDR_HEADER + u32(4) + bytes(8) + cdr_string(b"tag\x00"), BOUNDED_TYPE),
    "image": (CDR_HEADER + HEADER + IMAGE_SCALARS + u32(2) + b"ab", "sensor_msgs/msg/Image"),
    "joint-state": (CDR_HEADER + HEADER + u32(0) * 4, "sensor_msgs/msg/JointState"),
    "diagnostics": (CDR_HEADER + HEADER + u32(0), "diagnostic_msgs/msg/DiagnosticArray"),
}


@pytest.mark.parametrize("case", sorted(CRAFTED_VALID))
def test_crafted_inputs_without_the_defect_decode(case):
    """The malformed cases differ from these valid inputs only where intended."""
    data, type_name = CRAFTED_VALID[case]
    message = decode(data, type_name)
    assert serialize_message(message) == data


def test_unknown_message_type_name_is_typed():
    with pytest.raises(RosidlBufferError):
        deserialize_message(VALID_WIRES["image"][1], "no_pkg/msg/Nothing")


# ------------------------------------------------------------------------------- fuzzing
def check_random_bytes(type_name: str, body: bytes, header: bytes) -> None:
    decode_or_typed_error(header + body, type_name)


MUTATION = st.tuples(st.sampled_from(["flip", "set", "insert", "delete", "truncate"]),
                     st.integers(0, 1 << 16), st.integers(0, 255))


def mutate(wire: bytes, mutations) -> bytes:
    data = bytearray(wire)
    for operation, where, value in mutations:
        index = where % (len(data) + 1)
        if operation == "insert":
            data[index:index] = bytes([value])
        elif operation == "truncate":
            del data[index:]
        elif index < len(data):
            if operation == "flip":
                data[index] ^= 1 << (value % 8)
            elif operation == "set":
                data[index] = value
            else:
                del data[index]
    return bytes(data)


def check_mutated_message(type_name: str, data: st.DataObject) -> None:
    message = data.draw(message_strategy(type_name), label="message")
    wire = bytes(serialize_message(message))
    assert decode(wire, type_name) == message
    mutations = data.draw(st.lists(MUTATION, min_size=1, max_size=4), label="mutations")
    decode_or_typed_error(mutate(wire, mutations), type_name)


HEADERS = st.sampled_from([CDR_HEADER, b"\x00\x01\x00\x02", b"\x00\x00\x00\x00", b""])


@pytest.mark.parametrize("type_name", FUZZ_TYPES)
@fuzz_settings(QUICK_EXAMPLES)
@given(body=st.binary(max_size=256), header=HEADERS)
def test_fuzz_random_bytes(type_name, body, header):
    check_random_bytes(type_name, body, header)


@pytest.mark.parametrize("type_name", FUZZ_TYPES)
@fuzz_settings(QUICK_EXAMPLES)
@given(data=st.data())
def test_fuzz_mutated_messages(type_name, data):
    check_mutated_message(type_name, data)


@pytest.mark.parametrize("case", sorted(VALID_WIRES))
@fuzz_settings(QUICK_EXAMPLES)
@given(mutations=st.lists(MUTATION, min_size=1, max_size=4))
def test_fuzz_mutated_fixed_messages(case, mutations):
    type_name, wire = VALID_WIRES[case]
    decode_or_typed_error(mutate(wire, mutations), type_name)


@pytest.mark.slow
@pytest.mark.parametrize("type_name", FUZZ_TYPES)
def test_long_fuzz(type_name, request):
    if "slow" not in (request.config.option.markexpr or "") and not LONG_RUN:
        pytest.skip("long fuzz: opt in with `-m slow` or HYPOTHESIS_PROFILE=long")
    long = fuzz_settings(LONG_EXAMPLES)
    long(given(body=st.binary(max_size=1024), header=HEADERS)(
        lambda body, header: check_random_bytes(type_name, body, header)))()
    long(given(data=st.data())(lambda data: check_mutated_message(type_name, data)))()
