"""warp_buffer_backend: the ``"warp"`` plugin of rosidl_buffer (entry point group
``rosidl_buffer.backends``, name ``warp``) and its descriptor message
``warp_buffer_backend_msgs/msg/WarpBufferDescriptor`` (in ``msg/``).

The environment switches (``WARP_BUFFER_DISABLE_IPC``, and for tests ``WARP_BUFFER_TEST_HOST_ID``
and ``WARP_BUFFER_TEST_USER_ID``) are described in :mod:`warp_buffer`.
"""

from .backend import (
    DESCRIPTOR_TYPE,
    METADATA_VERSION,
    PeerDecision,
    PeerMetadata,
    WarpBufferBackend,
    format_metadata,
    parse_metadata,
)

__all__ = [
    "DESCRIPTOR_TYPE",
    "METADATA_VERSION",
    "PeerDecision",
    "PeerMetadata",
    "WarpBufferBackend",
    "format_metadata",
    "parse_metadata",
]
