"""``sensor_msgs/msg/Image`` as an HWC tensor view, with the row padding (``step``) kept as the
row stride, through the same core and framework adapters as ExperimentalTensor.

An image of ``C`` channels is viewed with shape ``(height, width, C)``; single-channel encodings
(mono8, 16UC1, 32FC1, Bayer) with shape ``(height, width)``, as cv_bridge does. Strides are
``(step / itemsize, C, 1)`` elements, so a padded row costs nothing. The framework modules expose
``allocate_image_msg``, ``from_output_image_msg``, ``from_input_image_msg`` and ``to_image_msg``.

Encodings: mono8, mono16, rgb8, bgr8, rgba8, bgra8, rgb16, bgr16, rgba16, bgra16, the OpenCV-style
``{8U,8S,16U,16S,32S,32F,64F}C{1..4}`` and the 8-bit Bayer patterns (a raw single-channel mosaic,
not demosaiced). Compressed, YUV and 16-bit Bayer encodings raise
:class:`UnsupportedEncodingError`. Multi-byte pixels with ``is_bigendian`` different from this
machine's order cannot be viewed zero-copy: ``clone=True`` converts them on the host (one copy),
``clone=False`` raises.
"""

from __future__ import annotations

import re
import sys
from typing import Any

import numpy as np

from rosidl_buffer.messages import get_message_type

from . import _api
from .dtypes import DType, dtype_from_name
from .errors import (
    InvalidTensorMetadataError,
    TensorSizeError,
    UnsupportedDTypeError,
    UnsupportedEncodingError,
    WrongMessageTypeError,
)
from .metadata import TensorLayout, contiguous_strides, normalize_shape
from .storage import allocate_data, backend_of, host_bytes

__all__ = [
    "IMAGE_MSG_TYPE",
    "NATIVE_BIGENDIAN",
    "ImageFormat",
    "allocate_image_msg",
    "from_input_image_msg",
    "from_output_image_msg",
    "image_format",
    "image_layout",
    "to_image_msg",
]

IMAGE_MSG_TYPE = "sensor_msgs/msg/Image"
#: ``is_bigendian`` of an image in this machine's byte order.
NATIVE_BIGENDIAN = int(sys.byteorder == "big")

_NAMED = {
    "mono8": (1, "uint8"), "mono16": (1, "uint16"),
    "rgb8": (3, "uint8"), "bgr8": (3, "uint8"), "rgba8": (4, "uint8"), "bgra8": (4, "uint8"),
    "rgb16": (3, "uint16"), "bgr16": (3, "uint16"), "rgba16": (4, "uint16"),
    "bgra16": (4, "uint16"),
    **{f"bayer_{p}8": (1, "uint8") for p in ("rggb", "bggr", "gbrg", "grbg")},
}
_CV_DEPTHS = {"8U": "uint8", "8S": "int8", "16U": "uint16", "16S": "int16", "32S": "int32",
              "32F": "float32", "64F": "float64"}
_CV = re.compile(r"^(8U|8S|16U|16S|32S|32F|64F)C([1-4])$")


class ImageFormat:
    """An encoding's pixel layout: ``channels`` and element :class:`DType`."""

    __slots__ = ("encoding", "channels", "dtype")

    def __init__(self, encoding: str, channels: int, dtype: DType) -> None:
        self.encoding, self.channels, self.dtype = encoding, channels, dtype

    def shape(self, height: int, width: int) -> tuple[int, ...]:
        return (height, width) if self.channels == 1 else (height, width, self.channels)

    @property
    def pixel_bytes(self) -> int:
        return self.channels * self.dtype.itemsize

    def __repr__(self) -> str:
        return f"ImageFormat({self.encoding!r}, channels={self.channels}, {self.dtype.name})"


_FORMATS: dict[str, ImageFormat] = {}


