"""Default values written in ``.msg`` files (``float64 w 1``) start new messages, as rclpy's
generated classes do; rosbags' parser drops them, so the project keeps its own."""

from __future__ import annotations

import uuid

import numpy as np
import pytest

from rosidl_buffer.errors import InvalidMessageDefinitionError
from rosidl_buffer.messages import (
    deserialize_message,
    get_message_type,
    register_message_definitions,
    serialize_message,
)


def test_the_distributions_defaults_start_new_messages() -> None:
    quaternion = get_message_type("geometry_msgs/msg/Quaternion")
    assert (quaternion().x, quaternion().y, quaternion().z, quaternion().w) == (0, 0, 0, 1.0)
    assert get_message_type("geometry_msgs/msg/Pose")().orientation.w == 1.0
    assert get_message_type("sensor_msgs/msg/NavSatStatus")().status == -2
    assert quaternion(w=0.5).w == 0.5  # a value given wins


def test_a_default_pose_is_the_identity_on_the_wire() -> None:
    pose_type = get_message_type("geometry_msgs/msg/Pose")
    wire = bytes(serialize_message(pose_type()))
    assert wire[-8:] == np.float64(1.0).tobytes()  # w, the last field
    assert deserialize_message(wire, pose_type).orientation.w == 1.0


def _register(text: str) -> type:
    name = f"defaults_test_{uuid.uuid4().hex[:8]}/msg/Defaults"
    register_message_definitions({name: text})
    return get_message_type(name)


def test_registered_definitions_keep_their_defaults() -> None:
    defaults = _register("""# every kind of default
float64 w 1.0  # a comment after the value
string s 'hi # not a comment'
string plain bare
int32[] numbers [1, 2, 3]
string[2] names ["a,b", 'c']
bool flag true
int8 negative -5
int32 CONSTANT=7
int32 zero
""")
    msg = defaults()
    assert (msg.w, msg.s, msg.plain, msg.flag, msg.negative, msg.zero) == (
        1.0, "hi # not a comment", "bare", True, -5, 0)
    assert msg.numbers.tolist() == [1, 2, 3] and msg.names == ["a,b", "c"]
    assert defaults.CONSTANT == 7
    msg.numbers[0] = 9
    msg.names.append("d")
    assert defaults().numbers.tolist() == [1, 2, 3] and defaults().names == ["a,b", "c"]
    assert defaults(w=2.0, numbers=[4]).w == 2.0


@pytest.mark.parametrize("line, words", [
    ("int32 x 1.5", "cannot default"),
    ("bool b maybe", "true or false"),
    ("int32[2] pair [1]", "1 values for an array of 2"),
    ("int32[<=1] few [1, 2]", "at most 1"),
    ("float64[] list 3", "list in brackets"),
    ("uint8 a 300", "out of uint8's range"),  # (these registered, then failed to serialize)
    ("int8 a -200", "out of int8's range"),
    ("float32 f 1e300", "out of float32's range"),
    ("int16[] v [1, 70000]", "out of int16's range"),
    ('string<=3 s "abcd"', "bound of 3"),
])
def test_a_default_its_type_cannot_hold_is_a_typed_error(line: str, words: str) -> None:
    with pytest.raises(InvalidMessageDefinitionError, match=words):
        _register(line + "\n")


def test_defaults_at_the_edges_of_their_types_are_taken() -> None:
    msg_type = _register('uint8 a 255\nint8 b -128\nstring<=3 s "abc"\n'
                         'int64 c -9223372036854775808\n')
    msg = msg_type()
    assert (msg.a, msg.b, msg.s, msg.c) == (255, -128, "abc", -(1 << 63))
    serialize_message(msg)  # and they go on the wire


def test_a_type_with_array_defaults_round_trips() -> None:
    defaults = _register("int32[] numbers [1, 2, 3]\nstring[2] names ['a', 'b']\n"
                         "uint8[] data [7]\n")
    msg = defaults()
    back = deserialize_message(bytes(serialize_message(msg)), defaults)
    assert back.numbers.tolist() == [1, 2, 3] and back.names == ["a", "b"]
    assert bytes(back.data) == b"\x07"
    from rosidl_buffer.messages._schema import get_schema

    hash(get_schema(defaults.__msgtype__).fields)  # field specs stay hashable (cache keys)
