"""The whole Zenoh wire layout of buffer_pubsub: ROS 2's rmw_zenoh 0.10.5 / 0.12.0, exactly.

Everything another process must agree on lives here, so a correction is made once. The upstream
source each rule follows is named beside it (``rmw_zenoh_cpp/src/detail/``).

Data keys (``liveliness_utils.cpp`` TopicInfo, ``buffer_endpoint_helpers.hpp``)
    ``<domain>/<topic>/<dds type name>/<RIHS01 type hash>`` (topic without leading/trailing
    ``/``). A *buffer-aware* endpoint (volatile, of a type with a top-level unbounded ``uint8[]``)
    also uses ``<data key>/_buf_cpu`` (one CPU stream shared by every CPU-only subscription) and
    ``<data key>/_buf/<32 hex subscription gid>`` (one stream per other subscription, serialized
    for it alone: backend descriptors where a backend serves it, CPU bytes otherwise).

Attachment (``attachment_helpers.cpp``; 33 bytes on every sample)
    int64 sequence number (LE, from 1), int64 source timestamp (ns since the epoch, LE), ``0x10``,
    16-byte publisher gid.

Liveliness tokens (``liveliness_utils.cpp`` Entity)
    node: ``@ros2_lv/<domain>/<zid>/<nid>/<nid>/NN/<enclave>/<namespace>/<node>``;
    endpoint: ``@ros2_lv/<domain>/<zid>/<nid>/<id>/<MP|MS>/<enclave>/<namespace>/<node>/<topic>/
    <type>/<hash>/<qos>[/backends:<name>:<meta>;...]``; inside a segment ``/`` becomes ``%`` (an
    empty namespace or enclave is ``%``). The 14th segment is present when the endpoint has a
    non-empty backend map: names sorted by byte order, name and metadata each escaped ``%`` ->
    ``%25``, ``;`` -> ``%3B``, ``:`` -> ``%3A``, ``/`` -> ``%2F``.

    The endpoint gid is XXH3-128 (seed 0) of the key *rebuilt canonically* from its parsed parts
    (QoS re-encoded with defaults left out, backends re-sorted and re-escaped, any segment after
    the 14th, or a 14th that does not start with ``backends:``, dropped), low 64 bits then high,
    little endian: the gid every rmw_zenoh peer computes for it.

Our extension: a locality segment
    Our endpoints append one segment after the ones above, ``wbloc:<host>:<pid>:<uid>`` (the host
    id escaped as a backend field is, plus any byte Zenoh keys forbid): same-host routes need to
    know where an endpoint lives. rmw_zenoh drops it when it rebuilds the key, so it changes
    neither the gid nor the route any ROS 2 peer computes; it also marks an endpoint as ours.
"""

from __future__ import annotations

import functools
import logging
import re
from dataclasses import dataclass, field
from typing import NamedTuple

import xxhash

from rosidl_buffer.messages import get_type_hash, normalize_type_name

from . import _streams
from .errors import WireFormatError

_log = logging.getLogger(__name__)

__all__ = [
    "ATTACHMENT_SIZE",
    "Attachment",
    "EndpointToken",
    "BEST_EFFORT",
    "KEEP_ALL",
    "KEEP_LAST",
    "LIVELINESS_PREFIX",
    "Locality",
    "NodeToken",
    "QoSProfile",
    "SubscriptionChannel",
    "buffer_channel_key",
    "cpu_channel_key",
    "data_key",
    "dds_type_name",
    "gid_from_key",
    "liveliness_domain_selector",
    "mangle",
    "new_attachment",
    "pack_attachment",
    "parse_attachment",
    "parse_token",
    "split_frame",
    "subscription_channel",
]

LIVELINESS_PREFIX = "@ros2_lv"
DEFAULT_ENCLAVE = ""
CPU_CHANNEL = "_buf_cpu"
BUFFER_CHANNEL = "_buf"
BACKENDS_PREFIX = "backends:"
LOCALITY_PREFIX = "wbloc:"
#: Segments of an endpoint key up to the QoS (all of them mandatory).
MANDATORY_ENDPOINT_SEGMENTS = 13
#: Segments up to the node name (what a node token has).
NODE_SEGMENTS = 9