def image_format(encoding: str) -> ImageFormat:
    """The :class:`ImageFormat` of ``encoding``; unsupported ones raise
    :class:`UnsupportedEncodingError`."""
    found = _FORMATS.get(encoding)
    if found is not None:
        return found
    spec = _NAMED.get(encoding)
    match = _CV.match(encoding) if isinstance(encoding, str) else None
    if spec is None and match is not None:
        spec = (int(match.group(2)), _CV_DEPTHS[match.group(1)])
    if spec is None:
        raise UnsupportedEncodingError(
            f"image encoding {encoding!r} is not supported; supported: "
            f"{', '.join(_NAMED)} and {{8U,8S,16U,16S,32S,32F,64F}}C{{1..4}}")
    found = _FORMATS[encoding] = ImageFormat(encoding, spec[0], dtype_from_name(spec[1]))
    return found


def image_msg_type() -> type:
    return get_message_type(IMAGE_MSG_TYPE)


def _check_image_msg(msg: Any) -> None:
    if getattr(msg, "__msgtype__", None) != IMAGE_MSG_TYPE:
        name = getattr(msg, "__msgtype__", type(msg).__name__)
        hint = " (use the *_tensor_msg functions)" if name.endswith("ExperimentalTensor") else ""
        raise WrongMessageTypeError(f"expected a {IMAGE_MSG_TYPE}, got {name}{hint}")


def _row_stride(fmt: ImageFormat, width: int, step: int) -> int:
    """``step`` in elements, after checking it holds a row and keeps elements aligned."""
    row = width * fmt.pixel_bytes
    if step < row:
        raise InvalidTensorMetadataError(
            f"step {step} is shorter than a {width}-pixel {fmt.encoding} row ({row} bytes)")
    if step % fmt.dtype.itemsize:
        raise InvalidTensorMetadataError(
            f"step {step} is not a multiple of the {fmt.dtype.itemsize}-byte {fmt.dtype.name} "
            f"elements of {fmt.encoding}; the rows cannot be viewed as strides")
    return step // fmt.dtype.itemsize


_LAYOUTS: dict[tuple[Any, ...], tuple[TensorLayout, bool]] = {}


def image_layout(msg: Any) -> tuple[TensorLayout, bool]:
    """The HWC :class:`TensorLayout` of an Image and whether its bytes are in this machine's
    order (validated once per distinct metadata)."""
    _check_image_msg(msg)
    key = (msg.height, msg.width, msg.encoding, msg.is_bigendian, msg.step, len(msg.data))
    found = _LAYOUTS.get(key)
    if found is None:
        found = _validate(*key)
        if len(_LAYOUTS) >= 256:
            _LAYOUTS.clear()
        _LAYOUTS[key] = found
    return found


def _validate(height: int, width: int, encoding: str, is_bigendian: int, step: int,
              nbytes: int) -> tuple[TensorLayout, bool]:
    fmt = image_format(encoding)
    height, width, step = int(height), int(width), int(step)
    row = _row_stride(fmt, width, step)
    need = step * height
    if nbytes < need:
        raise TensorSizeError(
            f"a {height}x{width} {encoding} image with step {step} needs {need} bytes of data, "
            f"the message has {nbytes}")
    strides = (row, fmt.channels, 1) if fmt.channels > 1 else (row, 1)
    native = fmt.dtype.itemsize == 1 or int(bool(is_bigendian)) == NATIVE_BIGENDIAN
    return TensorLayout(fmt.dtype, fmt.shape(height, width), strides, 0), native


def _sizes(what: str = "image", **sizes: Any) -> tuple[int, ...]:
    """The sizes given of an ``what`` (image, point cloud), as non-negative whole numbers (2.9
    is refused, not truncated)."""
    try:
        return normalize_shape(tuple(sizes.values()))
    except InvalidTensorMetadataError:
        given = ", ".join(f"{name}={value!r}" for name, value in sizes.items())
        raise InvalidTensorMetadataError(
            f"{what} sizes must be non-negative whole numbers, got {given}") from None


def image_spec(adapter: _api.Adapter[Any], height: int, width: int, encoding: str,
               step: int | None = None) -> tuple[int, int, int, TensorLayout]:
    """``(height, width, step, layout)`` of a new image (``allocate_image_msg``'s arguments,
    checked: sizes, encoding, the framework's dtype, a step that holds a row)."""
    fmt = image_format(encoding)
    adapter.check_dtype(fmt.dtype)
    height, width = _sizes(height=height, width=width)
    step = width * fmt.pixel_bytes if step is None else _sizes(step=step)[0]
    row = _row_stride(fmt, width, step)
    strides = (row, fmt.channels, 1) if fmt.channels > 1 else (row, 1)
    return height, width, step, TensorLayout(fmt.dtype, fmt.shape(height, width), strides, 0)


