"""The whole Zenoh wire layout of buffer_pubsub, in one place (after ROS 2's rmw_zenoh).

Everything another process must agree on lives here, so a correction is made once:

Data keys
    ``<domain>/<topic>/<dds type name>/<RIHS01 type hash>`` (topic without leading/trailing ``/``),
    plus, for buffer-aware topics, ``<data key>/_buf_cpu`` (one CPU stream shared by every
    subscription that accepts only CPU) and ``<data key>/_buf/<32 hex gid>`` (one stream per
    subscription that accepts some backend, with a payload serialized for that subscription: backend
    descriptors where the publisher's backend agreed to serve it, CPU bytes otherwise). A
    subscription listens on exactly one of the two (:func:`accepts_backends`).

Attachment (33 bytes, on every sample)
    int64 sequence number (LE, from 1), int64 source timestamp (ns since the epoch, LE),
    ``0x10``, 16-byte publisher gid.

Liveliness tokens
    node: ``@ros2_lv/<domain>/<zid>/<nid>/<nid>/NN/<enclave>/<namespace>/<node>``;
    endpoint: ``@ros2_lv/<domain>/<zid>/<nid>/<eid>/<MP|MS>/<enclave>/<namespace>/<node>/<topic>/
    <type>/<hash>/<qos>[/<extra>]``; inside a segment ``/`` becomes ``%`` and an empty value is
    ``%``. The endpoint gid is XXH3-128 (seed 0) of the key's first 13 segments (the extra segment
    left out), low 64 bits then high 64 bits, little endian: stock rmw_zenoh reads only the first
    13 segments of a token and derives the gid from them, so it computes the very gid our
    attachments carry.

Extra segment (our extension; its presence marks a *buffer-aware* endpoint)
    ``wb1;host=<h>;pid=<n>;uid=<n>;backends=<name>=<meta>,<name>=<meta>`` where every
    ``<h>``, ``<name>`` and ``<meta>`` is percent-encoded (``urllib.parse.quote(safe="")``), so the
    segment holds no ``/``, ``*``, ``$``, ``?``, ``#``, ``;``, ``,`` or ``=`` of its own.
    Publishers carry locality only (empty ``backends``); subscriptions list every backend they
    accept with the backend's metadata (``cpu`` included, empty metadata).
    Locality (host, pid, uid) is what backends need to judge a peer (same host? same process?).

Duplicate avoidance on the base key
    Buffer-aware publishers write the base key only while a subscription without the extra
    segment is matched, and mark those samples with the encoding ``application/cdr;wb1``
    (:data:`BUFFER_AWARE_ENCODING`; no ROS 2 implementation checks the encoding). Buffer-aware
    subscriptions also listen on the base key and accept there every sample with a valid
    attachment (any publisher, any gid, as rmw_zenoh does) except those so marked or from a
    publisher discovered with the extra segment: those reach them on ``_buf_cpu`` / ``_buf/<gid>``.
    So every subscription gets each message by exactly one route.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import NamedTuple
from urllib.parse import quote, unquote

import xxhash

from rosidl_buffer.messages import get_type_hash, normalize_type_name

from .errors import WireFormatError

__all__ = [
    "ATTACHMENT_SIZE",
    "Attachment",
    "EndpointToken",
    "LIVELINESS_PREFIX",
    "Locality",
    "NodeToken",
    "accepts_backends",
    "buffer_channel_key",
    "cpu_channel_key",
    "data_key",
    "dds_type_name",
    "gid_from_key",
    "liveliness_domain_selector",
    "mangle",
    "parse_token",
    "qos_history",
    "qos_segment",
]

LIVELINESS_PREFIX = "@ros2_lv"
DEFAULT_ENCLAVE = ""
CPU_CHANNEL = "_buf_cpu"
BUFFER_CHANNEL = "_buf"
EXTRA_VERSION = "wb1"
#: Encoding schema of base-key samples written by buffer-aware publishers (see the module doc).
BUFFER_AWARE_SCHEMA = EXTRA_VERSION
#: Segments of an endpoint key that stock rmw_zenoh reads (and hashes into the gid).
STOCK_ENDPOINT_SEGMENTS = 13

PUBLISHER_KIND = "MP"
SUBSCRIPTION_KIND = "MS"
NODE_KIND = "NN"

_ATTACHMENT = struct.Struct("<qqB16s")
ATTACHMENT_SIZE = _ATTACHMENT.size  # 33
_GID_LENGTH_PREFIX = 0x10


# --------------------------------------------------------------------------- names
def mangle(value: str) -> str:
    """One liveliness key segment: ``/`` -> ``%``, empty -> ``%``."""
    return value.replace("/", "%") if value else "%"


def demangle(segment: str) -> str:
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


def fully_qualified_topic(topic: str, namespace: str = "") -> str:
    """Resolve ``topic`` against ``namespace`` like rclpy: ``chatter`` in ``/ns`` -> ``/ns/chatter``."""
    topic = topic.strip()
    if not topic or topic.strip("/") == "":
        raise WireFormatError(f"invalid topic name {topic!r}")
    for bad in "*$?#":
        if bad in topic or bad in namespace:
            raise WireFormatError(f"topic or namespace contains {bad!r}: {namespace!r} {topic!r}")
    if not topic.startswith("/"):
        topic = "/".join(p for p in (namespace.strip("/"), topic) if p)
    return "/" + topic.strip("/")


def data_key(domain_id: int, topic: str, type_name: str) -> str:
    """The base data key of a fully qualified ``topic`` of ``type_name``."""
    return f"{domain_id}/{topic.strip('/')}/{dds_type_name(type_name)}/{get_type_hash(type_name)}"


def cpu_channel_key(base_key: str) -> str:
    return f"{base_key}/{CPU_CHANNEL}"


def buffer_channel_key(base_key: str, subscriber_gid: bytes) -> str:
    return f"{base_key}/{BUFFER_CHANNEL}/{subscriber_gid.hex()}"


def buffer_channel_wildcard(base_key: str) -> str:
    return f"{base_key}/{BUFFER_CHANNEL}/*"


def accepts_backends(backends: dict[str, str]) -> bool:
    """Does a subscription advertising ``backends`` take its own ``_buf/<gid>`` channel?

    Yes when it accepts any backend besides CPU; subscriptions that accept only CPU share
    ``_buf_cpu``. Both sides decide from the advertisement alone, so a subscription listens on
    exactly one of the two and never gets a message twice.
    """
    return any(name != "cpu" for name in backends)


KEEP_LAST = "keep_last"
KEEP_ALL = "keep_all"
_HISTORY_ENUM = {KEEP_LAST: "", KEEP_ALL: "2"}  # rmw enum numbers; keep-last is the default


def qos_segment(depth: int, history: str = KEEP_LAST) -> str:
    """rmw_zenoh's QoS segment for reliable, volatile, ``history`` of ``depth`` (42 default)."""
    return f"::{_HISTORY_ENUM[history]},{'' if depth == 42 else depth}:,:,:,,"


