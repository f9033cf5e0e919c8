"""sensor_msgs/msg/Image and PointCloud2 through tensor_conversions: HWC views with the row
padding as a stride, every encoding's round trip, byte order, zero-copy proven by data pointers,
typed errors for encodings, sizes and strides that don't fit."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import torch
import warp as wp

import tensor_conversions as tc
from rosidl_buffer.messages import deserialize_message, get_message_type, serialize_message
from tensor_conversions import numpy as tc_numpy
from tensor_conversions import pointcloud
from tensor_conversions.image import image_format
from tensor_conversions.testing import MODULES, to_raw

pytestmark = pytest.mark.usefixtures("warp_pool_drained")

ENCODINGS = {  # encoding -> (channels, numpy dtype)
    "mono8": (1, np.uint8), "mono16": (1, np.uint16), "rgb8": (3, np.uint8),
    "bgr8": (3, np.uint8), "rgba8": (4, np.uint8), "bgra8": (4, np.uint8),
    "8UC1": (1, np.uint8), "8UC2": (2, np.uint8), "8UC3": (3, np.uint8), "8UC4": (4, np.uint8),
    "16UC1": (1, np.uint16), "32FC1": (1, np.float32), "bayer_rggb8": (1, np.uint8),
    "bayer_bggr8": (1, np.uint8), "bayer_gbrg8": (1, np.uint8), "bayer_grbg8": (1, np.uint8),
}
IMAGE = get_message_type("sensor_msgs/msg/Image")


def _pixels(encoding: str, height: int = 3, width: int = 5, seed: int = 0) -> np.ndarray:
    channels, dtype = ENCODINGS[encoding]
    shape = (height, width) if channels == 1 else (height, width, channels)
    raw = np.random.default_rng(seed).integers(0, 256, (*shape, np.dtype(dtype).itemsize),
                                               dtype=np.uint8)
    if dtype == np.float32:
        raw[..., 3] &= 0x3F  # finite floats only
    return raw.view(dtype).reshape(shape)


def _native(framework: str, array: np.ndarray):
    if framework == "numpy":
        return array
    if framework == "torch":
        return torch.from_numpy(array.copy())
    return wp.array(array, dtype=wp.dtype_from_numpy(array.dtype), device="cpu")


def _ptr(value) -> int:
    if isinstance(value, np.ndarray):
        return value.ctypes.data
    if isinstance(value, torch.Tensor):
        return value.const_data_ptr()  # (read-only input views refuse data_ptr())
    return value.ptr


@pytest.mark.parametrize("framework", list(MODULES))
@pytest.mark.parametrize("encoding", list(ENCODINGS))
def test_every_encoding_round_trips(framework, encoding):
    module = MODULES[framework]
    pixels = _pixels(encoding)
    msg = module.to_image_msg(_native(framework, pixels), encoding)
    channels, dtype = ENCODINGS[encoding]
    assert (msg.height, msg.width, msg.encoding) == (3, 5, encoding)
    assert msg.step == 5 * channels * np.dtype(dtype).itemsize
    assert msg.is_bigendian == (sys.byteorder == "big")
    np.testing.assert_array_equal(msg.data.to_numpy(), pixels.reshape(-1).view(np.uint8))
    for clone in (True, False):
        out = module.from_input_image_msg(msg, clone=clone)
        assert tuple(out.shape) == pixels.shape
        np.testing.assert_array_equal(to_raw(out), to_raw(pixels))


@pytest.mark.parametrize("framework", list(MODULES))
def test_step_padding_is_a_row_stride_and_zero_copy(framework):
    module = MODULES[framework]
    msg = module.allocate_image_msg(4, 5, "rgb8", step=20)  # 15 bytes of pixels + 5 padding
    assert len(msg.data) == 80
    out = module.from_output_image_msg(msg)
    assert tuple(out.shape) == (4, 5, 3)
    pixels = _pixels("rgb8", 4, 5, seed=3)
    if framework == "warp":
        wp.copy(out, wp.array(pixels, dtype=wp.uint8, device="cpu"))
    else:
        out[...] = _native(framework, pixels)
    data = msg.data.numpy()
    assert _ptr(out) == data.ctypes.data  # the view IS the message storage
    rows = data.reshape(4, 20)
    np.testing.assert_array_equal(rows[:, :15].reshape(4, 5, 3), pixels)
    assert not rows[:, 15:].any()  # the padding was not written
    view = module.from_input_image_msg(msg, clone=False)
    assert _ptr(view) == data.ctypes.data
    np.testing.assert_array_equal(to_raw(view), to_raw(pixels))
    copy = module.from_input_image_msg(msg)
    assert _ptr(copy) != data.ctypes.data
    np.testing.assert_array_equal(to_raw(copy), to_raw(pixels))


def test_padded_16bit_rows_after_cdr_round_trip():
    msg = tc_numpy.allocate_image_msg(3, 4, "mono16", step=12)
    tc_numpy.from_output_image_msg(msg)[...] = np.arange(12, dtype=np.uint16).reshape(3, 4)
    received = deserialize_message(serialize_message(msg), IMAGE)
    view = tc_numpy.from_input_image_msg(received, clone=False)
    assert view.strides == (12, 2) and not view.flags.writeable
    np.testing.assert_array_equal(view, np.arange(12, dtype=np.uint16).reshape(3, 4))


@pytest.mark.parametrize("framework", list(MODULES))
def test_warp_storage_image(framework):
    module = MODULES[framework]
    pixels = _pixels("bgra8", 2, 6, seed=1)
    msg = module.to_image_msg(_native(framework, pixels), "bgra8", backend="warp", device="cpu")
    assert msg.data.get_backend_type() == "warp"
    for clone in (True, False):
        np.testing.assert_array_equal(to_raw(module.from_input_image_msg(msg, clone=clone)),
                                      to_raw(pixels))


def test_foreign_byte_order_is_converted_only_by_a_copy():
    values = np.arange(6, dtype=np.uint16).reshape(2, 3) * 257 + 1
    foreign = values.astype(values.dtype.newbyteorder())
    msg = IMAGE(height=2, width=3, encoding="16UC1", step=6,
                is_bigendian=int(sys.byteorder != "big"), data=foreign.view(np.uint8).reshape(-1))
    for module in MODULES.values():
        np.testing.assert_array_equal(to_raw(module.from_input_image_msg(msg)), to_raw(values))
        with pytest.raises(tc.InvalidTensorMetadataError, match="byte order"):
            module.from_input_image_msg(msg, clone=False)
    converted = tc_numpy.from_input_image_msg(msg)  # a clone is the caller's: writable
    converted[0, 0] = 7
    assert converted[0, 0] == 7 and foreign[0, 0] != foreign.dtype.type(7)
    # 8-bit pixels have no byte order: the flag does not matter
    msg8 = IMAGE(height=1, width=2, encoding="mono8", step=2, is_bigendian=1, data=[1, 2])
    assert tc_numpy.from_input_image_msg(msg8, clone=False).tolist() == [[1, 2]]
    # an empty image in the other byte order converts too (its copy's row stride was 0)
    empty = IMAGE(height=0, width=3, encoding="mono16", step=6,
                  is_bigendian=int(sys.byteorder != "big"), data=[])
    for module in MODULES.values():
        assert tuple(module.from_input_image_msg(empty).shape) == (0, 3)


def test_image_errors_are_typed():
    with pytest.raises(tc.UnsupportedEncodingError, match="yuv422"):
        tc_numpy.allocate_image_msg(2, 2, "yuv422")
    with pytest.raises(tc.UnsupportedEncodingError, match="jpeg"):
        tc_numpy.from_input_image_msg(IMAGE(height=1, width=1, encoding="jpeg", step=1, data=[0]))
    with pytest.raises(tc.InvalidTensorMetadataError, match="shorter"):
        tc_numpy.allocate_image_msg(2, 4, "rgb8", step=10)
    with pytest.raises(tc.InvalidTensorMetadataError, match="multiple"):
        tc_numpy.allocate_image_msg(2, 4, "mono16", step=9)
    short = IMAGE(height=4, width=4, encoding="mono8", step=4, data=bytes(15))
    with pytest.raises(tc.TensorSizeError, match="16 bytes"):
        tc_numpy.from_input_image_msg(short)
    with pytest.raises(tc.UnsupportedDTypeError, match="uint8"):
        tc_numpy.to_image_msg(np.zeros((2, 2, 3), np.float32), "rgb8")
    with pytest.raises(tc.InvalidTensorMetadataError, match="shape"):
        tc_numpy.to_image_msg(np.zeros((2, 2, 4), np.uint8), "rgb8")
    for sizes in ({"height": 2.9, "width": 2}, {"height": 2, "width": 2.5},
                  {"height": 2, "width": 2, "step": 7.9}, {"height": -1, "width": 2}):
        with pytest.raises(tc.InvalidTensorMetadataError, match="whole numbers"):
            tc_numpy.allocate_image_msg(encoding="rgb8", **sizes)  # was truncated: 2.9 -> 2
    assert tc_numpy.allocate_image_msg(np.int64(2), np.int32(3), "rgb8").step == 9
    for error in (tc.UnsupportedEncodingError, tc.InvalidTensorMetadataError, tc.TensorSizeError):
        assert issubclass(error, ValueError) and issubclass(error, tc.TensorConversionError)


def test_image_and_tensor_functions_refuse_each_other():
    image = tc_numpy.allocate_image_msg(2, 2, "mono8")
    tensor = tc_numpy.allocate_tensor_msg((2, 2), np.uint8)
    for module in MODULES.values():
        with pytest.raises(tc.WrongMessageTypeError, match="image_msg"):
            module.from_input_tensor_msg(image)
        with pytest.raises(tc.WrongMessageTypeError, match="tensor_msg"):
            module.from_output_image_msg(tensor)
    with pytest.raises(TypeError):  # WrongMessageTypeError is a TypeError
        tc_numpy.from_output_tensor_msg(image)


def test_image_format_table():
    assert (image_format("bgra8").channels, image_format("bgra8").dtype.name) == (4, "uint8")
    assert image_format("32FC3").dtype.name == "float32" and image_format("32FC3").channels == 3
    assert image_format("16SC2").dtype.name == "int16"


# ------------------------------------------------------------------------------ PointCloud2
CLOUD = get_message_type("sensor_msgs/msg/PointCloud2")
FIELD = get_message_type("sensor_msgs/msg/PointField")
FLOAT32, UINT8, FLOAT64 = 7, 2, 8


def _cloud(points: np.ndarray, *, height: int = 1, row_pad: int = 0) -> object:
    """A cloud whose points are the structured array ``points`` (its dtype gives the fields)."""
    codes = {np.dtype("<f4"): FLOAT32, np.dtype("u1"): UINT8, np.dtype("<f8"): FLOAT64}
    fields = [FIELD(name=name, offset=points.dtype.fields[name][1],
                    datatype=codes[points.dtype.fields[name][0]], count=1)
              for name in points.dtype.names]
    width = points.shape[0] // height
    step = points.dtype.itemsize
    rows = points.reshape(height, width).view(np.uint8).reshape(height, width * step)
    data = np.zeros((height, width * step + row_pad), np.uint8)
    data[:, :width * step] = rows
    return CLOUD(height=height, width=width, fields=fields, is_bigendian=False, point_step=step,
                 row_step=width * step + row_pad, data=data.reshape(-1), is_dense=True)


XYZI = np.dtype({"names": ["x", "y", "z", "intensity"], "formats": ["<f4"] * 4,
                 "offsets": [0, 4, 8, 16], "itemsize": 32})


def _xyzi(n: int) -> np.ndarray:
    points = np.zeros(n, XYZI)
    for i, name in enumerate(XYZI.names):
        points[name] = np.arange(n) * 10 + i
    return points


def test_structured_view_is_zero_copy():
    points = _xyzi(6)
    msg = _cloud(points)
    view = pointcloud.structured_view(msg)
    assert view.dtype == XYZI and view.shape == (6,)
    assert view.ctypes.data == msg.data.numpy(writable=False).ctypes.data
    np.testing.assert_array_equal(view["intensity"], points["intensity"])
    organised = pointcloud.structured_view(_cloud(points, height=2, row_pad=8))
    assert organised.shape == (2, 3)
    np.testing.assert_array_equal(organised["y"].reshape(-1), points["y"])


@pytest.mark.parametrize("framework", list(MODULES))
def test_xyz_tensor_is_a_strided_view_where_the_layout_allows(framework):
    module = MODULES[framework]
    points = _xyzi(5)
    msg = _cloud(points)
    view = module.from_input_pointcloud_msg(msg, ("x", "y", "z"), clone=False)
    expected = np.stack([points[n] for n in ("x", "y", "z")], axis=1)
    assert tuple(view.shape) == (5, 3)
    assert _ptr(view) == msg.data.numpy(writable=False).ctypes.data  # zero-copy
    np.testing.assert_array_equal(to_raw(view), to_raw(expected))
    clone = module.from_input_pointcloud_msg(msg, ("x", "y", "z"))
    assert _ptr(clone) != _ptr(view)
    np.testing.assert_array_equal(to_raw(clone), to_raw(expected))


@pytest.mark.parametrize("framework", list(MODULES))
def test_fields_that_are_not_adjacent_take_one_float32_copy(framework):
    module = MODULES[framework]
    points = _xyzi(4)
    msg = _cloud(points, height=2, row_pad=4)  # padded rows and a gap before intensity
    got = module.from_input_pointcloud_msg(msg, ("x", "intensity"))
    expected = np.stack([points["x"], points["intensity"]], axis=1).astype(np.float32)
    np.testing.assert_array_equal(to_raw(got), to_raw(expected))
    assert _ptr(got) != msg.data.numpy(writable=False).ctypes.data


def test_mixed_dtypes_are_converted_to_float32():
    dtype = np.dtype({"names": ["x", "y", "ring"], "formats": ["<f8", "<f8", "u1"],
                      "offsets": [0, 8, 16], "itemsize": 24})
    points = np.zeros(3, dtype)
    points["x"], points["y"], points["ring"] = [1, 2, 3], [4, 5, 6], [7, 8, 9]
    got = tc_numpy.from_input_pointcloud_msg(_cloud(points), ("x", "ring"))
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, [[1, 7], [2, 8], [3, 9]])
    xy = tc_numpy.from_input_pointcloud_msg(_cloud(points), ("x", "y"), clone=False)
    assert xy.dtype == np.float64  # adjacent float64 fields: a view keeps their dtype


@pytest.mark.parametrize("framework", list(MODULES))
def test_a_multi_count_field_gives_one_column_per_element(framework):
    module = MODULES[framework]
    n = 4
    values = np.arange(n * 4, dtype=np.float32).reshape(n, 4)  # a 3-vector and a scalar
    msg = CLOUD(height=1, width=n, is_bigendian=False, point_step=16, row_step=16 * n,
                data=values.view(np.uint8).reshape(-1), is_dense=True,
                fields=[FIELD(name="normal", offset=0, datatype=FLOAT32, count=3),
                        FIELD(name="curvature", offset=12, datatype=FLOAT32, count=1)])
    got = module.from_input_pointcloud_msg(msg, ("curvature", "normal"))
    assert tuple(got.shape) == (n, 4)
    np.testing.assert_array_equal(to_raw(got), to_raw(values[:, [3, 0, 1, 2]]))
    msg.width, msg.row_step, msg.data = 0, 0, b""  # no point: still 4 columns
    assert tuple(module.from_input_pointcloud_msg(msg, ("curvature", "normal")).shape) == (0, 4)


def test_pointcloud_errors_are_typed():
    msg = _cloud(_xyzi(2))
    with pytest.raises(tc.InvalidTensorMetadataError, match="rgb"):
        tc_numpy.from_input_pointcloud_msg(msg, ("x", "rgb"))
    msg.data = bytes(40)
    with pytest.raises(tc.TensorSizeError):
        pointcloud.structured_view(msg)
    with pytest.raises(tc.WrongMessageTypeError):
        pointcloud.structured_view(tc_numpy.allocate_image_msg(1, 1, "mono8"))
