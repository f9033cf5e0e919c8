"""Generated message classes, and the backend (descriptor) form of buffer fields on the wire."""

from __future__ import annotations

import os
import struct

import numpy as np
import pytest
from plugins.fake_backend import FAKE_BACKEND, FakeBackend, FakeBufferImpl
from plugins.message_tools import MIXED_TYPE

from rosidl_buffer import (
    MAX_BUFFER_DESCRIPTOR_SIZE,
    Buffer,
    DescriptorTooLargeError,
    DeserializationError,
    EndpointInfo,
    EndpointType,
    SerializationError,
    UnknownMessageTypeError,
    local_host_id,
)
from rosidl_buffer.messages import (
    CDR_HEADER,
    Message,
    deserialize_message,
    get_message_type,
    register_message_definitions,
    serialize_message,
)

IMAGE = "sensor_msgs/msg/Image"


# ------------------------------------------------------------------------------- type lookup
@pytest.mark.parametrize(
    ("name", "canonical", "buffer_fields"),
    [("tensor_msgs/msg/ExperimentalTensor", "tensor_msgs/msg/ExperimentalTensor", {"data"}),
     (IMAGE, IMAGE, {"data"}),
     ("sensor_msgs/Image", IMAGE, {"data"}),
     ("/sensor_msgs/msg/PointCloud2/", "sensor_msgs/msg/PointCloud2", {"data"}),
     ("std_msgs/msg/String", "std_msgs/msg/String", set()),
     (MIXED_TYPE, MIXED_TYPE, {"first", "empty_payload", "last"})],
)
def test_get_message_type(name, canonical, buffer_fields):
    cls = get_message_type(name)
    assert issubclass(cls, Message) and cls.__msgtype__ == canonical
    assert cls is get_message_type(canonical)  # one class per type
    assert cls.__name__ == canonical.rsplit("/", 1)[1]
    assert {f for f in cls.__slots__ if isinstance(getattr(cls(), f), Buffer)} == buffer_fields


@pytest.mark.parametrize("name", ["sensor_msgs/msg/NoSuchType", "no_pkg/msg/Image", "Image",
                                  "a/b/c/d", "sensor_msgs//Image"])
def test_unknown_message_type(name):
    with pytest.raises(UnknownMessageTypeError):
        get_message_type(name)


def test_constants_are_class_attributes():
    nav_sat_status = get_message_type("sensor_msgs/msg/NavSatStatus")
    assert nav_sat_status.STATUS_FIX == 0 and nav_sat_status.SERVICE_GPS == 1


# ------------------------------------------------------------------------------- construction
def test_keyword_construction():
    image_type = get_message_type(IMAGE)
    header = get_message_type("std_msgs/msg/Header")(frame_id="camera")
    image = image_type(header=header, height=2, width=3, encoding="mono8", step=3,
                       data=bytes(6))
    assert (image.height, image.width, image.encoding, image.step) == (2, 3, "mono8", 3)
    assert image.header.frame_id == "camera" and image.is_bigendian == 0


def test_unknown_keyword_is_a_type_error():
    with pytest.raises(TypeError, match="colour"):
        get_message_type(IMAGE)(colour="red")


def test_defaults():
    mixed = get_message_type(MIXED_TYPE)()
    assert mixed.first == Buffer() and mixed.first.get_backend_type() == "cpu"
    assert mixed.after_odd_payload == 0.0 and isinstance(mixed.after_odd_payload, float)
    assert mixed.letter == 0 and mixed.raw == 0 and isinstance(mixed.after_values, int)
    assert mixed.name == "" and mixed.short_name == "" and mixed.names == []
    assert mixed.values.dtype == np.float64 and mixed.values.shape == (0,)
    assert mixed.ids.dtype == np.int64 and mixed.bounded.dtype == np.int16
    assert mixed.position.tolist() == [0.0, 0.0, 0.0] and mixed.position.dtype == np.float64
    assert mixed.flags.tolist() == [False, False] and mixed.flags.dtype == np.bool_
    assert mixed.header == get_message_type("std_msgs/msg/Header")()
    assert mixed.header.stamp.sec == 0 and mixed.points == []


def test_defaults_are_not_shared():
    first, second = (get_message_type(MIXED_TYPE)() for _ in range(2))
    first.first.append(1)
    first.position[0] = 1.0
    first.names.append("x")
    first.header.frame_id = "changed"
    assert second == get_message_type(MIXED_TYPE)()


