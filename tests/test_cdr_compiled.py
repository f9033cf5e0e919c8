"""The compiled per-type CDR functions keep the generic codec's errors and edge cases.

Byte identity with rosbags for every type is tested in test_cdr_identity.py; these tests aim at
what the compiled form added: inline primitive runs and their per-field fallbacks, the wire-form
fast path for numeric arrays, per-argument decoder caching and the backend's returned impl.
"""

from __future__ import annotations

import numpy as np
import pytest

from rosidl_buffer import Buffer
from rosidl_buffer.errors import DeserializationError, SerializationError
from rosidl_buffer.messages import deserialize_message, get_message_type, serialize_message
from rosidl_buffer.messages._cdr import _codec

TENSOR = "tensor_msgs/msg/ExperimentalTensor"


def _tensor(**fields):
    return get_message_type(TENSOR)(dtype_code=1, dtype_bits=8, dtype_lanes=1,
                                    shape=np.array([4], np.int64), data=b"abcd", **fields)


def test_every_codec_has_readable_compiled_source():
    source = _codec(TENSOR).source
    assert "def size(m, pos, ctx):" in source and "def write(" in source
    assert "def read(ctx, pos):" in source
    # The three leading uint8/uint8/uint16 fields are one struct call, not three.
    assert source.count("packer.pack_into(out, pos, m.dtype_code, m.dtype_bits, m.dtype_lanes)") == 1


@pytest.mark.parametrize("field, value, words", [
    ("dtype_bits", 256, "dtype_bits"),
    ("dtype_lanes", -1, "dtype_lanes"),
    ("byte_offset", "seven", "byte_offset"),
])
def test_a_bad_value_in_a_primitive_run_names_its_field(field, value, words):
    msg = _tensor()
    setattr(msg, field, value)
    with pytest.raises(SerializationError, match=words):
        serialize_message(msg)


def test_a_truncated_primitive_run_raises_a_typed_error():
    data = bytes(serialize_message(_tensor()))
    with pytest.raises(DeserializationError, match="truncated"):
        deserialize_message(data[:6], TENSOR)


def test_arrays_not_in_wire_form_are_converted_and_checked():
    big_endian = np.array([2, 3], dtype=">i8")
    as_list = [2, 3]
    reference = bytes(serialize_message(_tensor(strides=np.array([2, 3], np.int64))))
    assert bytes(serialize_message(_tensor(strides=big_endian))) == reference
    assert bytes(serialize_message(_tensor(strides=as_list))) == reference
    strided = np.array([2, 0, 3], np.int64)[::2]  # not contiguous
    assert bytes(serialize_message(_tensor(strides=strided))) == reference
    with pytest.raises(SerializationError, match="1-D"):
        serialize_message(_tensor(strides=np.zeros((2, 2), np.int64)))
    with pytest.raises(SerializationError, match="strides"):
        serialize_message(_tensor(strides=["a"]))


def test_a_received_message_republishes_byte_identically_and_owns_its_arrays():
    original = _tensor(strides=np.array([1], np.int64))
    data = bytearray(serialize_message(original))
    received = deserialize_message(data, TENSOR)
    assert received.shape.dtype is np.dtype(np.int64)  # the native dtype: the fast path
    assert bytes(serialize_message(received)) == bytes(data)
    data[:] = bytes(len(data))  # the arrays were copied out of the wire bytes
    assert list(received.shape) == [4] and list(received.strides) == [1]


def test_decoders_by_class_and_by_name_agree():
    data = bytes(serialize_message(_tensor()))
    by_class = deserialize_message(data, get_message_type(TENSOR))
    by_name = deserialize_message(data, TENSOR)
    by_short_name = deserialize_message(data, "tensor_msgs/ExperimentalTensor")
    assert by_class == by_name == by_short_name == _tensor()


def test_a_reused_output_buffer_carries_no_bytes_of_an_earlier_message():
    out = bytearray(serialize_message(_tensor()))
    out[:] = b"\xff" * len(out)  # poison: padding must be written as zeros again
    again = serialize_message(_tensor(), out=out)
    assert again is out
    assert bytes(again) == bytes(serialize_message(_tensor()))


def test_a_backend_returning_something_other_than_an_impl_is_a_typed_error():
    from plugins.fake_backend import FakeBackend, FakeBufferImpl

    class Broken(FakeBackend):
        def from_descriptor_with_endpoint(self, descriptor, endpoint_info):
            return b"not an impl"

    backend = Broken()
    msg = _tensor()
    msg.data = Buffer(FakeBufferImpl(np.frombuffer(b"abcd", np.uint8)))
    descriptor = backend.create_descriptor_with_endpoint(msg.data.get_impl(), None)
    data = serialize_message(msg, route=lambda buffer: (backend.get_backend_type(), descriptor))
    with pytest.raises(DeserializationError, match="not a BufferImplBase"):
        deserialize_message(data, TENSOR, backends={backend.get_backend_type(): backend},
                            endpoint_info=object())