def new_image_msg(height: int, width: int, encoding: str, step: int, data: Any) -> Any:
    """An Image with these (checked) sizes over ``data``, in this machine's byte order."""
    return image_msg_type()(height=height, width=width, encoding=encoding,
                            is_bigendian=NATIVE_BIGENDIAN, step=step, data=data)


def allocate_image_msg(adapter: _api.Adapter[Any], height: int, width: int, encoding: str,
                       backend: str = "cpu", device: Any = None, step: int | None = None) -> Any:
    height, width, step, _layout = image_spec(adapter, height, width, encoding, step)
    return new_image_msg(height, width, encoding, step,
                         allocate_data(step * height, backend, device))


def from_output_image_msg(adapter: _api.Adapter[Any], msg: Any) -> Any:
    layout, native = image_layout(msg)
    if not native:
        raise InvalidTensorMetadataError(
            "this image's bytes are in the other byte order (is_bigendian); write a new message "
            "with allocate_image_msg")
    return _api.output_native(adapter, msg, layout)


def from_input_image_msg(adapter: _api.Adapter[Any], msg: Any, clone: bool = True) -> Any:
    layout, native = image_layout(msg)
    if native:
        return _api.input_native(adapter, msg, layout, clone)
    if not clone:
        raise InvalidTensorMetadataError(
            f"this {msg.encoding} image is in the other byte order (is_bigendian="
            f"{msg.is_bigendian}); a zero-copy view cannot convert it: use clone=True")
    if backend_of(msg.data) != "cpu":
        raise InvalidTensorMetadataError(
            "foreign byte order is converted only for CPU storage; subscribe with the cpu backend")
    # One documented host copy: view the bytes with their byte order, convert to native order.
    raw = host_bytes(msg.data, writable=False)
    foreign = np.ndarray(layout.shape, dtype=layout.dtype.numpy_dtype().newbyteorder(),
                         buffer=raw, strides=layout.byte_strides)
    copy = np.ascontiguousarray(foreign.astype(layout.dtype.numpy_dtype()))
    # An empty image's copy has 0 strides: its row is still width pixels long
    row = msg.width * image_format(msg.encoding).pixel_bytes
    temp = image_msg_type()(height=msg.height, width=msg.width, encoding=msg.encoding,
                            is_bigendian=NATIVE_BIGENDIAN, step=row,
                            data=copy.reshape(-1).view(np.uint8))
    # The copy is the caller's (clone=True): a writable view of it, as every clone is
    return _api.output_native(adapter, temp, image_layout(temp)[0])


def to_image_msg(adapter: _api.Adapter[Any], value: Any, encoding: str, *,
                 backend: str | None = None, device: Any = None) -> Any:
    fmt = image_format(encoding)
    shape, dtype, value_backend, value_device = adapter.describe(value)
    if dtype != fmt.dtype:
        raise UnsupportedDTypeError(
            f"{encoding} holds {fmt.dtype.name} pixels, the value is {dtype.name}")
    channels = 1 if len(shape) == 2 else (shape[2] if len(shape) == 3 else -1)
    if channels != fmt.channels:
        raise InvalidTensorMetadataError(
            f"{encoding} needs shape (height, width{'' if fmt.channels == 1 else ', ' + str(fmt.channels)}), "
            f"got {tuple(shape)}")
    if backend is None:
        backend, device = value_backend, value_device if device is None else device
    msg = allocate_image_msg(adapter, shape[0], shape[1], encoding, backend, device)
    layout, _ = image_layout(msg)
    flat = TensorLayout(fmt.dtype, tuple(shape), contiguous_strides(shape), 0)
    _api.write_value(adapter, msg, flat if len(shape) != len(layout.shape) else layout, value)
    return msg
