"""Liveliness tokens and gids as rmw_zenoh 0.10.5 / 0.12.0 build and read them.

Models ``rmw_zenoh_cpp/src/detail/liveliness_utils.cpp``: ``TopicInfo`` (the data key),
``escape_backend_field`` / ``unescape_backend_field``, the ``Entity`` constructor (token layout,
the optional 14th ``backends:`` segment, the gid), ``Entity::make(keyexpr)`` (parsing, then the
same constructor, so the token is rebuilt canonically), ``mangle_name`` / ``demangle_name``.
``legacy=True`` models 0.10.4 and older: 13 segments at most, no backends.
"""

from __future__ import annotations

import dataclasses

import xxhash

from tests.upstream_model import qos as qos_model

ADMIN_SPACE = "@ros2_lv"
NODE, PUBLISHER, SUBSCRIPTION, SERVICE, CLIENT = "NN", "MP", "MS", "SS", "SC"
ENTITY_KINDS = (NODE, PUBLISHER, SUBSCRIPTION, SERVICE, CLIENT)
# KeyexprIndex: AdminSpace .. NodeName (9 parts) for every token, .. TopicQoS (13) for endpoints,
# Backends (14th) optional.
NODE_PARTS, ENDPOINT_PARTS, MAX_PARTS = 9, 13, 14
U64 = 2**64


def subscription_token(domain_id: int) -> str:
    """``subscription_token``: the key of the graph's liveliness subscriber."""
    return f"{ADMIN_SPACE}/{domain_id}/**"


def mangle_name(name: str) -> str:
    """``mangle_name``: '/' -> '%' (nothing else is escaped)."""
    return name.replace("/", "%")


def demangle_name(name: str) -> str:
    """``demangle_name``: '%' -> '/'."""
    return name.replace("%", "/")


def strip_slashes(name: str) -> str:
    """``strip_slashes`` (TopicInfo): drop one leading and one trailing '/'."""
    start = 1 if name[:1] == "/" else 0
    end = len(name) - 1
    if name and name[end] == "/":
        end -= 1
    return name[start:end + 1]


def escape_backend_field(text: str) -> str:
    """``escape_backend_field``: only '%', ';', ':' and '/' are escaped, upper-case hex."""
    return "".join({"%": "%25", ";": "%3B", ":": "%3A", "/": "%2F"}.get(c, c) for c in text)


def unescape_backend_field(text: str) -> str:
    """``unescape_backend_field``: any ``%XY`` with two hex digits (either case) is decoded; a
    '%' followed by anything else stays as it is. Upstream works on bytes (std::string); the
    model decodes the result as UTF-8 with surrogate escapes so that no byte is lost."""
    raw = text.encode("utf-8", "surrogateescape")
    out = bytearray()
    i = 0
    hexdigits = b"0123456789abcdefABCDEF"
    while i < len(raw):
        # upstream: input[i] == '%' && i + 2 < size, and both following characters hex digits
        if raw[i] == 0x25 and i + 2 < len(raw) and raw[i + 1] in hexdigits \
                and raw[i + 2] in hexdigits:
            out.append(int(raw[i + 1:i + 3], 16))
            i += 3
            continue
        out.append(raw[i])
        i += 1
    return out.decode("utf-8", "surrogateescape")


def backends_segment(metadata: dict[str, str]) -> str:
    """The 14th segment: names sorted by byte order, ``name:meta`` joined by ';'."""
    names = sorted(metadata, key=lambda n: n.encode("utf-8", "surrogateescape"))
    return "backends:" + ";".join(
        f"{escape_backend_field(n)}:{escape_backend_field(metadata[n])}" for n in names)


def parse_backends_segment(segment: str) -> dict[str, str] | None:
    """``Entity::make``: the 14th segment's map, None where upstream leaves it unset (not a
    ``backends:`` segment, nothing after the prefix, or no entry with a non-empty name).
    An entry without ':' is a name with empty metadata; a repeated name keeps the last value."""
    if not segment.startswith("backends:"):
        return None
    body = segment[len("backends:"):]
    parsed: dict[str, str] = {}
    for entry in body.split(";") if body else []:
        if not entry:
            continue
        name, _, metadata = entry.partition(":")
        name, metadata = unescape_backend_field(name), unescape_backend_field(metadata)
        if name:
            parsed[name] = metadata
    return parsed or None


def gid_of(keyexpr: str) -> bytes:
    """The 16-byte gid: XXH3-128 (seed 0) of the token text, low 64 bits then high 64 bits, each
    little endian (``simplified_XXH3_128bits`` + the two memcpy of the Entity constructor)."""
    value = xxhash.xxh3_128_intdigest(keyexpr.encode("utf-8", "surrogateescape"))
    return (value % U64).to_bytes(8, "little") + (value >> 64).to_bytes(8, "little")