PUBLISHER_KIND = "MP"
SUBSCRIPTION_KIND = "MS"
NODE_KIND = "NN"
SERVICE_KIND = "SS"
CLIENT_KIND = "SC"
_ENTITY_KINDS = frozenset({NODE_KIND, PUBLISHER_KIND, SUBSCRIPTION_KIND, SERVICE_KIND,
                           CLIENT_KIND})

ATTACHMENT_SIZE = _streams.ATTACHMENT_SIZE  # 33: int64 sequence, int64 stamp, 0x10, gid


# --------------------------------------------------------------------------- names
def mangle(value: str) -> str:
    """One liveliness key segment: ``/`` -> ``%``; an empty value (which rcl spells ``/``) is
    ``%``."""
    return value.replace("/", "%") if value else "%"


def demangle(segment: str) -> str:
    """Inverse of :func:`mangle` for a namespace or enclave (``%`` is the empty one)."""
    return "" if segment == "%" else segment.replace("%", "/")


def dds_type_name(type_name: str) -> str:
    """``pkg/msg/Name`` -> ``pkg::msg::dds_::Name_``."""
    package, interface, name = normalize_type_name(type_name).split("/")
    return f"{package}::{interface}::dds_::{name}_"


def ros_type_name(dds_name: str) -> str:
    """Inverse of :func:`dds_type_name`; each part must be a name (``pkg::msg::dds_::Name_``)."""
    parts = dds_name.split("::")
    if (len(parts) != 4 or parts[2] != "dds_" or not parts[3].endswith("_")
            or not all(part.isidentifier() for part in (parts[0], parts[1], parts[3][:-1]))):
        raise WireFormatError(f"not a DDS type name: {dds_name!r}")
    return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"


def data_key(domain_id: int, topic: str, type_name: str) -> str:
    """The base data key of a fully qualified ``topic`` of ``type_name``."""
    return f"{domain_id}/{topic.strip('/')}/{dds_type_name(type_name)}/{get_type_hash(type_name)}"


def cpu_channel_key(base_key: str) -> str:
    """The shared CPU stream of a buffer-aware topic (``make_cpu_group_key``)."""
    return f"{base_key}/{CPU_CHANNEL}"


def buffer_channel_key(base_key: str, subscriber_gid: bytes) -> str:
    """The stream of one subscription (``make_accelerated_key``: gid in lower-case hex)."""
    return f"{base_key}/{BUFFER_CHANNEL}/{subscriber_gid.hex()}"


def liveliness_domain_selector(domain_id: int) -> str:
    return f"{LIVELINESS_PREFIX}/{domain_id}/**"


#: Our own admin space (a verbatim chunk: no ROS 2 key or wildcard of rmw_zenoh matches it).
ADMIN_PREFIX = "@warp_buffer"


def routes_key(domain_id: int, zid: str, node_id: int) -> str:
    """Where a node of ours answers what route each of its publishers takes (JSON); nodes
    that share a session answer on keys of their own."""
    return f"{ADMIN_PREFIX}/{domain_id}/{zid}/{node_id}/routes"


def routes_selector(domain_id: int) -> str:
    """Every node's routes key (``**``: also the ``<zid>/routes`` keys of older versions)."""
    return f"{ADMIN_PREFIX}/{domain_id}/**/routes"


def gid_from_key(canonical_key: str) -> bytes:
    """Endpoint gid: XXH3-128 of a canonical liveliness key, low 64 bits then high, LE."""
    # (surrogateescape: a backend field may unescape to bytes that are not UTF-8)
    data = canonical_key.encode("utf-8", "surrogateescape")
    return xxhash.xxh3_128_intdigest(data).to_bytes(16, "little")


# --------------------------------------------------------------------------- escaping
_BACKEND_ESCAPES = {"%": "%25", ";": "%3B", ":": "%3A", "/": "%2F"}


