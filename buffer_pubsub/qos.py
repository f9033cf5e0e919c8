"""QoS profiles as rclpy writes them: ``create_publisher(Image, "/image", qos_profile_sensor_data)``.

An endpoint's QoS is its keep-last ``depth`` (or keep-all ``history``), its ``reliability`` and its
``durability``; each node method takes them as keywords or as one :class:`QoSProfile`. The
policies are strings (``"best_effort"``); the enums rclpy users write
(``ReliabilityPolicy.BEST_EFFORT``) are the same strings, and upper-case names are read too.

What each policy does on the wire is rmw_zenoh's: ``best_effort`` publishes with Zenoh's
best-effort reliability and congestion control DROP, keep-all and reliable with BLOCK; a
transient-local reliable pair recovers missed samples from the publisher's cache. The QoS rides in
the endpoint's liveliness token, so ``ros2 topic info -v`` shows it. Deadline, lifespan and
liveliness are rmw_zenoh's defaults (it enforces none of them either).
"""

from __future__ import annotations

import dataclasses
import enum
from typing import Any

from . import wire
from .errors import InvalidEndpointError

__all__ = ["DurabilityPolicy", "HistoryPolicy", "MAX_DEPTH", "QoSProfile", "ReliabilityPolicy",
           "qos_profile_sensor_data", "qos_profile_system_default", "resolve_qos"]

#: What rmw_zenoh makes of depth 0 (rmw's "system default"; qos.cpp): a keep-all profile's
SYSTEM_DEFAULT_DEPTH = 42
#: Deepest keep-last queue (rmw's depth is a size_t; ours a queue in memory).
MAX_DEPTH = 2**31 - 1


class HistoryPolicy(str, enum.Enum):
    """What an endpoint's queue keeps: ``KEEP_LAST``, the newest ``depth`` messages, or
    ``KEEP_ALL``, every message (a reliable publisher then blocks rather than drop)."""

    KEEP_LAST = wire.KEEP_LAST
    KEEP_ALL = wire.KEEP_ALL


class ReliabilityPolicy(str, enum.Enum):
    """Whether delivery is guaranteed: ``RELIABLE`` retransmits lost messages,
    ``BEST_EFFORT`` may drop them (what sensor data usually wants)."""

    RELIABLE = wire.RELIABLE
    BEST_EFFORT = wire.BEST_EFFORT


class DurabilityPolicy(str, enum.Enum):
    """Whether late joiners see past messages: ``VOLATILE`` sends only what is published after
    a subscription appears, ``TRANSIENT_LOCAL`` lets it recover the publisher's cached ones."""

    VOLATILE = wire.VOLATILE
    TRANSIENT_LOCAL = wire.TRANSIENT_LOCAL


_CHOICES = {"history": HistoryPolicy, "reliability": ReliabilityPolicy,
            "durability": DurabilityPolicy}


def _policy(name: str, value: Any) -> str:
    choices = _CHOICES[name]
    if isinstance(value, choices):
        return value.value
    text = value.lower() if isinstance(value, str) else value
    if text not in {c.value for c in choices}:
        raise InvalidEndpointError(
            f"{name} must be one of {[c.value for c in choices]}, got {value!r}")
    return text


@dataclasses.dataclass(frozen=True)
class QoSProfile:
    """An endpoint's QoS: keep-last ``depth`` (ignored by keep-all, which keeps every message,
    but for a transient-local publisher's cache; 0 there is rmw_zenoh's default, 42),
    ``history``, ``reliability`` and ``durability``; checked when made."""

    depth: int = 10
    history: str = wire.KEEP_LAST
    reliability: str = wire.RELIABLE
    durability: str = wire.VOLATILE

    def __post_init__(self) -> None:
        for name in _CHOICES:
            object.__setattr__(self, name, _policy(name, getattr(self, name)))
        depth = self.depth
        keep_all = self.history == wire.KEEP_ALL
        if keep_all and depth == 0 and not isinstance(depth, bool):
            # rclpy's keep-all default (rmw's "system default" depth): rmw_zenoh's
            # best_available_qos makes it its default depth, which a transient-local cache keeps
            depth = SYSTEM_DEFAULT_DEPTH
            object.__setattr__(self, "depth", depth)
        if isinstance(depth, bool) or not isinstance(depth, int) or not 0 < depth <= MAX_DEPTH:
            raise InvalidEndpointError(f"depth must be an int in 1..{MAX_DEPTH}"
                                       + (" (or 0 for keep-all)" if keep_all else "")
                                       + f", got {depth!r}")

    @property
    def transient_local(self) -> bool:
        """True when ``durability`` is ``transient_local``."""
        return self.durability == wire.TRANSIENT_LOCAL


class _DefaultDepth(int):
    """The default ``depth`` (10), told apart from an explicit 10 by identity."""


#: The node methods' default ``depth`` (an int 10 of its own: see :func:`resolve_qos`).
DEFAULT_DEPTH = _DefaultDepth(10)

#: rclpy's profile for sensors (a camera, a lidar): keep-last 5, best-effort.
qos_profile_sensor_data = QoSProfile(depth=5, reliability=wire.BEST_EFFORT)
#: The defaults: keep-last 10, reliable, volatile.
qos_profile_system_default = QoSProfile()


def resolve_qos(depth: int | QoSProfile, history: Any, reliability: Any, durability: Any,
                qos_profile: int | QoSProfile | None) -> QoSProfile:
    """One profile from a node method's arguments: ``depth`` (an int or a profile, positional as
    rclpy's ``qos_profile``), or ``qos_profile=`` (rclpy's keyword), and the policy keywords
    (None: the profile's, else the default). A profile and policy keywords together are
    refused: which one wins would be a guess."""
    if qos_profile is not None:
        if depth is not DEFAULT_DEPTH:
            raise InvalidEndpointError("give either depth or qos_profile, not both")
        depth = qos_profile
    if isinstance(depth, QoSProfile):
        given = [n for n, v in (("history", history), ("reliability", reliability),
                                ("durability", durability)) if v is not None]
        if given:
            raise InvalidEndpointError(f"give {', '.join(given)} in the QoSProfile, not beside it")
        return depth
    return QoSProfile(depth=depth, history=wire.KEEP_LAST if history is None else history,
                      reliability=wire.RELIABLE if reliability is None else reliability,
                      durability=wire.VOLATILE if durability is None else durability)