def _history_fields(segment: str) -> list[str]:
    """The history part of a QoS segment (``::<history>,<depth>:...``), split at its comma."""
    parts = segment.split(":")
    return parts[2].split(",") if len(parts) > 2 else []


def qos_depth(segment: str) -> int:
    """The keep-last depth of a QoS segment (42 where it is left out); 0 for keep-all or a
    segment that names none."""
    fields = _history_fields(segment)
    if fields[:1] == ["2"] or len(fields) < 2:  # keep-all, or no depth given
        return 0
    if fields[1] == "":
        return 42
    return int(fields[1]) if fields[1].isdecimal() and fields[1].isascii() else 0


def qos_history(segment: str) -> str:
    """The history policy of a QoS segment (keep-last unless it names keep-all, 2)."""
    return KEEP_ALL if _history_fields(segment)[:1] == ["2"] else KEEP_LAST


def liveliness_domain_selector(domain_id: int) -> str:
    return f"{LIVELINESS_PREFIX}/{domain_id}/**"


def gid_from_key(key: str) -> bytes:
    """Endpoint gid: XXH3-128 of the liveliness key's first 13 segments (what stock rmw_zenoh
    hashes), low 64 bits then high, little endian."""
    stock = "/".join(key.split("/", STOCK_ENDPOINT_SEGMENTS)[:STOCK_ENDPOINT_SEGMENTS])
    return xxhash.xxh3_128_intdigest(stock.encode("utf-8")).to_bytes(16, "little")


# --------------------------------------------------------------------------- attachment
class Attachment(NamedTuple):
    """The 33-byte attachment of every sample (a NamedTuple: built once per message on the hot
    path, several times cheaper than a frozen dataclass)."""

    sequence_number: int
    source_timestamp_ns: int
    publisher_gid: bytes

    def encode(self) -> bytes:
        return _ATTACHMENT.pack(
            self.sequence_number, self.source_timestamp_ns, _GID_LENGTH_PREFIX, self.publisher_gid
        )

    @classmethod
    def decode(cls, data: bytes | None) -> Attachment:
        if data is None or len(data) != ATTACHMENT_SIZE:
            raise WireFormatError(
                f"attachment must be {ATTACHMENT_SIZE} bytes, got {None if data is None else len(data)}"
            )
        sequence, stamp, prefix, gid = _ATTACHMENT.unpack(data)
        if prefix != _GID_LENGTH_PREFIX:
            raise WireFormatError(f"attachment gid length prefix is {prefix:#x}, not 0x10")
        return cls(sequence, stamp, gid)


# --------------------------------------------------------------------------- liveliness tokens
@dataclass(frozen=True)
class Locality:
    host_id: str = ""
    process_id: int = 0
    user_id: int = -1


def encode_extra(locality: Locality, backends: dict[str, str]) -> str:
    listed = ",".join(f"{quote(name, safe='')}={quote(meta, safe='')}"
                      for name, meta in backends.items())
    return (f"{EXTRA_VERSION};host={quote(locality.host_id, safe='')};pid={locality.process_id};"
            f"uid={locality.user_id};backends={listed}")