def escape_backend_field(text: str) -> str:
    """``escape_backend_field``: only ``% ; : /`` are escaped, as upper-case ``%XX``."""
    return "".join(_BACKEND_ESCAPES.get(c, c) for c in text)


def _hex_value(c: str) -> int:
    return int(c, 16) if c in "0123456789abcdefABCDEF" else -1


def unescape_backend_field(text: str) -> str:
    """``unescape_backend_field``: every ``%XX`` with two hex digits (either case) is one byte;
    a ``%`` not followed by two hex digits stays as it is. Bytes are decoded as UTF-8."""
    out = bytearray()
    raw = text.encode("utf-8")
    i = 0
    while i < len(raw):
        byte = raw[i]
        if byte == 0x25 and i + 2 < len(raw):  # upstream tests i + 2 < size (see the test)
            hi, lo = _hex_value(chr(raw[i + 1])), _hex_value(chr(raw[i + 2]))
            if hi >= 0 and lo >= 0:
                out.append(hi << 4 | lo)
                i += 3
                continue
        out.append(byte)
        i += 1
    return out.decode("utf-8", errors="surrogateescape")


#: Besides the backend-field escapes, what a Zenoh key chunk cannot hold (the locality segment
#: carries a host id we do not control).
_KEY_UNSAFE = frozenset("*$?#") | frozenset(chr(n) for n in range(0x21))


def _escape_key_field(text: str) -> str:
    """:func:`escape_backend_field`, plus ``%XX`` for what a Zenoh key chunk cannot hold (a
    rmw_zenoh reader unescapes those too, so it rebuilds the same canonical key)."""
    return "".join(_BACKEND_ESCAPES.get(c) or (f"%{ord(c):02X}" if c in _KEY_UNSAFE else c)
                   for c in text)


# --------------------------------------------------------------------------- QoS
# rmw enum numbers (rmw/types.h)
HISTORY_SYSTEM_DEFAULT, HISTORY_KEEP_LAST, HISTORY_KEEP_ALL, HISTORY_UNKNOWN = 0, 1, 2, 3
RELIABILITY_RELIABLE, RELIABILITY_BEST_EFFORT = 1, 2
DURABILITY_TRANSIENT_LOCAL, DURABILITY_VOLATILE = 1, 2
LIVELINESS_AUTOMATIC = 1
_HISTORY_VALUES = frozenset({0, 1, 2, 3})
_RELIABILITY_VALUES = frozenset({0, 1, 2, 3, 4})
_DURABILITY_VALUES = frozenset({0, 1, 2, 3, 4})
_LIVELINESS_VALUES = frozenset({0, 1, 3, 4, 5})
#: RMW_DURATION_INFINITE, as (sec, nsec)
INFINITE = (9223372036, 854775807)
DEFAULT_DEPTH = 42  # rmw_zenoh's default history depth (qos.cpp)
_UINT64_MAX = 2**64 - 1

KEEP_LAST = "keep_last"
KEEP_ALL = "keep_all"
VOLATILE = "volatile"
TRANSIENT_LOCAL = "transient_local"
RELIABLE = "reliable"
BEST_EFFORT = "best_effort"


