"""Message types and their ROS 2 CDR serialization.

``get_message_type(name)`` returns the generated class of any message shipped with an installed
package (``.msg`` files announced through the ``rosidl_buffer.interfaces`` entry points) or known
to rosbags for ROS 2; ``serialize_message`` / ``deserialize_message`` convert to and from CDR.
"""

from ._cdr import (
    BUFFER_DESCRIPTOR_MARKER,
    CDR_HEADER,
    BufferRoute,
    deserialize_message,
    serialize_message,
    serialized_size,
)
from ._classes import (
    Message,
    get_message_type,
    iter_buffers,
    numpy_dtype,
    release_buffers,
    seal_buffers,
)
from ._schema import (
    INTERFACES_ENTRY_POINT_GROUP,
    FieldKind,
    FieldSpec,
    get_schema,
    get_typestore,
    normalize_type_name,
    register_message_definitions,
)

__all__ = [
    "BUFFER_DESCRIPTOR_MARKER",
    "CDR_HEADER",
    "INTERFACES_ENTRY_POINT_GROUP",
    "BufferRoute",
    "FieldKind",
    "FieldSpec",
    "Message",
    "buffer_fields",
    "deserialize_message",
    "fields_of",
    "get_message_type",
    "get_schema",
    "get_type_hash",
    "get_typestore",
    "iter_buffers",
    "normalize_type_name",
    "numpy_dtype",
    "register_message_definitions",
    "release_buffers",
    "seal_buffers",
    "serialize_message",
    "serialized_size",
]


def get_type_hash(name: str) -> str:
    """The type's REP 2016 hash, ``RIHS01_<64 hex>``, as rmw_zenoh puts in its keys."""
    return get_typestore().hash_rihs01(normalize_type_name(name))


def fields_of(msg_type: type[Message]) -> tuple[FieldSpec, ...]:
    """The fields of a generated message class, in order."""
    # underscored on purpose (a class attribute of every generated message): never a field name
    return msg_type._schema.fields


def buffer_fields(msg_type: type[Message]) -> frozenset[str]:
    """The names of ``msg_type``'s top-level unbounded ``uint8[]`` fields: held in a
    :class:`~rosidl_buffer.Buffer`, the ones that travel in backend form. A type with any is
    buffer-aware in rmw_zenoh's routing."""
    # underscored on purpose (a class attribute of every generated message): never a field name
    return msg_type._buffer_fields
