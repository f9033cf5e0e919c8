"""Message types for the model: a rosbags type store, names and hashes as rmw_zenoh uses them,
and the deterministic messages a model publisher sends.

- DDS type name: ``type_support_common.cpp`` ``_create_type_name`` (``pkg::msg::dds_::Name_``).
- Type hash: ``rosidl_stringify_type_hash`` (``RIHS01_<hex>``), computed by rosbags.
- ``tensor_msgs/msg/ExperimentalTensor`` is read from the checkout's
  ``tensor_conversions/msg/ExperimentalTensor.msg`` (a type definition, not project code).
- ``FAKE_DESCRIPTOR`` is the model's own descriptor type for its fake backends.
"""

from __future__ import annotations

import pathlib
from typing import Any

import numpy as np
from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

ROOT = pathlib.Path(__file__).resolve().parents[2]
TENSOR = "tensor_msgs/msg/ExperimentalTensor"
TENSOR_MSG_FILE = ROOT / "tensor_conversions" / "msg" / "ExperimentalTensor.msg"
FAKE_DESCRIPTOR = "upstream_model_msgs/msg/FakeDescriptor"
# The first field is a uint8 so that the uint64 after it shows where alignment is counted from.
FAKE_DESCRIPTOR_MSG = """\
uint8 version
uint64 size
string origin
uint8[] data
"""
_NUMPY = {"bool": np.bool_, "byte": np.uint8, "char": np.uint8, "int8": np.int8,
          "uint8": np.uint8, "int16": np.int16, "uint16": np.uint16, "int32": np.int32,
          "uint32": np.uint32, "int64": np.int64, "uint64": np.uint64, "float32": np.float32,
          "float64": np.float64}


def make_typestore() -> Typestore:
    """ROS 2 Lyrical's types, ExperimentalTensor (when the checkout has it) and the model's
    descriptor type."""
    store = get_typestore(Stores.ROS2_LYRICAL)
    types = dict(get_types_from_msg(FAKE_DESCRIPTOR_MSG, FAKE_DESCRIPTOR))
    if TENSOR_MSG_FILE.exists():
        types.update(get_types_from_msg(TENSOR_MSG_FILE.read_text(encoding="utf-8"), TENSOR))
    store.register(types)
    return store


def dds_type_name(ros_type: str) -> str:
    """``pkg/msg/Name`` -> ``pkg::msg::dds_::Name_``."""
    pkg, kind, name = ros_type.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def type_hash(store: Typestore, ros_type: str) -> str:
    """REP 2016 type hash as rmw_zenoh puts it in keys and tokens."""
    return store.hash_rihs01(ros_type)


def buffer_fields(store: Typestore, ros_type: str) -> list[str]:
    """``msg__type_support.cpp.em``: the TOP-LEVEL unbounded ``uint8[]`` members (each one a
    rosidl::Buffer); nested messages and bounded sequences keep the plain CDR sequence."""
    return [name for name, desc in store.fielddefs[ros_type][1]
            if desc[0] == Nodetype.SEQUENCE and desc[1][1] == 0
            and desc[1][0] == (Nodetype.BASE, ("uint8", 0))]


def default_value(store: Typestore, desc: Any) -> Any:
    """The zero value rosbags expects for one field description."""
    kind, detail = desc
    if kind == Nodetype.BASE:
        name = detail[0]
        return "" if name == "string" else (False if name == "bool" else _NUMPY[name](0).item())
    if kind == Nodetype.NAME:
        return default_message(store, detail)
    sub, length = detail
    if sub[0] == Nodetype.BASE and sub[1][0] != "string":
        return np.zeros(length if kind == Nodetype.ARRAY else 0, dtype=_NUMPY[sub[1][0]])
    return [default_value(store, sub) for _ in range(length if kind == Nodetype.ARRAY else 0)]


def default_message(store: Typestore, ros_type: str, **values: Any) -> Any:
    """A message of ``ros_type`` with zero fields, overridden by ``values``."""
    fields = {name: default_value(store, desc) for name, desc in store.fielddefs[ros_type][1]}
    fields.update(values)
    return store.types[ros_type](**fields)


def payload_pattern(index: int, size: int) -> bytes:
    """The bytes a model publisher puts in its buffer field for publish number ``index``."""
    return ((np.arange(size, dtype=np.uint64) + index * 7) % 251).astype(np.uint8).tobytes()


def sample_message(store: Typestore, ros_type: str, index: int, size: int) -> Any:
    """The message a model publisher sends: its buffer fields carry ``payload_pattern``, and a
    few well-known fields say what the bytes are."""
    data = np.frombuffer(payload_pattern(index, size), dtype=np.uint8).copy()
    values: dict[str, Any] = {name: data for name in buffer_fields(store, ros_type)}
    names = {name for name, _ in store.fielddefs[ros_type][1]}
    if ros_type == "sensor_msgs/msg/Image":
        values.update(height=1, width=size, step=size, encoding="mono8")
    elif ros_type == TENSOR:
        values.update(dtype_code=1, dtype_bits=8, dtype_lanes=1,
                      shape=np.array([size], dtype=np.int64))
    if "header" in names:
        values["header"] = default_message(store, "std_msgs/msg/Header", frame_id=f"model/{index}")
    if "data" in names and "data" not in values and isinstance(
            default_value(store, dict(store.fielddefs[ros_type][1])["data"]), str):
        values["data"] = f"model {index}"
    return default_message(store, ros_type, **values)


def scalar_summary(store: Typestore, ros_type: str, message: Any) -> dict[str, Any]:
    """Top-level scalar and string fields, and those one message level down (``header.frame_id``),
    as JSON-friendly values: what a test compares besides the buffer bytes."""
    out: dict[str, Any] = {}
    for name, (kind, detail) in store.fielddefs[ros_type][1]:
        value = getattr(message, name)
        if kind == Nodetype.BASE:
            out[name] = value.item() if hasattr(value, "item") else value
        elif kind == Nodetype.NAME:
            for sub_name, sub_value in scalar_summary(store, detail, value).items():
                if "." not in sub_name:
                    out[f"{name}.{sub_name}"] = sub_value
    return out
