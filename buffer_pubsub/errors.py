"""Typed errors of buffer_pubsub; all derive from :class:`rosidl_buffer.RosidlBufferError`."""

from __future__ import annotations

from rosidl_buffer.errors import RosidlBufferError

__all__ = ["PubSubError", "WireFormatError", "NodeClosedError", "TransportConfigError",
           "InvalidEndpointError", "InvalidNameError", "PayloadTooLargeError", "TransportError",
           "ExecutorModeError", "InvalidTimeoutError", "ForkedAfterZenohError",
           "WrongMessageTypeError"]


class PubSubError(RosidlBufferError):
    """Base class of buffer_pubsub errors."""


class WireFormatError(PubSubError, ValueError):
    """A key, liveliness token or attachment does not follow the wire layout."""


class NodeClosedError(PubSubError, RuntimeError):
    """The node (or the endpoint) was closed and can no longer be used."""


class TransportConfigError(PubSubError, ValueError):
    """The Zenoh configuration (file, router endpoint, domain id) is invalid."""


class InvalidEndpointError(PubSubError, ValueError):
    """Bad arguments to create_publisher / create_subscription or publish."""


class WrongMessageTypeError(InvalidEndpointError, TypeError):
    """publish() of something that is not the publisher's message type (a ``TypeError`` as
    well: ``except TypeError`` catches it as Python's own type mismatches)."""


class InvalidNameError(InvalidEndpointError):
    """A node name, namespace or topic name breaks the ROS 2 name rules."""


class PayloadTooLargeError(InvalidEndpointError):
    """A serialized message exceeds the largest message the transport carries."""


class TransportError(PubSubError, RuntimeError):
    """Zenoh failed underneath (wraps ``zenoh.ZError``; the original is the ``__cause__``)."""


class ExecutorModeError(PubSubError, RuntimeError):
    """``spin()`` / ``spin_once()`` on a node whose callbacks run on its own executor thread."""


class InvalidTimeoutError(PubSubError, ValueError):
    """A timeout that is not a number of seconds (NaN, a string)."""


class LoanError(PubSubError, RuntimeError):
    """A loan used wrongly: entered twice, or a factory that returned no message."""


class ForkedAfterZenohError(TransportError):
    """A Node in a process forked (without exec) after its parent had opened a Zenoh session:
    Zenoh's runtime threads are not copied by fork(), and a session opened there hung for good.
    Create fork workers before the first Node, or use multiprocessing's "spawn" or "forkserver"
    start method."""