@dataclasses.dataclass(frozen=True)
class NodeInfo:
    domain_id: int
    namespace: str
    name: str
    enclave: str


@dataclasses.dataclass(frozen=True)
class TopicInfo:
    domain_id: int
    name: str           # fully qualified ROS topic name, e.g. /camera/image
    type: str           # DDS-style name, e.g. sensor_msgs::msg::dds_::Image_
    type_hash: str      # RIHS01_<64 hex>
    qos: qos_model.QoS
    backend_metadata: dict[str, str] | None = None

    @property
    def topic_keyexpr(self) -> str:
        """TopicInfo::TopicInfo: ``<domain>/<topic without outer slashes>/<type>/<hash>``."""
        return f"{self.domain_id}/{strip_slashes(self.name)}/{self.type}/{self.type_hash}"


@dataclasses.dataclass(frozen=True)
class Entity:
    """A node or endpoint as the Entity constructor sees it; ``keyexpr`` and ``gid`` derive
    from the fields exactly as upstream computes them."""

    zid: str
    nid: str
    id: str
    kind: str
    node: NodeInfo
    topic: TopicInfo | None = None
    legacy: bool = False

    @property
    def keyexpr(self) -> str:
        """The Entity constructor's token text."""
        parts = [""] * (ENDPOINT_PARTS if self.legacy else MAX_PARTS)
        parts[0:9] = [ADMIN_SPACE, str(self.node.domain_id), self.zid, self.nid, self.id,
                      self.kind, mangle_name(self.node.enclave),
                      mangle_name(self.node.namespace), mangle_name(self.node.name)]
        if self.topic is not None:
            parts[9:13] = [mangle_name(self.topic.name), mangle_name(self.topic.type),
                           mangle_name(self.topic.type_hash), qos_model.to_keyexpr(self.topic.qos)]
            if not self.legacy and self.topic.backend_metadata:
                parts[13] = backends_segment(self.topic.backend_metadata)
        # Upstream's join: append each non-empty part, stop at the first empty NEXT part.
        out = ""
        for i, part in enumerate(parts):
            out += part
            if i == len(parts) - 1 or not parts[i + 1]:
                break
            out += "/"
        return out

    @property
    def gid(self) -> bytes:
        return gid_of(self.keyexpr)

    @property
    def gid_hex(self) -> str:
        """``gid_to_hex``: 32 lower-case hex digits, byte order as stored."""
        return self.gid.hex()


def _stoul(text: str) -> int | None:
    """``std::stoul`` base 10: leading white space, a sign, digits, junk after them ignored;
    None where it throws (no digits, out of range). A '-' wraps as strtoul does."""
    i = 0
    while i < len(text) and text[i] in " \t\n\v\f\r":
        i += 1
    negative = i < len(text) and text[i] == "-"
    if i < len(text) and text[i] in "+-":
        i += 1
    j = i
    while j < len(text) and text[j] in "0123456789":
        j += 1
    if j == i or int(text[i:j]) >= U64:
        return None
    return (-int(text[i:j])) % U64 if negative else int(text[i:j])


def parse(keyexpr: str, *, legacy: bool = False) -> Entity | None:
    """``Entity::make(keyexpr)``: the entity a reader builds from a token, or None where
    upstream rejects it (logs an error and returns nullptr). A non-numeric domain makes
    upstream's ``std::stoul`` throw out of ``Entity::make``: the model returns None there too.

    The returned entity's ``keyexpr`` is the canonical rebuild that upstream hashes."""
    parts = keyexpr.split("/")
    if len(parts) < NODE_PARTS or any(not p for p in parts) or parts[0] != ADMIN_SPACE:
        return None
    kind = parts[5]
    if kind not in ENTITY_KINDS:
        return None
    domain_id = _stoul(parts[1])
    if domain_id is None:
        return None
    node = NodeInfo(domain_id=domain_id, namespace=demangle_name(parts[7]),
                    name=demangle_name(parts[8]), enclave=demangle_name(parts[6]))
    topic = None
    if kind != NODE:
        if len(parts) < ENDPOINT_PARTS:
            return None
        qos = qos_model.from_keyexpr(parts[12])
        if qos is None:
            return None
        metadata = None
        if not legacy and len(parts) > ENDPOINT_PARTS:
            metadata = parse_backends_segment(parts[13])
        topic = TopicInfo(domain_id=domain_id, name=demangle_name(parts[9]),
                          type=demangle_name(parts[10]), type_hash=demangle_name(parts[11]),
                          qos=qos, backend_metadata=metadata)
    return Entity(zid=parts[2], nid=parts[3], id=parts[4], kind=kind, node=node, topic=topic,
                  legacy=legacy)