@dataclass(frozen=True)
class QoSProfile:
    """An endpoint's QoS as its token carries it (rmw enum numbers; durations ``(sec, nsec)``).

    The defaults are rmw_zenoh's (``qos.cpp``): reliable, volatile, keep-last 42, automatic
    liveliness, infinite deadline, lifespan and lease.
    """

    reliability: int = RELIABILITY_RELIABLE
    durability: int = DURABILITY_VOLATILE
    history: int = HISTORY_KEEP_LAST
    depth: int = DEFAULT_DEPTH
    deadline: tuple[int, int] = INFINITE
    lifespan: tuple[int, int] = INFINITE
    liveliness: int = LIVELINESS_AUTOMATIC
    liveliness_lease: tuple[int, int] = INFINITE

    @classmethod
    def of(cls, depth: int, history: str = KEEP_LAST, durability: str = VOLATILE,
           reliability: str = RELIABLE) -> QoSProfile:
        """What our endpoints offer: ``reliability``, ``durability``, ``history`` of ``depth``."""
        return cls(history=HISTORY_KEEP_ALL if history == KEEP_ALL else HISTORY_KEEP_LAST,
                   depth=depth, durability=DURABILITY_TRANSIENT_LOCAL
                   if durability == TRANSIENT_LOCAL else DURABILITY_VOLATILE,
                   reliability=RELIABILITY_BEST_EFFORT if reliability == BEST_EFFORT
                   else RELIABILITY_RELIABLE)

    @property
    def best_effort(self) -> bool:
        return self.reliability == RELIABILITY_BEST_EFFORT

    @property
    def keep_all(self) -> bool:
        return self.history == HISTORY_KEEP_ALL

    @property
    def history_name(self) -> str:
        return KEEP_ALL if self.keep_all else KEEP_LAST

    @property
    def transient_local(self) -> bool:
        return self.durability == DURABILITY_TRANSIENT_LOCAL

    def to_keyexpr(self) -> str:
        """``qos_to_keyexpr``: ``R:D:H,depth:Ds,Dns:Ls,Lns:Liv,LivS,LivNs``, a field left empty
        where it equals the default."""
        d = QoSProfile()

        def part(value: object, default: object) -> str:
            return "" if value == default else str(value)

        return ":".join([
            part(self.reliability, d.reliability),
            part(self.durability, d.durability),
            f"{part(self.history, d.history)},{part(self.depth, d.depth)}",
            f"{part(self.deadline[0], d.deadline[0])},{part(self.deadline[1], d.deadline[1])}",
            f"{part(self.lifespan[0], d.lifespan[0])},{part(self.lifespan[1], d.lifespan[1])}",
            f"{part(self.liveliness, d.liveliness)},{part(self.liveliness_lease[0], d.liveliness_lease[0])},"
            f"{part(self.liveliness_lease[1], d.liveliness_lease[1])}",
        ])

    @classmethod
    def from_keyexpr(cls, text: str) -> QoSProfile:
        """``keyexpr_to_qos``: empty fields take the defaults; WireFormatError where rmw_zenoh
        rejects the segment (too few parts, unknown enum value, a number that is not an unsigned
        decimal of its width)."""
        d = cls()
        parts = text.split(":")
        if len(parts) < 6:
            raise WireFormatError(f"QoS segment {text!r} has {len(parts)} parts, not 6")
        history, deadline, lifespan, liveliness = (p.split(",") for p in parts[2:6])
        if len(history) < 2 or len(deadline) < 2 or len(lifespan) < 2 or len(liveliness) < 3:
            raise WireFormatError(f"malformed QoS segment {text!r}")

        def enum(value: str, default: int, allowed: frozenset[int]) -> int:
            # upstream looks the text up in a map of std::to_string(value): "01" is unknown
            if value == "":
                return default
            if value not in {str(v) for v in allowed}:
                raise WireFormatError(f"QoS segment {text!r}: unknown policy value {value!r}")
            return int(value)

        def number(value: str, default: int, limit: int) -> int:
            # str_to_size_t: a leading '-' refused, then strtoull (leading C whitespace and a
            # sign taken, a negative wrapping modulo 2**64), the whole text a number that fits
            if value == "":
                return default
            body = value.lstrip(" \t\n\v\f\r") if value[0] != "-" else ""
            negative = body.startswith("-")
            if body.startswith(("+", "-")):
                body = body[1:]
            digits = int(body) if body.isascii() and body.isdecimal() else None
            parsed = (None if digits is None or digits > _UINT64_MAX else
                      -digits % (_UINT64_MAX + 1) if negative else digits)
            if parsed is None or parsed > limit:
                raise WireFormatError(f"QoS segment {text!r}: {value!r} is not a valid number")
            return parsed

        return cls(
            reliability=enum(parts[0], d.reliability, _RELIABILITY_VALUES),
            durability=enum(parts[1], d.durability, _DURABILITY_VALUES),
            history=enum(history[0], d.history, _HISTORY_VALUES),
            depth=number(history[1], d.depth, _UINT64_MAX),
            deadline=(number(deadline[0], d.deadline[0], _UINT64_MAX),
                      number(deadline[1], d.deadline[1], _UINT64_MAX)),
            lifespan=(number(lifespan[0], d.lifespan[0], _UINT64_MAX),
                      number(lifespan[1], d.lifespan[1], _UINT64_MAX)),
            liveliness=enum(liveliness[0], d.liveliness, _LIVELINESS_VALUES),
            liveliness_lease=(number(liveliness[1], d.liveliness_lease[0], _UINT64_MAX),
                              number(liveliness[2], d.liveliness_lease[1], _UINT64_MAX)),
        )


