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