@pytest.mark.parametrize("value", [b"\x01\x02", bytearray(b"\x01\x02"), [1, 2],
                                   np.array([1, 2], np.uint8)],
                         ids=["bytes", "bytearray", "list", "ndarray"])
def test_buffer_fields_wrap_assigned_values(value):
    image = get_message_type(IMAGE)(data=value)
    assert isinstance(image.data, Buffer) and image.data == [1, 2]
    image.data = value
    assert isinstance(image.data, Buffer) and image.data.get_backend_type() == "cpu"


def test_buffer_fields_keep_an_assigned_buffer_and_its_backend():
    buffer = Buffer(FakeBufferImpl([1, 2]))
    image = get_message_type(IMAGE)(data=buffer)
    assert image.data is buffer and image.data.get_backend_type() == FAKE_BACKEND


def test_equality_by_value():
    image_type = get_message_type(IMAGE)
    assert image_type(data=b"ab", width=1) == image_type(data=[97, 98], width=1)
    assert image_type(data=b"ab") != image_type(data=b"ac")
    assert image_type(width=1) != image_type(width=2)
    assert image_type(data=Buffer(FakeBufferImpl(b"ab"))) == image_type(data=b"ab")
    mixed_type = get_message_type(MIXED_TYPE)
    point = get_message_type("geometry_msgs/msg/Point")
    assert mixed_type(points=[point(x=1.0)], position=[1, 2, 3]) == \
        mixed_type(points=[point(x=1.0)], position=np.array([1.0, 2.0, 3.0]))
    assert mixed_type(points=[point(x=1.0)]) != mixed_type(points=[point(x=2.0)])
    assert image_type() != get_message_type("sensor_msgs/msg/CompressedImage")()


def test_messages_are_unhashable():
    with pytest.raises(TypeError):
        hash(get_message_type(IMAGE)())


def test_repr_names_type_and_fields():
    text = repr(get_message_type(IMAGE)(encoding="rgb8"))
    assert text.startswith("sensor_msgs.msg.Image(") and "encoding='rgb8'" in text


def test_get_fields_and_field_types():
    assert get_message_type(IMAGE).get_fields_and_field_types() == {
        "header": "std_msgs/msg/Header", "height": "uint32", "width": "uint32",
        "encoding": "string", "is_bigendian": "uint8", "step": "uint32", "data": "uint8[]",
    }
    types = get_message_type(MIXED_TYPE).get_fields_and_field_types()
    assert types["position"] == "float64[3]" and types["flags"] == "bool[2]"
    assert types["bounded"] == "int16[<=5]" and types["short_name"] == "string<=10"
    assert types["names"] == "string[]" and types["points"] == "geometry_msgs/msg/Point[]"
    # a .msg char is IDL uint8 (rosidl_adapter), as rclpy's generated classes report it
    assert types["letter"] == "uint8" and types["raw"] == "byte"


@pytest.mark.parametrize(
    ("fields", "match"),
    [({"position": [1.0, 2.0]}, "exactly 3"), ({"bounded": list(range(6))}, "bound 5"),
     ({"short_name": "x" * 11}, "bound 10"), ({"name": "\ud800"}, "'name'.*UTF-8"),
     ({"name": 5}, "expected str"), ({"after_values": 256}, "uint8"),
     ({"after_values": -1}, "uint8"), ({"ids": [[1, 2]]}, "1-D"),
     ({"names": "not-a-list"}, "list"), ({"points": [1]}, "Point")],
)
def test_invalid_field_values_raise_serialization_error(fields, match):
    with pytest.raises(SerializationError, match=match):
        serialize_message(get_message_type(MIXED_TYPE)(**fields))


@pytest.mark.parametrize(("type_name", "fields"), [
    ("std_msgs/msg/Float64MultiArray", {"data": None}),
    ("std_msgs/msg/Float64MultiArray", {"data": 5}),
    ("std_msgs/msg/Float64MultiArray", {"data": np.array(5.0)}),
    ("sensor_msgs/msg/LaserScan", {"ranges": None}),
    ("sensor_msgs/msg/LaserScan", {"intensities": 3.0}),
    ("std_msgs/msg/Int32MultiArray", {"data": 7}),
    (MIXED_TYPE, {"position": 1.0}),
    (MIXED_TYPE, {"bounded": None}),
])
def test_a_numeric_sequence_set_to_none_or_a_scalar_is_refused(type_name, fields):
    # Not a one-element sequence ([nan], [5.0]) on the wire. (None for an integer field is
    # refused as an object value before its shape is looked at.)
    (name,) = fields
    with pytest.raises(SerializationError, match=f"{name!r}.*(1-D|object values)"):
        serialize_message(get_message_type(type_name)(**fields))


