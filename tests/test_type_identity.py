"""Type identity with ROS 2: a node of ours and a ROS 2 node meet on the same data key only if
the type name and its RIHS01 hash agree (REP 2016).

``ExperimentalTensor`` is upstream's (ros2/rosidl_buffer_backends ``tensor_msgs``): its definition
is written out below as released (comments left out: they take no part in the hash) and hashed
by rosbags from that text alone, independently of the ``.msg`` file we ship. The standard types
users send must hash as in the ROS 2 distributions that have rosidl::Buffer (Lyrical, Rolling);
they are unchanged since Jazzy, which is checked against rosbags' stores of each.
"""

from __future__ import annotations

import pytest
from rosbags.typesys import Stores, get_types_from_msg, get_typestore as rosbags_typestore

from rosidl_buffer.messages import (
    buffer_fields,
    get_message_type,
    get_type_hash,
    register_message_definitions,
)

UPSTREAM_EXPERIMENTAL_TENSOR = """
uint8  dtype_code
uint8  dtype_bits
uint16 dtype_lanes
int64[]  shape
int64[]  strides
uint64   byte_offset
uint8[] data
"""


def test_experimental_tensor_has_upstreams_definition_and_hash():
    store = rosbags_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(UPSTREAM_EXPERIMENTAL_TENSOR,
                                      "tensor_msgs/msg/ExperimentalTensor"))
    assert get_type_hash("tensor_msgs/msg/ExperimentalTensor") == \
        store.hash_rihs01("tensor_msgs/msg/ExperimentalTensor")


@pytest.mark.parametrize("name", [
    "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/PointCloud2",
    "std_msgs/msg/UInt8MultiArray", "std_msgs/msg/String",
])
def test_standard_types_hash_as_in_the_buffer_era_distributions(name):
    ours = get_type_hash(name)
    for store in (Stores.ROS2_LYRICAL, Stores.ROS2_KILTED, Stores.ROS2_JAZZY):
        assert rosbags_typestore(store).hash_rihs01(name) == ours, store


#: ``hash_string`` of each type's ``share/std_msgs/msg/<Name>.json`` in the released
#: ros-std-msgs 5.5.1 wheel (what rosidl generates, and rmw_zenoh puts in its keys).
RELEASED_STD_MSGS_HASHES = {
    "std_msgs/msg/Char":
        "RIHS01_3ad2d04dd29ba19d04b16659afa3ccaedd691914b02a64e82e252f2fa6a586a9",
    "std_msgs/msg/Header":
        "RIHS01_f49fb3ae2cf070f793645ff749683ac6b06203e41c891e17701b1cb597ce6a01",
    "std_msgs/msg/ByteMultiArray":
        "RIHS01_972fec7f50ab3c1d06783c228e79e8a9a509021708c511c059926261ada901d4",
    "std_msgs/msg/String":
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
    "std_msgs/msg/UInt8MultiArray":
        "RIHS01_5687e861b8d307a5e48b7515467ae7a5fc2daf805bd0ce6d8e9e604bade9f385",
}


@pytest.mark.parametrize("name", sorted(RELEASED_STD_MSGS_HASHES))
def test_hashes_are_the_ones_ros2_generates(name):
    # Char is the case rosbags alone gets wrong: it hashes a char as type id 13, while rosidl
    # turns a .msg char into IDL uint8 (type id 3) before it describes the type.
    assert get_type_hash(name) == RELEASED_STD_MSGS_HASHES[name]


def test_a_char_field_hashes_and_routes_as_the_uint8_rosidl_makes_of_it():
    definition = "char one\nchar[] letters\nchar[4] fixed\nbyte[] raw\nuint8[<=8] bounded\n"
    register_message_definitions({"identity_test_msgs/msg/Chars": definition})
    store = rosbags_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(definition.replace("char", "uint8"),
                                      "identity_test_msgs/msg/Chars"))
    assert get_type_hash("identity_test_msgs/msg/Chars") == \
        store.hash_rihs01("identity_test_msgs/msg/Chars")
    # rmw_zenoh's typesupport: a top-level unbounded uint8 sequence is a buffer field; byte[]
    # (octet) and bounded or fixed arrays are not
    assert buffer_fields(get_message_type("identity_test_msgs/msg/Chars")) == {"letters"}
