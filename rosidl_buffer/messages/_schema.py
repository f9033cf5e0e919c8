"""Message schemas: ``.msg`` definitions parsed by rosbags, turned into field specs we can codegen.

Definitions come from two places: the ROS 2 types rosbags ships, and the ``.msg`` files that
packages of this project (or any installed distribution) ship and announce through the entry point
group ``rosidl_buffer.interfaces`` (name = ROS package name, value = the Python package whose
directory holds the ``.msg`` files). This keeps rosidl_buffer free of imports of its dependents.
"""

from __future__ import annotations

import enum
import functools
import logging
import threading
from collections.abc import Mapping
from typing import Any
from dataclasses import dataclass
from importlib import metadata, resources

from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, TypesysError, get_types_from_msg
from rosbags.typesys import get_typestore as _rosbags_typestore
from rosbags.typesys.store import Typestore

from ..errors import InvalidMessageDefinitionError, UnknownMessageTypeError
from ._defaults import DISTRIBUTION_DEFAULTS, parse_defaults

__all__ = [
    "INTERFACES_ENTRY_POINT_GROUP",
    "FieldKind",
    "FieldSpec",
    "MessageSchema",
    "get_schema",
    "get_typestore",
    "normalize_type_name",
    "register_message_definitions",
]

INTERFACES_ENTRY_POINT_GROUP = "rosidl_buffer.interfaces"

#: The ROS 2 distribution whose standard messages rosbags provides: Lyrical, the distribution of
#: rmw_zenoh 0.10.5, the first with rosidl::Buffer (its Image, CompressedImage, PointCloud2 and
#: UInt8MultiArray have the same definitions and RIHS01 hashes as Jazzy's and Kilted's).
ROS_DISTRIBUTION = Stores.ROS2_LYRICAL

_log = logging.getLogger(__name__)

# Primitive name -> struct format char (little-endian, no padding). 'byte' and 'char' are uint8
# on the wire (rosidl maps them to octet / uint8).
PRIMITIVE_FORMATS: dict[str, str] = {
    "bool": "?",
    "byte": "B",
    "char": "B",
    "int8": "b",
    "uint8": "B",
    "int16": "h",
    "uint16": "H",
    "int32": "i",
    "uint32": "I",
    "int64": "q",
    "uint64": "Q",
    "float32": "f",
    "float64": "d",
}


class FieldKind(enum.Enum):
    """What a field's element is: a ``PRIMITIVE`` type (``bool``, ``byte``, ``uint8``,
    ``float64``, ...), a ``STRING`` (``string`` / ``string<=N``) or a nested ``MESSAGE`` type."""

    PRIMITIVE = "primitive"
    STRING = "string"
    MESSAGE = "message"


@dataclass(frozen=True)
class FieldSpec:
    """One field of a message.

    ``element`` is the primitive name (``"uint8"``, ``"string"``) or the nested message type;
    ``array_length`` > 0 for ``T[N]``; ``is_sequence`` for ``T[]`` / ``T[<=N]`` with
    ``sequence_bound`` (0 = unbounded); ``string_bound`` for ``string<=N``.
    """

    name: str
    kind: FieldKind
    element: str
    array_length: int = 0
    is_sequence: bool = False
    sequence_bound: int = 0
    string_bound: int = 0
    #: The ``.msg`` file's default value (``float64 w 1``), None: the type's zero.
    default: Any = None

    @property
    def is_buffer(self) -> bool:
        """An unbounded ``uint8[]``: held in a :class:`~rosidl_buffer.Buffer`."""
        return self.is_sequence and self.sequence_bound == 0 and self.element == "uint8"

    @property
    def is_collection(self) -> bool:
        """True for a fixed-size array ``T[N]`` or a sequence ``T[]`` / ``T[<=N]``."""
        return self.is_sequence or self.array_length > 0


@dataclass(frozen=True)
class MessageSchema:
    name: str
    fields: tuple[FieldSpec, ...]
    constants: tuple[tuple[str, str, object], ...]


def normalize_type_name(name: str) -> str:
    """``pkg/Name`` or ``pkg/msg/Name`` -> ``pkg/msg/Name``."""
    if not isinstance(name, str):
        raise UnknownMessageTypeError(f"a message type name is a str such as "
                                      f"'sensor_msgs/msg/Image', not {type(name).__name__}")
    parts = name.strip().strip("/").split("/")
    if len(parts) == 2:
        parts = [parts[0], "msg", parts[1]]
    if len(parts) != 3 or not all(parts):
        raise UnknownMessageTypeError(f"not a message type name: {name!r} (expected pkg/msg/Name)")
    return "/".join(parts)


_lock = threading.RLock()
_store: Typestore | None = None
#: Field default values by type name (rosbags drops them: see ._defaults).
_DEFAULTS: dict[str, dict[str, Any]] = {name: dict(values) for name, values in
                                        DISTRIBUTION_DEFAULTS.items()}


_scanned_packages: set[tuple[str, str]] = set()


def _field_as_idl(desc: Any) -> Any:
    """A rosbags field description as ROS 2's IDL has it: ``char`` is ``uint8``."""
    node_type, detail = desc
    if node_type == Nodetype.BASE:
        return (node_type, ("uint8", detail[1])) if detail[0] == "char" else desc
    if node_type in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        return (node_type, (_field_as_idl(detail[0]), detail[1]))
    return desc