def test_fields_named_like_python_keywords_round_trip():
    from rosidl_buffer.messages import register_message_definitions

    register_message_definitions({"cdr_compiled_test/msg/Keywords":
                                  "uint8 from\nstring class\nint64[] lambda\nuint16 import\n"})
    cls = get_message_type("cdr_compiled_test/msg/Keywords")
    msg = cls()
    setattr(msg, "from", 3)
    setattr(msg, "class", "x")
    setattr(msg, "lambda", np.array([5, 6], np.int64))
    setattr(msg, "import", 9)
    assert deserialize_message(serialize_message(msg), cls) == msg


@pytest.mark.parametrize(("type_name", "fields", "name"), [
    ("std_msgs/msg/Float32", {"data": 1e300}, "data"),  # a one-field primitive run
    ("geometry_msgs/msg/Point32", {"y": -1e39}, "y"),  # the middle field of a run
    ("std_msgs/msg/String", {"data": "\ud800"}, "data"),  # a lone surrogate: not UTF-8
])
def test_a_value_the_wire_type_cannot_hold_is_a_serialization_error_naming_its_field(
        type_name, fields, name):
    # struct's OverflowError and str.encode's UnicodeEncodeError are not raw exceptions out of
    # serialize_message. (float32 inf and nan are fine: they are float32 values.)
    with pytest.raises(SerializationError, match=f"'{name}'"):
        serialize_message(get_message_type(type_name)(**fields))
    point = get_message_type("geometry_msgs/msg/Point32")(x=float("inf"), y=float("nan"))
    back = deserialize_message(serialize_message(point), type(point))
    assert back.x == float("inf") and back.y != back.y


def test_a_fixed_layout_descriptor_is_packed_with_one_struct_call_and_sized_once(monkeypatch):
    """A descriptor of primitives only (the warp backend's) is sized once per type, packed and
    unpacked with its precompiled struct (at phase 0 the warp descriptor's LAYOUT): the bytes and
    the decoded values are those of the field-by-field path, the reference."""
    from plugins.fake_backend import FakeBufferImpl
    from rosidl_buffer.messages import _cdr
    from warp_buffer import descriptor as desc

    codec = _codec(desc.DESCRIPTOR_TYPE)
    assert codec.fixed is not None and codec.fixed[0][0].format == desc.LAYOUT.format
    sent = desc.make(tuple(range(1, len(desc.FIELDS) + 1)))
    received = []

    class Backend:
        def get_descriptor_type(self):
            return desc.descriptor_type()

        def from_descriptor_with_endpoint(self, descriptor, endpoint_info):
            received.append(desc.fields_of(descriptor))
            return FakeBufferImpl(b"x")

    def round_trip():
        msg = _tensor()
        msg.data = Buffer(FakeBufferImpl(b"abcd"))
        data = serialize_message(msg, route=lambda buffer: ("warp", sent))
        deserialize_message(data, TENSOR, backends={"warp": Backend()}, endpoint_info=object())
        return bytes(data)

    def no_sizing(*args):
        raise AssertionError("the descriptor was sized again")

    monkeypatch.setattr(_cdr, "_descriptor_size", no_sizing)
    fast = round_trip()
    monkeypatch.undo()
    monkeypatch.setattr(codec, "fixed", None)  # the field-by-field path
    assert round_trip() == fast
    assert received == [desc.fields_of(sent)] * 2


def test_the_inline_numeric_sequences_read_back_and_refuse_every_truncation():
    msg = _tensor(strides=np.array([1], np.int64))
    msg.shape = np.array([4, 1], np.int64)
    data = bytes(serialize_message(msg))
    back = deserialize_message(data, TENSOR)
    assert back.shape.tolist() == [4, 1] and back.strides.tolist() == [1]
    assert bytes(serialize_message(back)) == data
    for cut in range(4, len(data)):  # every cut inside the fields after the header
        with pytest.raises(DeserializationError):
            deserialize_message(data[:cut], TENSOR)


def test_an_inline_sequence_count_past_the_data_is_a_truncation():
    data = bytearray(serialize_message(_tensor()))
    data[8:12] = (0xFFFFFFF0).to_bytes(4, "little")  # the shape's count, absurd
    with pytest.raises(DeserializationError, match="truncated"):
        deserialize_message(bytes(data), TENSOR)
