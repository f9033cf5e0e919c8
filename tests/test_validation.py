"""The publisher's field validation (buffer_pubsub._validation): each field's quick test takes
only values its full check accepts; everything else gets the full check's verdict."""

from __future__ import annotations

import numpy as np
import pytest

from buffer_pubsub._validation import validate_message
from rosidl_buffer.errors import SerializationError
from rosidl_buffer.messages import get_message_type

CAMERA_INFO = "sensor_msgs/msg/CameraInfo"


def _camera_info(**fields):
    msg = get_message_type(CAMERA_INFO)()
    for name, value in fields.items():
        setattr(msg, name, value)
    return msg


@pytest.mark.parametrize("fields", [
    {},
    {"height": 480, "width": np.uint32(640)},  # an exact int, a NumPy integer
    {"binning_x": True},  # a bool is an integer 0/1
    {"height": 2**32 - 1},
    {"k": np.zeros(9), "d": [0.1, 0.2]},  # an array, a list of floats
    {"k": np.zeros(9, np.int32)},  # integers in a float array
    {"distortion_model": "plumb_bob"},
    {"d": []},  # an empty list (NumPy would call it float64)
])
def test_accepted_values(fields):
    validate_message(_camera_info(**fields))


@pytest.mark.parametrize("fields, error", [
    ({"height": "480"}, "CameraInfo.height: expected an int"),
    ({"height": 2**32}, "CameraInfo.height: .* out of range"),
    ({"width": -1}, "CameraInfo.width: .* out of range"),
    ({"height": 480.0}, "CameraInfo.height: expected an int"),
    ({"k": np.zeros(8)}, "CameraInfo.k: expected exactly 9 elements"),
    ({"k": []}, "CameraInfo.k: expected exactly 9 elements"),
    ({"k": np.zeros((3, 3))}, "CameraInfo.k: expected a 1-D sequence"),
    ({"d": np.array(["a"])}, "CameraInfo.d: expected float64 values"),
    ({"distortion_model": b"plumb_bob"}, "CameraInfo.distortion_model: expected str"),
])
def test_rejected_values_name_the_field(fields, error):
    with pytest.raises(SerializationError, match=error):
        validate_message(_camera_info(**fields))


def test_nested_messages_are_checked_too():
    msg = _camera_info()
    msg.header.stamp.sec = 1.5
    with pytest.raises(SerializationError, match="stamp"):
        validate_message(msg)
    msg.header.stamp.sec = 1
    msg.roi.width = -3
    with pytest.raises(SerializationError, match="roi"):
        validate_message(msg)


@pytest.mark.parametrize("empty", [[], (), np.array([], np.int64)])
def test_an_empty_integer_array_is_accepted(empty):
    tensor = get_message_type("tensor_msgs/msg/ExperimentalTensor")(shape=[0], strides=empty)
    validate_message(tensor)
    ints = get_message_type("std_msgs/msg/Int32MultiArray")(data=empty)
    validate_message(ints)


@pytest.mark.parametrize("type_name, fields, error", [
    ("std_msgs/msg/Int8MultiArray", {"data": np.array([300, -200])}, "out of the range"),
    ("std_msgs/msg/UInt16MultiArray", {"data": np.array([-1])}, "out of the range"),
    ("std_msgs/msg/UInt64MultiArray", {"data": np.array([-1], np.int64)}, "out of the range"),
    ("std_msgs/msg/Float32", {"data": 1e300}, "out of range for float32"),
    ("std_msgs/msg/Float32MultiArray", {"data": np.array([1e300, 1.0])}, "range of float32"),
    ("geometry_msgs/msg/Point32", {"x": -1e39}, "out of range for float32"),
    ("std_msgs/msg/String", {"data": "a\ud800b"}, "not valid Unicode"),
])
def test_values_the_wire_cannot_carry_are_refused_on_every_route(type_name, fields, error):
    """The serializer wrapped these (300 -> 44 in int8) or raised a builtin error, and only
    when a remote subscriber made the publisher serialize; in-process subscribers got them."""
    msg = get_message_type(type_name)(**fields)
    with pytest.raises(SerializationError, match=error):
        validate_message(msg)


@pytest.mark.parametrize("type_name, fields", [
    ("std_msgs/msg/Int8MultiArray", {"data": np.array([127, -128])}),  # int64, in range
    ("std_msgs/msg/Int8MultiArray", {"data": np.array([1, -1], np.int8)}),
    ("std_msgs/msg/UInt8MultiArray", {"data": np.array([True, False])}),
    ("std_msgs/msg/Float32", {"data": float(np.finfo(np.float32).max)}),
    ("std_msgs/msg/Float32", {"data": float("inf")}),
    ("std_msgs/msg/Float32", {"data": float("nan")}),
    ("std_msgs/msg/Float64", {"data": 1e300}),
    ("std_msgs/msg/Float32MultiArray", {"data": np.array([1.5, np.inf, np.nan])}),
    ("std_msgs/msg/Float32MultiArray", {"data": np.array([1, 2], np.int64)}),
    ("std_msgs/msg/String", {"data": "h\u00e9llo \U0001f600"}),  # non-ASCII, valid
])
def test_values_in_range_pass(type_name, fields):
    validate_message(get_message_type(type_name)(**fields))