def _as_idl(types: dict[str, tuple[list, list]]) -> dict[str, tuple[list, list]]:
    """Message definitions as ROS 2 builds them: ``rosidl_adapter`` turns a ``.msg`` file's
    ``char`` into IDL ``uint8`` (``MSG_TYPE_TO_IDL``), so the type description, hence the REP
    2016 hash rmw_zenoh puts in its keys, records a uint8 (rosbags hashes a ``char`` as its own
    type id, 13), and a top-level ``char[]`` is an unbounded uint8 sequence: a buffer field to
    rmw_zenoh's typesupport. The values (0-255) and the CDR (one byte) are the same either way."""
    return {name: (constants, [(field, _field_as_idl(desc)) for field, desc in fields])
            for name, (constants, fields) in types.items()}


def _shipped_definitions() -> dict[str, tuple[list, list]]:
    """Parse the ``.msg`` files of interface packages announced since the last scan."""
    types: dict[str, tuple[list, list]] = {}
    for entry_point in metadata.entry_points(group=INTERFACES_ENTRY_POINT_GROUP):
        package = entry_point.name
        if (package, entry_point.value) in _scanned_packages:
            continue
        _scanned_packages.add((package, entry_point.value))
        try:
            folder = resources.files(entry_point.value)
            for item in sorted(folder.iterdir(), key=lambda p: p.name):
                if item.name.endswith(".msg"):
                    type_name = f"{package}/msg/{item.name[:-4]}"
                    text = item.read_text(encoding="utf-8")
                    types.update(_as_idl(get_types_from_msg(text, type_name)))
                    _DEFAULTS[type_name] = parse_defaults(text, type_name)
        except Exception as exc:  # one broken package must not hide the others
            _log.warning("cannot load message package %s (%s): %s", package, entry_point.value, exc)
    return types


def get_typestore() -> Typestore:
    """The rosbags typestore holding ROS 2's standard types plus every shipped ``.msg``."""
    global _store
    with _lock:
        if _store is None:
            store = _rosbags_typestore(ROS_DISTRIBUTION)
            store.fielddefs.update(_as_idl(store.fielddefs))  # (before any use of the store)
            shipped = _shipped_definitions()
            if shipped:
                store.register(shipped)
            _store = store
        return _store


def _register_new_packages() -> None:
    """Pick up interface packages installed (or put on sys.path) after the first scan."""
    with _lock:
        store = get_typestore()
        shipped = _shipped_definitions()
        if shipped:
            store.register(shipped)


def register_message_definitions(definitions: dict[str, str]) -> None:
    """Add message types at run time: ``{"pkg/msg/Name": "<.msg text>"}``.

    For definitions that do not ship as files (tests, generated code). A definition rosbags
    cannot parse, a name that already exists with a different definition and a default value
    its field's type cannot hold raise :class:`InvalidMessageDefinitionError`.
    """
    if not isinstance(definitions, Mapping):
        raise InvalidMessageDefinitionError(
            f"definitions are a dict of 'pkg/msg/Name' -> .msg text, not "
            f"{type(definitions).__name__}")
    types: dict[str, tuple[list, list]] = {}
    defaults: dict[str, dict[str, Any]] = {}
    for name, text in definitions.items():
        name = normalize_type_name(name)
        if not isinstance(text, str):
            raise InvalidMessageDefinitionError(
                f"{name}: the definition is .msg text (a str), not {type(text).__name__}")
        try:
            types.update(_as_idl(get_types_from_msg(text, name)))
        except TypesysError as exc:
            raise InvalidMessageDefinitionError(f"{name}: {exc}") from exc
        defaults[name] = parse_defaults(text, name)
    with _lock:
        try:
            get_typestore().register(types)
        except TypesysError as exc:  # a name known already, with another definition
            raise InvalidMessageDefinitionError(str(exc)) from exc
        _DEFAULTS.update(defaults)


def _field_spec(name: str, desc: tuple, default: Any = None) -> FieldSpec:
    node_type, detail = desc
    if node_type == Nodetype.BASE:
        base, bound = detail
        kind = FieldKind.STRING if base == "string" else FieldKind.PRIMITIVE
        if base not in PRIMITIVE_FORMATS and base != "string":
            # wstring and float128 have no agreed CDR form in ROS 2 Python tooling.
            raise UnknownMessageTypeError(f"field {name!r}: type {base!r} is not supported")
        return FieldSpec(name, kind, base, string_bound=bound, default=default)
    if node_type == Nodetype.NAME:
        return FieldSpec(name, FieldKind.MESSAGE, detail)
    sub, count = detail
    element = _field_spec(name, sub)
    if node_type == Nodetype.ARRAY:
        return FieldSpec(name, element.kind, element.element, array_length=count,
                         string_bound=element.string_bound, default=default)
    return FieldSpec(name, element.kind, element.element, is_sequence=True,
                     sequence_bound=count, string_bound=element.string_bound, default=default)


@functools.lru_cache(maxsize=None)
def get_schema(type_name: str) -> MessageSchema:
    """The schema of a message type, raising :class:`UnknownMessageTypeError` if unknown."""
    name = normalize_type_name(type_name)
    store = get_typestore()
    if name not in store.fielddefs:
        _register_new_packages()
    try:
        constants, fields = store.fielddefs[name]
    except KeyError:
        raise UnknownMessageTypeError(
            f"unknown message type {name!r}: not shipped with the project nor known to rosbags "
            f"for {ROS_DISTRIBUTION.value}"
        ) from None
    defaults = _DEFAULTS.get(name, {})
    return MessageSchema(
        name=name,
        fields=tuple(_field_spec(field_name, desc, defaults.get(field_name))
                     for field_name, desc in fields),
        constants=tuple((c[0], c[1], c[2]) for c in constants),
    )
