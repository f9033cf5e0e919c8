"""QoS profiles as a bag stores them (``offered_qos_profiles``) and as buffer_pubsub takes them.

A recording stores the profiles of the topic's publishers as the graph shows them (buffer_pubsub's
are reliable and volatile, keep-last ``depth`` or keep-all; a ROS 2 node's may differ).
``ros2 bag play`` reads reliability and durability from the profiles to choose its publishers'
QoS, and so does ``bag play``; deadline, lifespan and lease stay unset (0 s: the default,
infinite).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)

KEEP_LAST = "keep_last"
KEEP_ALL = "keep_all"
#: History depth recorded for a publisher whose own depth the graph does not show (rclcpp's).
DEFAULT_DEPTH = 10
_UNSET = QosTime(0, 0)


def offered_profile(history: str = KEEP_LAST, depth: int = DEFAULT_DEPTH, *,
                    best_effort: bool = False, transient_local: bool = False) -> Qos:
    """The profile a publisher with this history (and reliability, durability) offers."""
    return Qos(history=QosHistory.KEEP_ALL if history == KEEP_ALL else QosHistory.KEEP_LAST,
               depth=depth,
               reliability=QosReliability.BEST_EFFORT if best_effort else QosReliability.RELIABLE,
               durability=(QosDurability.TRANSIENT_LOCAL if transient_local
                           else QosDurability.VOLATILE),
               deadline=_UNSET, lifespan=_UNSET, liveliness=QosLiveliness.AUTOMATIC,
               liveliness_lease_duration=_UNSET, avoid_ros_namespace_conventions=False)


def offered_profiles(publishers: Sequence[Any]) -> list[Qos]:
    """The profiles of a topic's publishers as the graph shows them (``TopicEndpointInfo``, ours
    or another ROS 2 node's), as ``ros2 bag record`` stores them; one default profile when the
    graph shows none."""
    from buffer_pubsub import wire

    profiles = [offered_profile(p.qos_profile.history_name, p.qos_profile.depth,
                                best_effort=p.qos_profile.reliability == wire.RELIABILITY_BEST_EFFORT,
                                transient_local=p.qos_profile.transient_local)
                for p in publishers]
    return profiles or [offered_profile()]


def latched(profiles: Sequence[Qos]) -> bool:
    """Whether every profile offers transient-local durability: rosbag2 then records the topic
    transient-local (a latched message published before the recording starts is in the bag)
    and plays it so (a subscriber that comes later still gets it)."""
    return bool(profiles) and all(p.durability == QosDurability.TRANSIENT_LOCAL
                                  for p in profiles)


def publisher_history(profiles: Sequence[Qos]) -> tuple[str, int]:
    """History and depth for a player's publisher from a topic's recorded profiles: keep-all if
    any recorded publisher kept all (nothing it sent may be dropped), else keep-last of the
    deepest recorded depth (at least 1)."""
    if any(p.history == QosHistory.KEEP_ALL for p in profiles):
        return KEEP_ALL, max([p.depth for p in profiles] + [DEFAULT_DEPTH])
    depth = max((p.depth for p in profiles if p.depth > 0), default=DEFAULT_DEPTH)
    return KEEP_LAST, depth


def publisher_reliability(profiles: Sequence[Qos]) -> str:
    """Reliability for a player's publisher: best-effort when every recorded publisher offered
    it, else reliable. rosbag2 offers the recorded profile when all agree and its reliable
    default when they differ (qos.cpp ``adapt_offer_to_recorded_offers``)."""
    best_effort = bool(profiles) and all(p.reliability == QosReliability.BEST_EFFORT
                                         for p in profiles)
    return "best_effort" if best_effort else "reliable"
