"""``sensor_msgs/msg/PointCloud2``: a NumPy structured view, and an N x F tensor of chosen fields.

:func:`structured_view` gives the points as a NumPy structured array over the message bytes
(zero-copy for CPU storage; fields keep their byte order, offsets and padding). Shape is
``(width,)`` for an unorganised cloud (``height == 1``), else ``(height, width)``.

``allocate_pointcloud_msg(width, fields, dtype)`` makes a cloud of packed fields of one dtype
(``point_step = len(fields) * itemsize``), and ``from_output_pointcloud_msg(msg)`` gives the
writable ``(N, F)`` view of its points to fill (``loan_pointcloud_msg`` loans such clouds from a
publisher's pool, :mod:`.loan`).

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

from rosidl_buffer.messages import get_message_type

from . import _api
from .dtypes import DType, dtype_from_numpy
from .errors import (
    InvalidTensorMetadataError,
    TensorSizeError,
    UnsupportedDTypeError,
    WrongMessageTypeError,
)
from .metadata import TensorLayout
from .storage import allocate_data, backend_of, host_bytes

__all__ = ["POINTCLOUD_MSG_TYPE", "allocate_pointcloud_msg", "field_dtype",
           "from_input_pointcloud_msg", "from_output_pointcloud_msg", "structured_view"]

POINTCLOUD_MSG_TYPE = "sensor_msgs/msg/PointCloud2"

# sensor_msgs/msg/PointField datatype constants
_DATATYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
_DATATYPE_OF = {code: datatype for datatype, code in _DATATYPES.items()}


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


def _chosen(msg: Any, fields: Sequence[str] | None) -> tuple[list[str], TensorLayout | None]:
    """The field names asked (all for None), checked against the cloud, and their zero-copy
    ``(N, F)`` layout (None: they take a copy)."""
    _check(msg)
    known = [f.name for f in msg.fields]
    names = known if fields is None else list(fields)
    missing = [n for n in names if n not in known]
    if not names or missing:
        raise InvalidTensorMetadataError(
            f"PointCloud2 has no field(s) {missing or '(none asked)'}; it has {known}")
    field_dtype(msg)  # validates datatypes and point_step
    _check_size(msg)
    return names, _zero_copy_layout(msg, names)


def from_input_pointcloud_msg(adapter: _api.Adapter[Any], msg: Any,
                              fields: Sequence[str] = ("x", "y", "z"), clone: bool = True) -> Any:
    names, layout = _chosen(msg, fields)
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


def cloud_spec(adapter: _api.Adapter[Any], width: int, fields: Sequence[str], dtype: Any,
               height: int = 1) -> tuple[tuple[str, ...], DType, int, int, TensorLayout]:
    """``(names, dtype, height, width, layout)`` of a new cloud of packed ``fields`` of one
    ``dtype`` (``allocate_pointcloud_msg``'s arguments, checked); ``layout`` is the writable
    ``(height * width, len(fields))`` view of its points."""
    names = tuple(fields)
    if not names or not all(isinstance(n, str) and n for n in names) or len(set(names)) != len(
            names):
        raise InvalidTensorMetadataError(
            f"fields must be distinct non-empty names, got {list(fields)!r}")
    dt = adapter.to_dtype(dtype)
    adapter.check_dtype(dt)
    try:
        code = dt.numpy_dtype().str[1:]
    except UnsupportedDTypeError:
        code = None
    if code not in _DATATYPE_OF:
        raise UnsupportedDTypeError(
            f"a PointField holds int8..uint32, float32 or float64 values, not {dt.name}")
    from .image import _sizes

    height, width = _sizes("point cloud", height=height, width=width)
    count = len(names)
    layout = TensorLayout(dt, (height * width, count), (count, 1), 0)
    return names, dt, height, width, layout


def _point_fields(names: tuple[str, ...], dt: DType) -> list[Any]:
    point_field = get_message_type("sensor_msgs/msg/PointField")
    datatype = _DATATYPE_OF[dt.numpy_dtype().str[1:]]
    return [point_field(name=name, offset=i * dt.itemsize, datatype=datatype, count=1)
            for i, name in enumerate(names)]


def write_cloud_metadata(msg: Any, names: tuple[str, ...], dt: DType, height: int,
                         width: int) -> None:
    """The metadata of a cloud of packed ``names`` of ``dt`` (this machine's byte order)."""
    point_step = len(names) * dt.itemsize
    msg.height, msg.width = height, width
    msg.fields = _point_fields(names, dt)
    msg.is_bigendian = sys.byteorder == "big"
    msg.point_step, msg.row_step = point_step, point_step * width
    msg.is_dense = True


def new_cloud_msg(names: tuple[str, ...], dt: DType, height: int, width: int,
                  data: Any) -> Any:
    """A PointCloud2 of packed ``names`` of ``dt`` over ``data``."""
    msg = get_message_type(POINTCLOUD_MSG_TYPE)(data=data)
    write_cloud_metadata(msg, names, dt, height, width)
    return msg


def cloud_matches(msg: Any, names: tuple[str, ...], dt: DType, height: int,
                  width: int) -> bool:
    """``msg`` still has the metadata :func:`write_cloud_metadata` wrote."""
    point_step = len(names) * dt.itemsize
    if (msg.height != height or msg.width != width or msg.point_step != point_step
            or msg.row_step != point_step * width or bool(msg.is_bigendian) != (
                sys.byteorder == "big")):
        return False
    fields = msg.fields
    if len(fields) != len(names):
        return False
    datatype = _DATATYPE_OF[dt.numpy_dtype().str[1:]]
    return all(f.name == name and f.offset == i * dt.itemsize and f.datatype == datatype
               and f.count == 1 for i, (f, name) in enumerate(zip(fields, names)))


def allocate_pointcloud_msg(adapter: _api.Adapter[Any], width: int, fields: Sequence[str],
                            dtype: Any, height: int = 1, backend: str = "cpu",
                            device: Any = None) -> Any:
    names, dt, height, width, layout = cloud_spec(adapter, width, fields, dtype, height)
    return new_cloud_msg(names, dt, height, width,
                         allocate_data(layout.required_nbytes, backend, device))


def from_output_pointcloud_msg(adapter: _api.Adapter[Any], msg: Any,
                               fields: Sequence[str] | None = None) -> Any:
    names, layout = _chosen(msg, fields)
    if layout is None:
        raise InvalidTensorMetadataError(
            f"fields {names} are not one strided view of the points (one dtype, count 1, "
            "adjacent in that order, this machine's byte order, rows unpadded): write them "
            "through structured_view of a CPU copy, or allocate a packed cloud")
    return _api.output_native(adapter, msg, layout)


class _CopyMsg:
    """A stand-in message over a host copy, so the copy reaches the framework the same way."""

    __slots__ = ("data", "layout", "_native")

    def __init__(self, table: np.ndarray) -> None:
        from rosidl_buffer import Buffer

        self.data = Buffer(table.reshape(-1).view(np.uint8))
        self._native = None
        self.layout = TensorLayout(dtype_from_numpy(np.float32), table.shape, (table.shape[1], 1), 0)
