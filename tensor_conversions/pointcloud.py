"""``sensor_msgs/msg/PointCloud2``: a NumPy structured view, and an N x F tensor of chosen fields.

:func:`structured_view` gives the points as a NumPy structured array over the message bytes
(zero-copy for CPU storage; fields keep their byte order, offsets and padding). Shape is
``(width,)`` for an unorganised cloud (``height == 1``), else ``(height, width)``.

``from_input_pointcloud_msg(msg, fields=("x", "y", "z"))`` in each framework module gives an
``(N, F)`` tensor, ``N = height * width``. It is a zero-copy strided view when the layout allows:
the chosen fields share one dtype, have ``count == 1``, sit next to each other in the order asked
(offsets ``o, o + itemsize, ...``), the byte order is this machine's, and rows have no padding
(``row_step == width * point_step`` or ``height == 1``). Otherwise it is ONE copy on the host:
each field converted to float32 and gathered (``clone`` is then irrelevant). ``F`` counts
columns: a field of ``count`` k (e.g. a 3-vector ``normal``) gives k of them, in order.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from typing import Any

import numpy as np

from . import _api
from .dtypes import dtype_from_numpy
from .errors import InvalidTensorMetadataError, TensorSizeError, WrongMessageTypeError
from .metadata import TensorLayout
from .storage import backend_of, host_bytes

__all__ = ["POINTCLOUD_MSG_TYPE", "field_dtype", "from_input_pointcloud_msg", "structured_view"]

POINTCLOUD_MSG_TYPE = "sensor_msgs/msg/PointCloud2"

# sensor_msgs/msg/PointField datatype constants
_DATATYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def _check(msg: Any) -> None:
    if getattr(msg, "__msgtype__", None) != POINTCLOUD_MSG_TYPE:
        name = getattr(msg, "__msgtype__", type(msg).__name__)
        raise WrongMessageTypeError(f"expected a {POINTCLOUD_MSG_TYPE}, got {name}")


def field_dtype(msg: Any) -> np.dtype:
    """The structured NumPy dtype of one point (``itemsize == point_step``)."""
    _check(msg)
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for field in msg.fields:
        code = _DATATYPES.get(int(field.datatype))
        if code is None:
            raise InvalidTensorMetadataError(
                f"PointField {field.name!r} has unknown datatype {field.datatype}")
        count = int(field.count) or 1
        names.append(field.name)
        formats.append(np.dtype(order + code) if count == 1 else (np.dtype(order + code), count))
        offsets.append(int(field.offset))
    try:
        return np.dtype({"names": names, "formats": formats, "offsets": offsets,
                         "itemsize": int(msg.point_step)})
    except (ValueError, TypeError) as exc:
        raise InvalidTensorMetadataError(f"the PointFields do not fit point_step "
                                         f"{msg.point_step}: {exc}") from None


def _check_size(msg: Any) -> None:
    height, width = int(msg.height), int(msg.width)
    if height > 1 and int(msg.row_step) < width * int(msg.point_step):
        raise InvalidTensorMetadataError(
            f"row_step {msg.row_step} is shorter than {width} points of {msg.point_step} bytes")
    need = 0 if height * width == 0 else (height - 1) * int(msg.row_step) + width * int(msg.point_step)
    if len(msg.data) < need:
        raise TensorSizeError(f"a {height}x{width} cloud needs {need} bytes, data has "
                              f"{len(msg.data)}")


def structured_view(msg: Any) -> np.ndarray:
    """The points as a read-only structured array over the message's host bytes (no copy).

    Warp storage is copied to the host first (one copy, ``Buffer.to_numpy``).
    """
    dtype = field_dtype(msg)
    _check_size(msg)
    height, width = int(msg.height), int(msg.width)
    data = msg.data
    raw = host_bytes(data, writable=False) if backend_of(data) == "cpu" else data.to_numpy()
    shape: tuple[int, ...] = (width,) if height == 1 else (height, width)
    strides: tuple[int, ...] = (int(msg.point_step),) if height == 1 else (
        int(msg.row_step), int(msg.point_step))
    if height * width == 0:
        return np.empty(shape, dtype=dtype)
    view = np.ndarray(shape, dtype=dtype, buffer=raw, strides=strides)
    view.flags.writeable = False
    return view


def _zero_copy_layout(msg: Any, names: Sequence[str]) -> TensorLayout | None:
    """The (N, F) strided layout of ``names`` over the bytes, or None if it takes a copy."""
    by_name = {f.name: f for f in msg.fields}
    chosen = [by_name[n] for n in names]
    code = int(chosen[0].datatype)
    itemsize = np.dtype(_DATATYPES[code]).itemsize
    first = int(chosen[0].offset)
    point_step, width, height = int(msg.point_step), int(msg.width), int(msg.height)
    if (any(int(f.datatype) != code or (int(f.count) or 1) != 1 for f in chosen)
            or any(int(f.offset) != first + i * itemsize for i, f in enumerate(chosen))
            or (itemsize > 1 and bool(msg.is_bigendian) != (sys.byteorder == "big"))
            or point_step % itemsize or first % itemsize
            or (height > 1 and int(msg.row_step) != width * point_step)):
        return None
    dtype = dtype_from_numpy(np.dtype(_DATATYPES[code]))
    return TensorLayout(dtype, (height * width, len(chosen)), (point_step // itemsize, 1), first)


def from_input_pointcloud_msg(adapter: _api.Adapter[Any], msg: Any,
                              fields: Sequence[str] = ("x", "y", "z"), clone: bool = True) -> Any:
    _check(msg)
    names = list(fields)
    known = [f.name for f in msg.fields]
    missing = [n for n in names if n not in known]
    if not names or missing:
        raise InvalidTensorMetadataError(
            f"PointCloud2 has no field(s) {missing or '(none asked)'}; it has {known}")
    field_dtype(msg)  # validates datatypes and point_step
    _check_size(msg)
    layout = _zero_copy_layout(msg, names)
    if layout is not None:
        return _api.input_native(adapter, msg, layout, clone)
    points = structured_view(msg).reshape(-1)
    # A field of count k gives k columns (from its dtype: the count holds with no point too)
    columns = [points[name].reshape(points.shape[0], int(np.prod(points.dtype[name].shape)))
               for name in names]
    table = np.empty((points.shape[0], sum(c.shape[1] for c in columns)), dtype=np.float32)
    start = 0
    for column in columns:
        table[:, start:start + column.shape[1]] = column
        start += column.shape[1]
    carrier = _CopyMsg(table)
    if clone:  # the copy asked for is this one: the caller's, writable
        return _api.output_native(adapter, carrier, carrier.layout)
    return _api.input_native(adapter, carrier, carrier.layout, clone=False)


class _CopyMsg:
    """A stand-in message over a host copy, so the copy reaches the framework the same way."""

    __slots__ = ("data", "layout", "_native")

    def __init__(self, table: np.ndarray) -> None:
        from rosidl_buffer import Buffer

        self.data = Buffer(table.reshape(-1).view(np.uint8))
        self._native = None
        self.layout = TensorLayout(dtype_from_numpy(np.float32), table.shape, (table.shape[1], 1), 0)