# --------------------------------------------------------------------------- attachment
class Attachment(NamedTuple):
    """The 33-byte attachment of every sample (a NamedTuple: built once per message on the hot
    path, several times cheaper than a frozen dataclass)."""

    sequence_number: int
    source_timestamp_ns: int
    publisher_gid: bytes

    def encode(self) -> bytes:
        return pack_attachment(self.sequence_number, self.source_timestamp_ns,
                               self.publisher_gid)

    @classmethod
    def decode(cls, data: bytes | None) -> Attachment:
        """The attachment at the head of ``data`` (WireFormatError: shorter than 33 bytes, or a
        malformed one); bytes past it are ignored, as rmw_zenoh ignores them."""
        return parse_attachment(data)


#: ``new_attachment((sequence, stamp, gid))``: an Attachment built in C, without the NamedTuple's
#: generated ``__new__`` (a Python frame on every publish and arrival).
new_attachment = functools.partial(tuple.__new__, Attachment)
_streams.configure(new_attachment, WireFormatError)
#: ``parse_attachment(data)``: :meth:`Attachment.decode` in one C call (what arrivals use).
parse_attachment = _streams.parse_attachment
#: ``pack_attachment(sequence, stamp, gid)``: :meth:`Attachment.encode` in one C call.
pack_attachment = _streams.pack_attachment
#: ``split_frame(frame)``: a lane frame's Attachment and its CDR payload (a memoryview of the
#: frame's tail), in one C call; WireFormatError as :meth:`Attachment.decode`.
split_frame = _streams.split_frame


# --------------------------------------------------------------------------- backends segment
def encode_backends(backends: dict[str, str], *, declarable: bool = False) -> str:
    """The 14th segment for a non-empty backend map (``Entity`` constructor), as rmw_zenoh
    rebuilds and hashes it; ``declarable``: also escaping what a Zenoh key cannot hold (upstream
    leaves a ``*`` in metadata as it is, and then fails to declare the token)."""
    escape = _escape_key_field if declarable else escape_backend_field
    return BACKENDS_PREFIX + ";".join(
        f"{escape(name)}:{escape(backends[name])}"
        for name in sorted(backends, key=lambda n: n.encode("utf-8", "surrogateescape")))


def decode_backends(segment: str) -> dict[str, str] | None:
    """The backend map of a 14th segment as ``Entity::make`` parses it: None when the segment is
    not a backends segment or names no backend (the key is then rebuilt without it)."""
    if not segment.startswith(BACKENDS_PREFIX):
        return None
    parsed: dict[str, str] = {}
    for entry in segment[len(BACKENDS_PREFIX):].split(";"):
        if not entry:
            continue
        name, _, metadata = entry.partition(":")
        name = unescape_backend_field(name)
        if name:
            parsed[name] = unescape_backend_field(metadata)  # a repeated name: the last wins
    return parsed or None


# --------------------------------------------------------------------------- locality segment
@dataclass(frozen=True)
class Locality:
    """Where one of our endpoints lives (carried in our locality segment)."""

    host_id: str = ""
    process_id: int = 0
    user_id: int = -1



def encode_extension(locality: Locality, max_rate_hz: float = 0.0) -> str:
    """Our segment: ``wbloc:<host>:<pid>:<uid>``, plus ``:<max rate in Hz>`` for a subscription
    that asked for at most that many messages a second (see :mod:`buffer_pubsub.subscription`)."""
    text = (f"{LOCALITY_PREFIX}{_escape_key_field(locality.host_id)}:{locality.process_id}:"
            f"{locality.user_id}")
    return f"{text}:{max_rate_hz!r}" if max_rate_hz > 0 else text


