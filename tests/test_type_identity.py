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

from rosidl_buffer.messages import get_type_hash

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
