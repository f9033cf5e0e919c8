"""Typed errors of ``warp-buffer bag`` (the command prints them as one line and exits 1)."""

from __future__ import annotations

from rosidl_buffer.errors import RosidlBufferError

__all__ = ["BagDamagedError", "BagError", "BagReadError", "BagWriteError", "UnknownTopicError"]


class BagError(RosidlBufferError):
    """A bag cannot be recorded, played or described as asked."""


class BagReadError(BagError, OSError):
    """The path is no readable rosbag2 bag (missing, not a bag, damaged)."""


class BagDamagedError(BagReadError):
    """The bag opens but its storage file is damaged inside (bytes changed after it was
    closed): its records disagree with its index, or reading them fails."""


class BagWriteError(BagError, OSError):
    """The bag cannot be created or written (the directory exists, the disk is full)."""


class UnknownTopicError(BagError, LookupError):
    """A topic asked for is not in the graph (record) or not in the bag (play)."""