_INTEGER = re.compile(r"-?[0-9]+")  # (ASCII digits: str.isdecimal takes other scripts' too)


def decode_extension(segment: str) -> tuple[Locality, float]:
    """Inverse of :func:`encode_extension`; WireFormatError for anything else."""
    fields = segment[len(LOCALITY_PREFIX):].split(":")
    if len(fields) not in (3, 4) or not all(_INTEGER.fullmatch(f) for f in fields[1:3]):
        raise WireFormatError(f"malformed locality segment {segment!r}")
    rate = 0.0
    if len(fields) == 4:
        try:
            rate = float(fields[3])
        except ValueError:
            raise WireFormatError(f"malformed rate in {segment!r}") from None
        if not 0 < rate < float("inf"):
            raise WireFormatError(f"malformed rate in {segment!r}")
    return Locality(unescape_backend_field(fields[0]), int(fields[1]), int(fields[2])), rate


# --------------------------------------------------------------------------- tokens
@dataclass(frozen=True)
class NodeToken:
    domain_id: int
    zid: str
    node_id: str
    namespace: str
    name: str
    enclave: str = DEFAULT_ENCLAVE

    def __post_init__(self) -> None:
        object.__setattr__(self, "node_id", str(self.node_id))

    def key(self) -> str:
        return "/".join([
            LIVELINESS_PREFIX, str(self.domain_id), self.zid, self.node_id, self.node_id,
            NODE_KIND, mangle(self.enclave), mangle(self.namespace), mangle(self.name),
        ])


class SubscriptionChannel:
    """Which stream a buffer-aware publisher writes a subscription on (see
    :func:`subscription_channel`)."""

    CPU = "cpu"  # the shared _buf_cpu stream: it advertises exactly one backend, cpu
    OWN = "own"  # its own _buf/<gid> stream: it advertises anything else
    BASE = "base"  # the base key only: it advertises nothing (see subscription_channel)


@dataclass(frozen=True)
class EndpointToken:
    """A publisher (``MP``) or subscription (``MS``) as advertised through liveliness; or a
    service server (``SS``) or client (``SC``), whose key has the same layout (``topic``: the
    service's name), known to the graph and never routed (this transport has no services).

    ``backends`` is the parsed 14th segment (None: the token has none); ``locality`` and
    ``max_rate_hz`` our extension segment (None: not one of ours; 0: no rate asked). ``node_id`` and ``entity_id`` keep the text of the
    token (rmw_zenoh hashes them as text).
    """

    domain_id: int
    zid: str
    node_id: str
    entity_id: str
    kind: str
    namespace: str
    node_name: str
    topic: str  # fully qualified, e.g. "/robot1/chatter"
    type_name: str  # ROS form, pkg/msg/Name
    type_hash: str
    qos: QoSProfile
    backends: dict[str, str] | None = field(default=None, hash=False, compare=False)
    locality: Locality | None = None
    enclave: str = DEFAULT_ENCLAVE
    max_rate_hz: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "node_id", str(self.node_id))
        object.__setattr__(self, "entity_id", str(self.entity_id))

    def canonical_key(self, *, declarable: bool = False) -> str:
        """The key as rmw_zenoh rebuilds it (no locality segment): what the gid hashes."""
        segments = [
            LIVELINESS_PREFIX, str(self.domain_id), self.zid, self.node_id, self.entity_id,
            self.kind, mangle(self.enclave), mangle(self.namespace), mangle(self.node_name),
            mangle(self.topic), mangle(dds_type_name(self.type_name)), mangle(self.type_hash),
            self.qos.to_keyexpr(),
        ]
        if self.backends:
            segments.append(encode_backends(self.backends, declarable=declarable))
        return "/".join(segments)

    def key(self) -> str:
        """The key this endpoint declares: the canonical key (key-unsafe bytes of backend
        metadata escaped), plus our locality segment."""
        key = self.canonical_key(declarable=True)
        if self.locality is None:
            return key
        return f"{key}/{encode_extension(self.locality, self.max_rate_hz)}"

    @property
    def gid(self) -> bytes:
        # Cached: every received message looks the gid up, and building the key plus XXH3 cost
        # tens of us. The token is frozen; the cache lives in the instance __dict__.
        gid = self.__dict__.get("_gid")
        if gid is None:
            gid = gid_from_key(self.canonical_key())
            object.__setattr__(self, "_gid", gid)
        return gid

    @property
    def is_publisher(self) -> bool:
        return self.kind == PUBLISHER_KIND

    @property
    def is_service(self) -> bool:
        """A service server or client, not a topic's endpoint."""
        return self.kind in (SERVICE_KIND, CLIENT_KIND)

    @property
    def is_ours(self) -> bool:
        """Declared by warp-buffer (it carries our locality segment)."""
        return self.locality is not None


