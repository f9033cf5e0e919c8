"""CPU serialization is byte-identical to rosbags' ROS 2 CDR, and copies a payload only once."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from plugins.fake_backend import FakeBufferImpl
from plugins.message_tools import MIXED_TYPE, message_strategy, to_rosbags

from rosidl_buffer import Buffer
from rosidl_buffer.messages import (
    CDR_HEADER,
    deserialize_message,
    get_message_type,
    get_typestore,
    serialize_message,
    serialized_size,
)

TYPESTORE = get_typestore()
ALL_TYPES = sorted(TYPESTORE.fielddefs)
# Types with buffers, every array kind, nested message sequences, strings and constants.
SAMPLED_TYPES = [
    MIXED_TYPE,
    "tensor_msgs/msg/ExperimentalTensor",
    "sensor_msgs/msg/Image",
    "sensor_msgs/msg/PointCloud2",
    "sensor_msgs/msg/CameraInfo",
    "sensor_msgs/msg/BatteryState",
    "sensor_msgs/msg/JointState",
    "std_msgs/msg/ByteMultiArray",
    "std_msgs/msg/Char",
    "diagnostic_msgs/msg/DiagnosticArray",
    "rcl_interfaces/msg/ParameterValue",
    "nav_msgs/msg/OccupancyGrid",
    "visualization_msgs/msg/Marker",
    "rmw_dds_common/msg/Gid",
]


def assert_identical_to_rosbags(message) -> bytes:
    """Our bytes equal rosbags' for the same content, and decode back to an equal message."""
    ours = serialize_message(message)
    theirs = bytes(TYPESTORE.serialize_cdr(to_rosbags(message), message.__msgtype__))
    assert bytes(ours) == theirs
    assert serialized_size(message) == len(ours)
    assert deserialize_message(ours, type(message)) == message
    assert deserialize_message(theirs, message.__msgtype__) == message
    return theirs


def mixed_message():
    cls = get_message_type(MIXED_TYPE)
    point = get_message_type("geometry_msgs/msg/Point")
    header = get_message_type("std_msgs/msg/Header")
    stamp = get_message_type("builtin_interfaces/msg/Time")(sec=-7, nanosec=999_999_999)
    return cls(
        first=b"\x01\x02\x03",  # odd length: the float64 after it needs padding
        after_odd_payload=2.5,
        values=[1.0, -2.0],
        after_values=200,
        empty_payload=b"",
        empty_values=[],
        after_empty=7,
        ids=[-(2**63), 2**63 - 1, 0],
        position=[1.5, 2.5, 3.5],
        flags=[True, False],
        bounded=[-1, 2, 3],
        name="näme ✓",
        names=["", "a", "ab\u00e9"],
        short_name="0123456789",
        header=header(stamp=stamp, frame_id="map"),
        points=[point(x=1.0, y=2.0, z=3.0), point(x=-1.0)],
        letter=ord("Z"),
        raw=0xFF,
        last=bytes(range(256)) * 3,
    )


def test_mixed_message_is_byte_identical_to_rosbags():
    wire = assert_identical_to_rosbags(mixed_message())
    assert wire[:4] == CDR_HEADER


def test_mixed_message_round_trips_through_rosbags_deserializer():
    message = mixed_message()
    decoded = TYPESTORE.deserialize_cdr(bytes(serialize_message(message)), MIXED_TYPE)
    assert bytes(decoded.last) == bytes(message.last)
    assert decoded.names == message.names and decoded.header.frame_id == "map"
    assert np.asarray(decoded.ids).tolist() == np.asarray(message.ids).tolist()


@pytest.mark.parametrize(
    "fields",
    [{"first": b"", "values": [1.0]}, {"first": b"\x01", "values": []},
     {"first": b"\x01\x02", "empty_payload": b"\x09", "after_empty": 1, "ids": [5]},
     {"points": [], "names": [""], "bounded": []}],
    ids=["empty-then-float", "odd-then-empty-floats", "short-payloads", "empty-sequences"],
)
def test_alignment_around_sequences(fields):
    assert_identical_to_rosbags(get_message_type(MIXED_TYPE)(**fields))


@pytest.mark.parametrize("type_name", ALL_TYPES)
def test_default_message_of_every_type_is_byte_identical(type_name):
    assert_identical_to_rosbags(get_message_type(type_name)())


@pytest.mark.parametrize("type_name", SAMPLED_TYPES)
@settings(max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(data=st.data())
def test_generated_messages_are_byte_identical(type_name, data):
    assert_identical_to_rosbags(data.draw(message_strategy(type_name)))


@pytest.mark.parametrize("type_name", ALL_TYPES)
@settings(max_examples=4, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(data=st.data())
def test_generated_messages_of_every_type_are_byte_identical(type_name, data):
    assert_identical_to_rosbags(data.draw(message_strategy(type_name)))


def test_buffers_in_another_backend_serialize_as_cpu_bytes():
    image_type = get_message_type("sensor_msgs/msg/Image")
    on_fake = image_type(data=Buffer(FakeBufferImpl(b"abcdef")), width=6)
    assert serialize_message(on_fake) == serialize_message(image_type(data=b"abcdef", width=6))


# ------------------------------------------------------------------------------- large payloads
PAYLOAD_SIZE = 16 * 1024 * 1024


@pytest.fixture(scope="module")
def large_image():
    payload = np.random.default_rng(0).integers(0, 256, PAYLOAD_SIZE, dtype=np.uint8)
    image_type = get_message_type("sensor_msgs/msg/Image")
    return image_type(height=1024, width=4096, step=4096, encoding="rgba8", data=payload), payload


def _peak_allocation(function):
    tracemalloc.start()
    try:
        result = function()
        return result, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_large_payload_is_written_once(large_image):
    message, payload = large_image
    wire, peak = _peak_allocation(lambda: serialize_message(message))
    assert isinstance(wire, bytearray) and len(wire) == serialized_size(message)
    assert np.array_equal(np.frombuffer(wire, np.uint8)[-PAYLOAD_SIZE:], payload)
    # The output buffer is the only payload-sized allocation: no intermediate copy.
    assert PAYLOAD_SIZE <= peak < 1.25 * PAYLOAD_SIZE


def test_large_payload_deserializes_without_a_copy(large_image):
    message, payload = large_image
    wire = bytes(serialize_message(message))
    decoded, peak = _peak_allocation(lambda: deserialize_message(wire, type(message)))
    assert peak < PAYLOAD_SIZE // 16
    assert np.shares_memory(np.asarray(decoded.data), np.frombuffer(wire, np.uint8))
    assert decoded == message


def test_large_payload_is_byte_identical_to_rosbags(large_image):
    message, _ = large_image
    assert bytes(serialize_message(message)) == bytes(
        TYPESTORE.serialize_cdr(to_rosbags(message), message.__msgtype__))


def test_a_string_with_an_embedded_nul_round_trips_like_rosbags():
    # rosbags (and rmw's C++ typesupport) carry it: a relay republishes what it received.
    wire = CDR_HEADER + (4).to_bytes(4, "little") + b"a\x00b\x00"
    received = deserialize_message(wire, "std_msgs/msg/String")
    assert received.data == TYPESTORE.deserialize_cdr(wire, "std_msgs/msg/String").data == "a\x00b"
    assert bytes(serialize_message(received)) == wire
    message = get_message_type(MIXED_TYPE)(name="\x00", names=["x\x00y"])
    assert_identical_to_rosbags(message)