@pytest.mark.parametrize(("type_name", "value", "match"), [
    ("std_msgs/msg/Int8MultiArray", np.array([300]), "300"),
    ("std_msgs/msg/Int8MultiArray", np.array([1, -129]), "-129"),
    ("std_msgs/msg/Int8MultiArray", np.array([1.9]), "float64"),
    ("std_msgs/msg/Int8MultiArray", [1.9], "float64"),
    ("std_msgs/msg/Int8MultiArray", [1, 2.0], "float64"),
    ("std_msgs/msg/UInt16MultiArray", np.array([-1]), "-1"),
    ("std_msgs/msg/UInt16MultiArray", np.array([70000]), "70000"),
    ("std_msgs/msg/UInt64MultiArray", [-1, 2**63], "-1"),
    ("std_msgs/msg/Int32MultiArray", np.array(["1"]), "not int32"),
    ("std_msgs/msg/Float32MultiArray", np.array([1e300, 1.0]), "range of float32"),
    ("std_msgs/msg/Float32MultiArray", [1.0, -1e39], "range of float32"),
    ("std_msgs/msg/UInt16MultiArray", [np.int64(-1), np.uint64(1)], "out of bounds"),
])
def test_integer_sequences_refuse_values_that_do_not_fit_instead_of_casting(
        type_name, value, match):
    with pytest.raises(SerializationError, match=f"'data'.*{match}"):
        serialize_message(get_message_type(type_name)(data=value))


@pytest.mark.parametrize(("type_name", "value", "expected"), [
    ("std_msgs/msg/Int8MultiArray", np.array([-128, 127]), [-128, 127]),  # int64, in range
    ("std_msgs/msg/Int8MultiArray", np.array([1, 2], np.uint64), [1, 2]),
    ("std_msgs/msg/UInt16MultiArray", np.array([True, False]), [1, 0]),
    ("std_msgs/msg/UInt16MultiArray", np.array([], np.int64), []),
    ("std_msgs/msg/UInt16MultiArray", [], []),
    ("std_msgs/msg/UInt64MultiArray", [2**64 - 1, 1], [2**64 - 1, 1]),  # NumPy infers float64
    ("std_msgs/msg/Float32MultiArray", np.array([1, 2]), [1.0, 2.0]),  # ints into floats: fine
    ("std_msgs/msg/Float32MultiArray", [1, 2.5], [1.0, 2.5]),
])
def test_integer_and_float_sequences_take_values_that_fit(type_name, value, expected):
    cls = get_message_type(type_name)
    assert deserialize_message(serialize_message(cls(data=value)), cls).data.tolist() == expected


def test_bounded_sequences_longer_than_their_bound_are_refused_on_read():
    # integer_range is IntegerRange[<=1]; numeric bounded sequences were checked already.
    from rosidl_buffer.messages import get_typestore

    store = get_typestore()
    name = "rcl_interfaces/msg/ParameterDescriptor"
    ranges = [store.types["rcl_interfaces/msg/IntegerRange"](from_value=0, to_value=10, step=1)]
    fields = dict(name="p", type=2, description="", additional_constraints="", read_only=False,
                  dynamic_typing=False, floating_point_range=[])
    within = bytes(store.serialize_cdr(store.types[name](integer_range=ranges, **fields), name))
    assert len(deserialize_message(within, name).integer_range) == 1
    over = bytes(store.serialize_cdr(store.types[name](integer_range=ranges * 2, **fields), name))
    with pytest.raises(DeserializationError, match="'integer_range'.*bound 1"):
        deserialize_message(over, name)


def test_bounded_string_sequence_longer_than_its_bound_is_refused_on_read():

    type_name = "warp_buffer_test_msgs/msg/BoundedNames"
    register_message_definitions({type_name: "string[<=2] names\n"})
    strings = b"".join(struct.pack("<I", 2) + b"a\x00" + b"\x00\x00" for _ in range(3))
    with pytest.raises(DeserializationError, match="'names'.*bound 2"):
        deserialize_message(CDR_HEADER + struct.pack("<I", 3) + strings, type_name)
    ok = CDR_HEADER + struct.pack("<I", 2) + strings[:16]
    assert deserialize_message(ok, type_name).names == ["a", "a"]


def test_serialize_requires_a_message():
    with pytest.raises(SerializationError):
        serialize_message(object())  # type: ignore[arg-type]