def subscription_channel(token: EndpointToken) -> str:
    """How a buffer-aware publisher reaches subscription ``token`` (a :class:`SubscriptionChannel`).

    As ``PublisherData::on_subscriber_discovered``: exactly one advertised backend, ``cpu`` ->
    the shared CPU stream; any other map -> its own stream. A subscription that advertises
    nothing is ``BASE`` here, where rmw_zenoh gives it its own stream too: a pre-0.10.5 or
    transient-local subscription listens on the base key only, and a buffer-era one with no
    backend listens there as well, so the base key reaches it in every case (see the publisher).
    """
    backends = token.backends
    if backends is None:
        return SubscriptionChannel.BASE
    if len(backends) == 1 and "cpu" in backends:
        return SubscriptionChannel.CPU
    return SubscriptionChannel.OWN


def parse_token(key: str) -> NodeToken | EndpointToken:
    """Parse a liveliness key as ``Entity::make`` does. WireFormatError where rmw_zenoh rejects
    the token too."""
    parts = key.split("/")
    if len(parts) < NODE_SEGMENTS or parts[0] != LIVELINESS_PREFIX:
        raise WireFormatError(f"not a ROS 2 liveliness key: {key!r}")
    if not all(parts):
        raise WireFormatError(f"liveliness key with an empty segment: {key!r}")
    kind = parts[5]
    if kind not in _ENTITY_KINDS:
        raise WireFormatError(f"liveliness key of unknown entity {kind!r}: {key!r}")
    if not (parts[1].isascii() and parts[1].isdecimal()):
        raise WireFormatError(f"non-numeric domain id in liveliness key {key!r}")
    domain_id = int(parts[1])
    if kind == NODE_KIND:
        return NodeToken(domain_id, parts[2], parts[3], demangle(parts[7]),
                         parts[8].replace("%", "/"), demangle(parts[6]))
    if len(parts) < MANDATORY_ENDPOINT_SEGMENTS:
        raise WireFormatError(f"endpoint liveliness key has {len(parts)} segments: {key!r}")
    qos = QoSProfile.from_keyexpr(parts[12])
    extra = parts[MANDATORY_ENDPOINT_SEGMENTS:]
    backends = decode_backends(extra[0]) if extra else None
    # Ours comes last; rmw_zenoh reads only a 14th segment starting with "backends:", so a
    # malformed one of ours leaves the token valid: its endpoint is judged foreign (no locality).
    locality, max_rate_hz = None, 0.0
    if extra and extra[-1].startswith(LOCALITY_PREFIX):
        try:
            locality, max_rate_hz = decode_extension(extra[-1])
        except WireFormatError as exc:
            _log.debug("ignoring the locality of liveliness token %s: %s", key, exc)
    return EndpointToken(
        domain_id=domain_id, zid=parts[2], node_id=parts[3], entity_id=parts[4], kind=kind,
        namespace=demangle(parts[7]), node_name=parts[8].replace("%", "/"),
        topic=parts[9].replace("%", "/"), type_name=ros_type_name(parts[10].replace("%", "/")),
        type_hash=parts[11].replace("%", "/"), qos=qos, backends=backends, locality=locality,
        enclave=demangle(parts[6]), max_rate_hz=max_rate_hz,
    )
