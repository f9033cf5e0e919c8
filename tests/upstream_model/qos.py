"""QoS as rmw_zenoh writes it into liveliness tokens.

Models ``qos.cpp`` (``QoS::QoS`` defaults, ``QoS::best_available_qos``) and
``liveliness_utils.cpp`` (``qos_to_keyexpr``, ``keyexpr_to_qos``, ``str_to_size_t``) of
rmw_zenoh_cpp 0.10.5 / 0.12.0. Enum numbers are rmw's (``rmw/types.h``).
"""

from __future__ import annotations

import dataclasses
from enum import IntEnum

U64_MAX = 2**64 - 1


class History(IntEnum):
    SYSTEM_DEFAULT = 0
    KEEP_LAST = 1
    KEEP_ALL = 2
    UNKNOWN = 3


class Reliability(IntEnum):
    SYSTEM_DEFAULT = 0
    RELIABLE = 1
    BEST_EFFORT = 2
    UNKNOWN = 3
    BEST_AVAILABLE = 4


class Durability(IntEnum):
    SYSTEM_DEFAULT = 0
    TRANSIENT_LOCAL = 1
    VOLATILE = 2
    UNKNOWN = 3
    BEST_AVAILABLE = 4


class Liveliness(IntEnum):
    SYSTEM_DEFAULT = 0
    AUTOMATIC = 1
    MANUAL_BY_NODE = 2  # deprecated: absent from liveliness_utils.cpp's string tables
    MANUAL_BY_TOPIC = 3
    UNKNOWN = 4
    BEST_AVAILABLE = 5


#: RMW_DURATION_INFINITE as (sec, nsec).
INFINITE = (9223372036, 854775807)
#: RMW_QOS_DEADLINE_DEFAULT / LIFESPAN / LEASE_DURATION default: "unspecified".
UNSPECIFIED = (0, 0)


@dataclasses.dataclass(frozen=True)
class QoS:
    """An rmw_qos_profile_t (durations as (sec, nsec))."""

    history: int = History.KEEP_LAST
    depth: int = 10
    reliability: int = Reliability.RELIABLE
    durability: int = Durability.VOLATILE
    deadline: tuple[int, int] = UNSPECIFIED
    lifespan: tuple[int, int] = UNSPECIFIED
    liveliness: int = Liveliness.SYSTEM_DEFAULT
    lease: tuple[int, int] = UNSPECIFIED


#: qos.cpp, QoS::QoS(): rmw_zenoh's defaults, the reference of the token's QoS segment.
DEFAULT_QOS = QoS(history=History.KEEP_LAST, depth=42, reliability=Reliability.RELIABLE,
                  durability=Durability.VOLATILE, deadline=INFINITE, lifespan=INFINITE,
                  liveliness=Liveliness.AUTOMATIC, lease=INFINITE)

# liveliness_utils.cpp: the str_to_qos_* tables (MANUAL_BY_NODE has no entry).
_HISTORY_VALUES = {0, 1, 2, 3}
_RELIABILITY_VALUES = {0, 1, 2, 3, 4}
_DURABILITY_VALUES = {0, 1, 2, 3, 4}
_LIVELINESS_VALUES = {0, 1, 3, 4, 5}


def adapt(qos: QoS) -> QoS:
    """qos.cpp ``best_available_qos``: what a publisher or subscription puts in its token."""
    d = DEFAULT_QOS
    history = d.history if qos.history in (History.SYSTEM_DEFAULT, History.UNKNOWN) else qos.history
    reliability = (d.reliability if qos.reliability in (Reliability.SYSTEM_DEFAULT,
                                                        Reliability.UNKNOWN) else qos.reliability)
    durability = (d.durability if qos.durability in (Durability.SYSTEM_DEFAULT,
                                                     Durability.UNKNOWN) else qos.durability)
    liveliness = (d.liveliness if qos.liveliness in (Liveliness.SYSTEM_DEFAULT,
                                                     Liveliness.UNKNOWN) else qos.liveliness)
    return QoS(history=history, depth=qos.depth or d.depth, reliability=reliability,
               durability=durability,
               deadline=d.deadline if qos.deadline == UNSPECIFIED else qos.deadline,
               lifespan=d.lifespan if qos.lifespan == UNSPECIFIED else qos.lifespan,
               liveliness=liveliness, lease=d.lease if qos.lease == UNSPECIFIED else qos.lease)