# ------------------------------------------------------------------------------- backend form
def publisher_endpoint() -> EndpointInfo:
    return EndpointInfo(
        gid=bytes(range(16)), node_name="talker", node_namespace="/", topic_name="/image",
        topic_type=IMAGE, endpoint_type=EndpointType.PUBLISHER, host_id=local_host_id(),
        process_id=os.getpid(), user_id=os.getuid(),
    )


def fake_route(backend: FakeBackend, described: list | None = None):
    """What a transport passes: describe every non-CPU buffer with ``backend``."""
    def route(buffer):
        impl = buffer.get_impl()
        descriptor = backend.create_descriptor_with_endpoint(impl, publisher_endpoint())
        if described is not None:
            described.append(descriptor)
        return FAKE_BACKEND, descriptor
    return route


def fake_image(payload=b"\x01\x02\x03\x04\x05"):
    return get_message_type(IMAGE)(encoding="mono8", width=len(payload), height=1,
                                   data=Buffer(FakeBufferImpl(payload)))


def test_backend_form_wire_layout():
    described = []
    image = fake_image()
    wire = bytes(serialize_message(image, route=fake_route(FakeBackend(note="hi"), described)))
    cpu_wire = bytes(serialize_message(image))
    # Up to the buffer field (the last of Image) both forms agree.
    start = len(cpu_wire) - 4 - len(image.data)
    assert wire[:start] == cpu_wire[:start] and wire[:4] == CDR_HEADER
    name = FAKE_BACKEND.encode() + b"\x00"
    # rosidl_typesupport_fastrtps 3.9.4+ (buffer_serialization.hpp): two marker words, 0xFFFFFFFF
    # then "ROS2" read as a little-endian uint32, before the backend name
    prefix = struct.pack("<III", 0xFFFFFFFF, 0x524F5332, len(name)) + name
    descriptor_start = start + len(prefix)
    padding = -(descriptor_start - len(CDR_HEADER)) % 8  # the descriptor starts with a uint64
    (descriptor,) = described
    expected_descriptor = struct.pack("<QII", descriptor.handle, 5, 3) + b"hi\x00"
    assert wire[start:] == prefix + bytes(padding) + expected_descriptor


def test_backend_form_round_trip():
    backend = FakeBackend()
    image = fake_image()
    wire = serialize_message(image, route=fake_route(backend))
    assert len(wire) < len(serialize_message(image)) + 64  # a descriptor, not a payload copy
    received = deserialize_message(wire, IMAGE, backends={FAKE_BACKEND: backend},
                                   endpoint_info=publisher_endpoint())
    assert received.data.get_backend_type() == FAKE_BACKEND
    assert received == image
    assert backend.rebuilt_from == [publisher_endpoint()]


def test_route_is_not_asked_about_cpu_buffers():
    asked = []
    image = get_message_type(IMAGE)(data=b"abc")
    wire = serialize_message(image, route=lambda buffer: asked.append(buffer))
    assert asked == [] and bytes(wire) == bytes(serialize_message(image))


def test_route_none_serves_the_buffer_by_cpu():
    image = fake_image()
    assert serialize_message(image, route=lambda buffer: None) == serialize_message(image)
    received = deserialize_message(serialize_message(image), IMAGE)
    assert received.data.get_backend_type() == "cpu" and received == image


def test_backend_form_in_a_message_with_several_buffers():
    backend = FakeBackend()
    mixed = get_message_type(MIXED_TYPE)(
        first=Buffer(FakeBufferImpl(b"abc")), empty_payload=b"", last=Buffer(b"xyz"),
        after_odd_payload=1.5, names=["a", "b"])
    wire = serialize_message(mixed, route=fake_route(backend))
    received = deserialize_message(wire, MIXED_TYPE, backends={FAKE_BACKEND: backend},
                                   endpoint_info=publisher_endpoint())
    assert received == mixed
    assert [received.first.get_backend_type(), received.last.get_backend_type()] == \
        [FAKE_BACKEND, "cpu"]


def test_descriptor_over_the_limit_is_refused():
    backend = FakeBackend(note="x" * MAX_BUFFER_DESCRIPTOR_SIZE)
    with pytest.raises(DescriptorTooLargeError, match=str(MAX_BUFFER_DESCRIPTOR_SIZE)):
        serialize_message(fake_image(), route=fake_route(backend))


