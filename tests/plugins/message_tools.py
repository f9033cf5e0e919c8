"""Test helpers for messages: a mixed test type, hypothesis strategies, a converter to rosbags."""

from __future__ import annotations

import functools

import numpy as np
from hypothesis import strategies as st

from rosidl_buffer import Buffer
from rosidl_buffer.messages import (
    get_message_type,
    get_schema,
    get_typestore,
    register_message_definitions,
)
from rosidl_buffer.messages._classes import numpy_dtype
from rosidl_buffer.messages._schema import FieldKind, FieldSpec

MIXED_TYPE = "warp_buffer_test_msgs/msg/Mixed"

# Several uint8[] (one left empty), every array kind, and fields whose alignment depends on what
# precedes them: an odd-length uint8[] before a float64, a uint8 after non-empty and empty float64[].
MIXED_DEFINITION = """\
uint8[] first
float64 after_odd_payload
float64[] values
uint8 after_values
uint8[] empty_payload
float64[] empty_values
uint8 after_empty
int64[] ids
float64[3] position
bool[2] flags
int16[<=5] bounded
string name
string[] names
string<=10 short_name
std_msgs/Header header
geometry_msgs/Point[] points
char letter
byte raw
uint8[] last
"""

register_message_definitions({MIXED_TYPE: MIXED_DEFINITION})


def to_rosbags(message):
    """The rosbags dataclass instance with the same content as one of our messages.

    rosbags holds ``byte`` as int8 (ROS 1's meaning), ROS 2 and we as an octet (uint8): the same
    bits on the wire, so the converter reinterprets them.
    """
    cls = get_typestore().types[message.__msgtype__]
    values = {}
    for spec in get_schema(message.__msgtype__).fields:
        value = getattr(message, spec.name)
        if spec.is_buffer:
            value = value.to_numpy()
        elif spec.kind is FieldKind.MESSAGE:
            value = [to_rosbags(v) for v in value] if spec.is_collection else to_rosbags(value)
        elif spec.is_collection and spec.kind is FieldKind.PRIMITIVE:
            value = np.asarray(value, dtype=numpy_dtype(spec.element))
            if spec.element == "byte":
                value = value.view(np.int8)
        elif spec.element == "byte":
            value = int(np.uint8(value).view(np.int8))
        elif spec.is_collection:
            value = list(value)
        values[spec.name] = value
    return cls(**values)


# ------------------------------------------------------------------------ hypothesis strategies
_INT_RANGES = {
    name: (int(np.iinfo(numpy_dtype(name)).min), int(np.iinfo(numpy_dtype(name)).max))
    for name in ("byte", "char", "int8", "uint8", "int16", "uint16", "int32", "uint32",
                 "int64", "uint64")
}
_TEXT = st.characters(codec="utf-8", exclude_characters="\x00")
_ASCII = st.characters(min_codepoint=1, max_codepoint=127)


def _element(spec: FieldSpec) -> st.SearchStrategy:
    if spec.kind is FieldKind.MESSAGE:
        return message_strategy(spec.element)
    if spec.kind is FieldKind.STRING:
        if spec.string_bound:  # ASCII: the bound then counts characters and bytes alike
            return st.text(_ASCII, max_size=spec.string_bound)
        return st.text(_TEXT, max_size=8)
    if spec.element == "bool":
        return st.booleans()
    if spec.element.startswith("float"):
        width = 32 if spec.element == "float32" else 64
        return st.floats(allow_nan=False, width=width)
    low, high = _INT_RANGES[spec.element]
    return st.integers(low, high)


def _field(spec: FieldSpec) -> st.SearchStrategy:
    if spec.is_buffer:
        return st.binary(max_size=24).map(Buffer)
    element = _element(spec)
    if spec.array_length:
        items = st.lists(element, min_size=spec.array_length, max_size=spec.array_length)
    elif spec.is_sequence:
        items = st.lists(element, max_size=min(spec.sequence_bound or 4, 4))
    else:
        return element
    if spec.kind is FieldKind.PRIMITIVE:
        dtype = numpy_dtype(spec.element)
        return items.map(lambda values: np.array(values, dtype=dtype))
    return items


@functools.lru_cache(maxsize=None)
def message_strategy(type_name: str) -> st.SearchStrategy:
    """Messages of ``type_name`` with arbitrary valid field values."""
    cls = get_message_type(type_name)
    fields = {spec.name: _field(spec) for spec in get_schema(type_name).fields}
    return st.builds(cls, **fields)