def to_keyexpr(qos: QoS) -> str:
    """liveliness_utils.cpp ``qos_to_keyexpr``: each field empty where equal to the default.

    ``R:D:H,depth:Ds,Dns:Ls,Lns:Liv,LivS,LivNs``."""
    d = DEFAULT_QOS
    for value, table in ((qos.history, _HISTORY_VALUES), (qos.reliability, _RELIABILITY_VALUES),
                         (qos.durability, _DURABILITY_VALUES),
                         (qos.liveliness, _LIVELINESS_VALUES)):
        if value not in table:  # upstream: std::unordered_map::at throws
            raise ValueError(f"no QoS string for enum value {value}")

    def field(value: int, default: int) -> str:
        return "" if value == default else str(int(value))

    return (f"{field(qos.reliability, d.reliability)}:{field(qos.durability, d.durability)}:"
            f"{field(qos.history, d.history)},{field(qos.depth, d.depth)}:"
            f"{field(qos.deadline[0], d.deadline[0])},{field(qos.deadline[1], d.deadline[1])}:"
            f"{field(qos.lifespan[0], d.lifespan[0])},{field(qos.lifespan[1], d.lifespan[1])}:"
            f"{field(qos.liveliness, d.liveliness)},{field(qos.lease[0], d.lease[0])},"
            f"{field(qos.lease[1], d.lease[1])}")


def str_to_size_t(text: str, default: int) -> int | None:
    """liveliness_utils.cpp ``str_to_size_t``: empty -> default; a leading '-' rejected; then
    ``strtoull`` base 10 (leading white space and a sign accepted), no junk after the digits,
    no overflow. None where upstream returns std::nullopt."""
    if text == "":
        return default
    if text[0] == "-":
        return None
    i = 0
    while i < len(text) and text[i] in " \t\n\v\f\r":
        i += 1
    negative = False
    if i < len(text) and text[i] in "+-":
        negative = text[i] == "-"
        i += 1
    j = i
    while j < len(text) and text[j] in "0123456789":
        j += 1
    if j == i or j != len(text):
        return None
    value = int(text[i:j])
    if value > U64_MAX:
        return None
    return (-value) % 2**64 if negative else value


def from_keyexpr(text: str) -> QoS | None:
    """liveliness_utils.cpp ``keyexpr_to_qos``; None where upstream returns std::nullopt.

    Parts beyond the sixth ``:`` field, or beyond the expected ``,`` sub-fields, are ignored."""
    d = DEFAULT_QOS
    parts = text.split(":")
    if len(parts) < 6:
        return None
    history_parts = parts[2].split(",")
    deadline_parts = parts[3].split(",")
    lifespan_parts = parts[4].split(",")
    liveliness_parts = parts[5].split(",")
    if (len(history_parts) < 2 or len(deadline_parts) < 2 or len(lifespan_parts) < 2
            or len(liveliness_parts) < 3):
        return None

    def enum(value: str, default: int, table: set[int]) -> int | None:
        if value == "":
            return default
        # The tables are keyed by std::to_string(enum): only the canonical decimal text matches.
        return int(value) if value in {str(v) for v in table} else None

    history = enum(history_parts[0], d.history, _HISTORY_VALUES)
    reliability = enum(parts[0], d.reliability, _RELIABILITY_VALUES)
    durability = enum(parts[1], d.durability, _DURABILITY_VALUES)
    liveliness = enum(liveliness_parts[0], d.liveliness, _LIVELINESS_VALUES)
    numbers = [str_to_size_t(history_parts[1], d.depth),
               str_to_size_t(deadline_parts[0], d.deadline[0]),
               str_to_size_t(deadline_parts[1], d.deadline[1]),
               str_to_size_t(lifespan_parts[0], d.lifespan[0]),
               str_to_size_t(lifespan_parts[1], d.lifespan[1]),
               str_to_size_t(liveliness_parts[1], d.lease[0]),
               str_to_size_t(liveliness_parts[2], d.lease[1])]
    if None in (history, reliability, durability, liveliness) or None in numbers:
        return None
    depth, dl_s, dl_ns, ls_s, ls_ns, lv_s, lv_ns = numbers
    return QoS(history=history, depth=depth, reliability=reliability, durability=durability,
               deadline=(dl_s, dl_ns), lifespan=(ls_s, ls_ns), liveliness=liveliness,
               lease=(lv_s, lv_ns))


def compatible(pub: QoS, sub: QoS) -> bool:
    """Whether ``rmw_qos_profile_check_compatible`` would say anything but ERROR.

    Used by graph_cache.cpp ``publisher_count_matched_subscriptions``. That function lives in
    rmw (``qos_profiles.c``), outside the sources this model is written from: the model checks
    its documented error cases (reliability, durability, deadline, liveliness kind and lease)."""
    if pub.reliability == Reliability.BEST_EFFORT and sub.reliability == Reliability.RELIABLE:
        return False
    if pub.durability == Durability.VOLATILE and sub.durability == Durability.TRANSIENT_LOCAL:
        return False
    if pub.deadline > sub.deadline:
        return False
    if pub.liveliness == Liveliness.AUTOMATIC and sub.liveliness == Liveliness.MANUAL_BY_TOPIC:
        return False
    return pub.lease <= sub.lease