def decode_extra(segment: str) -> tuple[Locality, dict[str, str]]:
    parts = segment.split(";")
    if parts[0] != EXTRA_VERSION:
        raise WireFormatError(f"unknown extra segment version in {segment!r}")
    values: dict[str, str] = {}
    for part in parts[1:]:
        key, sep, value = part.partition("=")
        if not sep:
            raise WireFormatError(f"malformed extra segment field {part!r}")
        values[key] = value
    try:
        locality = Locality(unquote(values.get("host", "")), int(values.get("pid", "0")),
                            int(values.get("uid", "-1")))
    except ValueError as exc:
        raise WireFormatError(f"malformed locality in {segment!r}: {exc}") from None
    backends: dict[str, str] = {}
    for item in filter(None, values.get("backends", "").split(",")):
        name, _, meta = item.partition("=")
        backends[unquote(name)] = unquote(meta)
    return locality, backends


@dataclass(frozen=True)
class NodeToken:
    domain_id: int
    zid: str
    node_id: int
    namespace: str
    name: str
    enclave: str = DEFAULT_ENCLAVE

    def key(self) -> str:
        return "/".join([
            LIVELINESS_PREFIX, str(self.domain_id), self.zid, str(self.node_id), str(self.node_id),
            NODE_KIND, mangle(self.enclave), mangle(self.namespace), self.name,
        ])


@dataclass(frozen=True)
class EndpointToken:
    """A publisher (``MP``) or subscription (``MS``) as advertised through liveliness.

    ``buffer_aware`` endpoints carry the extra segment (locality and accepted backends).
    """

    domain_id: int
    zid: str
    node_id: int
    entity_id: int
    kind: str
    namespace: str
    node_name: str
    topic: str  # fully qualified, e.g. "/robot1/chatter"
    type_name: str  # ROS form, pkg/msg/Name
    type_hash: str
    qos: str
    buffer_aware: bool = False
    locality: Locality = field(default_factory=Locality)
    backends: dict[str, str] = field(default_factory=dict, hash=False, compare=False)
    enclave: str = DEFAULT_ENCLAVE

    def key(self) -> str:
        segments = [
            LIVELINESS_PREFIX, str(self.domain_id), self.zid, str(self.node_id),
            str(self.entity_id), self.kind, mangle(self.enclave), mangle(self.namespace),
            self.node_name, mangle(self.topic), dds_type_name(self.type_name), self.type_hash,
            self.qos,
        ]
        if self.buffer_aware:
            segments.append(encode_extra(self.locality, self.backends))
        return "/".join(segments)

    @property
    def gid(self) -> bytes:
        # Cached: publish() and every received message look the gid up, and building the key
        # (percent-encoding) plus XXH3 cost tens of us each time. The token is frozen; the
        # cache lives in the instance __dict__ and takes no part in eq/hash.
        gid = self.__dict__.get("_gid")
        if gid is None:
            gid = gid_from_key(self.key())
            object.__setattr__(self, "_gid", gid)
        return gid

    @property
    def is_publisher(self) -> bool:
        return self.kind == PUBLISHER_KIND


def parse_token(key: str) -> NodeToken | EndpointToken | None:
    """Parse a liveliness key; None for kinds we do not route (services, clients, unknown)."""
    parts = key.split("/")
    if len(parts) < 9 or parts[0] != LIVELINESS_PREFIX:
        raise WireFormatError(f"not a ROS 2 liveliness key: {key!r}")
    try:
        domain_id, node_id, entity_id = int(parts[1]), int(parts[3]), int(parts[4])
    except ValueError:
        raise WireFormatError(f"non-numeric ids in liveliness key {key!r}") from None
    kind = parts[5]
    if kind == NODE_KIND:
        return NodeToken(domain_id, parts[2], node_id, demangle(parts[7]), parts[8],
                         demangle(parts[6]))
    if kind not in (PUBLISHER_KIND, SUBSCRIPTION_KIND):
        return None
    if len(parts) < STOCK_ENDPOINT_SEGMENTS:
        raise WireFormatError(f"endpoint liveliness key has {len(parts)} segments: {key!r}")
    # As stock rmw_zenoh: the first 13 segments make the endpoint; ours adds a 14th (wb1;...),
    # segments other implementations may add are ignored.
    locality, backends = Locality(), {}
    aware = len(parts) > STOCK_ENDPOINT_SEGMENTS and parts[13].startswith(EXTRA_VERSION + ";")
    if aware:
        locality, backends = decode_extra(parts[13])
    return EndpointToken(
        domain_id=domain_id, zid=parts[2], node_id=node_id, entity_id=entity_id, kind=kind,
        namespace=demangle(parts[7]), node_name=parts[8], topic=demangle(parts[9]),
        type_name=ros_type_name(parts[10]), type_hash=parts[11], qos=parts[12],
        buffer_aware=aware, locality=locality, backends=backends, enclave=demangle(parts[6]),
    )