def test_descriptor_at_the_limit_is_accepted():
    # uint64 handle + uint32 size + string (4-byte length, text, NUL) = exactly the limit
    note = "x" * (MAX_BUFFER_DESCRIPTOR_SIZE - 8 - 4 - 4 - 1)
    backend = FakeBackend(note=note)
    image = fake_image()
    wire = serialize_message(image, route=fake_route(backend))
    received = deserialize_message(wire, IMAGE, backends={FAKE_BACKEND: backend},
                                   endpoint_info=publisher_endpoint())
    assert received == image


def test_oversize_descriptor_on_the_wire_is_a_deserialization_error(monkeypatch):
    backend = FakeBackend(note="x" * MAX_BUFFER_DESCRIPTOR_SIZE)
    from rosidl_buffer.messages import _cdr  # a writer without the limit crafts the bytes
    monkeypatch.setattr(_cdr, "MAX_BUFFER_DESCRIPTOR_SIZE", 1 << 20)
    wire = serialize_message(fake_image(), route=fake_route(backend))
    monkeypatch.undo()
    with pytest.raises(DeserializationError, match="limit"):
        deserialize_message(wire, IMAGE, backends={FAKE_BACKEND: backend},
                            endpoint_info=publisher_endpoint())


@pytest.mark.parametrize("backends", [None, {}, {"warp": FakeBackend()}],
                         ids=["none", "empty", "other"])
def test_unknown_backend_name_is_a_deserialization_error(backends):
    wire = serialize_message(fake_image(), route=fake_route(FakeBackend()))
    with pytest.raises(DeserializationError, match=FAKE_BACKEND):
        deserialize_message(wire, IMAGE, backends=backends, endpoint_info=publisher_endpoint())


def test_backend_form_needs_the_publisher_endpoint():
    backend = FakeBackend()
    wire = serialize_message(fake_image(), route=fake_route(backend))
    with pytest.raises(DeserializationError, match="endpoint"):
        deserialize_message(wire, IMAGE, backends={FAKE_BACKEND: backend})


def test_messages_pickle_by_type_name_with_buffers_as_cpu_bytes():
    import pickle

    from tensor_conversions import numpy as tn

    tensor = tn.allocate_tensor_msg((4,), np.float32, backend="warp", device="cpu")
    tn.from_output_tensor_msg(tensor)[:] = [1, 2, 3, 4]
    copy = pickle.loads(pickle.dumps(tensor))  # the class lives in no importable module
    assert type(copy) is type(tensor) and copy.data.get_backend_type() == "cpu"
    np.testing.assert_array_equal(tn.from_input_tensor_msg(copy), [1, 2, 3, 4])
    image = get_message_type("sensor_msgs/msg/Image")(height=2, width=3, encoding="mono8",
                                                      step=3, data=bytes(range(6)))
    assert pickle.loads(pickle.dumps(image)) == image


NESTED_BUFFER_TYPE = "warp_buffer_test_msgs/msg/ImagePair"
register_message_definitions({
    NESTED_BUFFER_TYPE: "sensor_msgs/Image left\nsensor_msgs/Image[] more\nuint8[] blob\n"})


def test_only_top_level_buffers_travel_as_descriptors():
    """As upstream's generated type support (msg__type_support.cpp.em): a nested message is
    serialized by its plain codec, so its buffers are CPU bytes even on an endpoint route."""
    backend = FakeBackend()
    pair = get_message_type(NESTED_BUFFER_TYPE)(
        left=fake_image(b"L"), more=[fake_image(b"M")], blob=Buffer(FakeBufferImpl(b"top")))
    described = []
    wire = serialize_message(pair, route=fake_route(backend, described))
    assert len(described) == 1  # the top-level blob alone
    received = deserialize_message(wire, NESTED_BUFFER_TYPE, backends={FAKE_BACKEND: backend},
                                   endpoint_info=publisher_endpoint())
    assert received.left.data.get_backend_type() == "cpu" and bytes(received.left.data) == b"L"
    assert bytes(received.more[0].data) == b"M"
    assert received.blob.get_backend_type() == FAKE_BACKEND


def test_a_descriptor_in_a_nested_message_is_malformed():
    backend = FakeBackend()
    image_wire = bytes(serialize_message(fake_image(b"L"), route=fake_route(backend)))
    # the same bytes as the nested `left` of a pair whose other fields are empty
    pair_wire = image_wire + struct.pack("<II", 0, 0)
    with pytest.raises(DeserializationError, match="nested"):
        deserialize_message(pair_wire, NESTED_BUFFER_TYPE, backends={FAKE_BACKEND: backend},
                            endpoint_info=publisher_endpoint())
