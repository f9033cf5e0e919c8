"""Typed errors of the rosidl_buffer layer.

Every error this library raises on bad input derives from :class:`RosidlBufferError`, so a caller
(a transport, a subscription callback loop) can catch one family and keep running.
"""

from __future__ import annotations

__all__ = [
    "RosidlBufferError",
    "CpuBackendRequiredError",
    "BackendError",
    "UnknownBackendError",
    "BackendLoadError",
    "SerializationError",
    "DeserializationError",
    "DescriptorTooLargeError",
    "UnknownMessageTypeError",
    "InvalidBufferDataError",
    "InvalidMessageDefinitionError",
    "UnknownFieldError",
    "NativeExtensionMissingError",
    "BufferOverwrittenError",
    "BufferReleasedError",
]


class RosidlBufferError(Exception):
    """Base class of every error raised by rosidl_buffer and the packages built on it."""


class CpuBackendRequiredError(RosidlBufferError, TypeError):
    """A vector-like operation was used on a buffer whose storage is not CPU memory."""

    def __init__(self, operation: str, backend: str) -> None:
        super().__init__(
            f"Operation '{operation}' requires CPU backend. Current backend: {backend}. "
            "Use to_numpy() for a CPU copy."
        )
        self.operation = operation
        self.backend = backend


class BackendError(RosidlBufferError):
    """A buffer backend failed or was misused."""


class UnknownBackendError(BackendError, LookupError):
    """No backend plugin of that name is registered."""


class BackendLoadError(BackendError):
    """A backend plugin is registered but could not be loaded or instantiated."""


class SerializationError(RosidlBufferError, ValueError):
    """A message could not be serialized (a field value does not fit its declared type)."""


class DeserializationError(RosidlBufferError, ValueError):
    """Bytes are not a valid CDR encoding of the requested message type."""


class DescriptorTooLargeError(SerializationError):
    """A backend descriptor serialized to more than MAX_BUFFER_DESCRIPTOR_SIZE bytes."""


class UnknownMessageTypeError(RosidlBufferError, LookupError):
    """No message definition of that name ships with the project or is known to rosbags."""


class InvalidMessageDefinitionError(RosidlBufferError, ValueError):
    """A ``.msg`` definition the project cannot take as written: a field's default value that
    its type cannot hold (``int32 x 1.5``), or a fixed array's of the wrong length."""


class InvalidBufferDataError(RosidlBufferError, TypeError, ValueError):
    """Data that a ``uint8[]`` buffer cannot hold as given: ``None``, a ``str``, values of
    another kind (a float array into a uint8 field) or out of its range (300); never silently
    truncated or cast. Also a ``TypeError`` and a ``ValueError``."""


class UnknownFieldError(RosidlBufferError, AttributeError, TypeError):
    """A message has no field of that name (a misspelt keyword or attribute); the message
    names the closest field. Also an ``AttributeError`` (attributes) and a ``TypeError``
    (keywords), as Python raises for each."""


class NativeExtensionMissingError(RosidlBufferError, ImportError):
    """A native extension of the project (its per-message core, compiled from C at install) is
    not built or does not load; the message names it and the remedy. Also an ``ImportError``."""


class BufferReleasedError(RosidlBufferError, RuntimeError):
    """The buffer was released (``buffer.release()``, ``with buffer:``): its storage may no
    longer be accessed through it. A backend raises a subclass of its own (warp_buffer's
    ``HandleReleasedError``)."""


class BufferOverwrittenError(RosidlBufferError):
    """The backend memory a descriptor names was reused for a later message before this reader
    imported it: its publisher went more than the route's delivery queue (its keep-last depth
    and the few descriptors a reader may hold in hand) ahead. What a keep-last queue drops, so a
    transport counts it as dropped, not as an error."""
