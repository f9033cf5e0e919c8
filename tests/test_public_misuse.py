"""Wrong input to the public API gets the library's typed errors, not an internal
AttributeError or TypeError."""

from __future__ import annotations

import numpy as np
import pytest

import tensor_conversions
import tensor_conversions.numpy as tcn
from rosidl_buffer.errors import (DeserializationError, InvalidMessageDefinitionError,
                                  UnknownMessageTypeError)
from rosidl_buffer.messages import (deserialize_message, get_message_type,
                                    register_message_definitions)
from tensor_conversions.errors import (InvalidTensorMetadataError, UnsupportedDTypeError,
                                       UnsupportedValueError, WrongMessageTypeError)
from warp_buffer import to_buffer
from warp_buffer.errors import UnsupportedSourceError

CASES = [
    ("get_message_type(None)", lambda: get_message_type(None), UnknownMessageTypeError,
     "not NoneType"),
    ("get_message_type(123)", lambda: get_message_type(123), UnknownMessageTypeError, "not int"),
    ("register_message_definitions(None)", lambda: register_message_definitions(None),
     InvalidMessageDefinitionError, "not NoneType"),
    ("a definition that is not text",
     lambda: register_message_definitions({"trial_pkg/msg/NotText": 5}),
     InvalidMessageDefinitionError, "not int"),
    ("a known name with another definition",
     lambda: register_message_definitions({"sensor_msgs/msg/Image": "int8 x"}),
     InvalidMessageDefinitionError, "sensor_msgs/msg/Image"),
    ("deserialize_message(None)", lambda: deserialize_message(None, "std_msgs/msg/String"),
     DeserializationError, "not NoneType"),
    ("to_buffer(array, None)", lambda: to_buffer(np.zeros(8, np.uint8), None),
     UnsupportedSourceError, "WriteHandle"),
    ("allocate_tensor_msg(dtype=None)", lambda: tcn.allocate_tensor_msg((2,), None),
     UnsupportedDTypeError, "None"),
    ("a point cloud of width -1", lambda: tcn.allocate_pointcloud_msg(-1, ("x",), np.float32),
     InvalidTensorMetadataError, "point cloud sizes"),
    ("loan_tensor_msg(None)", lambda: tcn.loan_tensor_msg(None, (2,), np.float32),
     UnsupportedValueError, "Publisher, not NoneType"),
    ("release_output(None)", lambda: tensor_conversions.release_output(None),
     WrongMessageTypeError, "not NoneType"),
]


@pytest.mark.parametrize(("call", "expected", "words"), [c[1:] for c in CASES],
                         ids=[c[0] for c in CASES])
def test_wrong_input_gets_a_typed_error(call, expected, words) -> None:
    with pytest.raises(expected, match=words):
        call()

