"""Default values of ``.msg`` fields (``float64 w 1``), which rosbags' parser drops.

A field written ``TYPE NAME VALUE`` starts at ``VALUE`` in a new message, as rclpy's generated
classes do; every other field at its type's zero. The definitions rosbags ships (the ROS 2
distribution's) come without their text, so their non-zero defaults are listed here:
``DISTRIBUTION_DEFAULTS`` holds every one in that distribution's interface packages
(common_interfaces and rcl_interfaces sources: the others are zeros or have none).
"""

from __future__ import annotations

import re
import struct
from collections.abc import Iterator
from typing import Any

from ..errors import InvalidMessageDefinitionError

DISTRIBUTION_DEFAULTS: dict[str, dict[str, Any]] = {
    "geometry_msgs/msg/Quaternion": {"w": 1.0},  # the identity rotation
    "sensor_msgs/msg/NavSatStatus": {"status": -2},  # STATUS_UNKNOWN
}

# TYPE NAME VALUE; a constant (TYPE NAME=VALUE) has its "=" right after the name.
_FIELD = re.compile(
    r"^\s*(?P<type>\S+)\s+(?P<name>[A-Za-z][A-Za-z0-9_]*)\s+(?P<value>[^=\s].*?)\s*$")
_ARRAY = re.compile(r"^(?P<base>[^\[]+)\[(?P<bound><=)?(?P<count>\d*)\]$")
_FLOATS = frozenset({"float32", "float64"})
_STRINGS = frozenset({"string", "wstring"})


def parse_defaults(text: str, type_name: str) -> dict[str, Any]:
    """The default values of ``text``'s fields (its first definition: a bag's concatenated
    ``MSG:`` sections after a line of ``=`` are other types), by field name."""
    defaults: dict[str, Any] = {}
    for raw in text.splitlines():
        if raw.startswith("==="):
            break
        match = _FIELD.match(_strip_comment(raw))
        if match is None:
            continue
        field_type, name, value = match["type"], match["name"], match["value"]
        try:
            defaults[name] = _value(field_type, value)
        except ValueError as exc:
            raise InvalidMessageDefinitionError(
                f"{type_name}: field {name!r} ({field_type}) cannot default to {value}: {exc}"
            ) from None
    return defaults


def _unquoted(text: str) -> Iterator[tuple[int, str]]:
    """``(index, character)`` of each character of ``text`` outside quotes (quotes excluded)."""
    quote = ""
    for i, char in enumerate(text):
        if quote:
            if char == quote:
                quote = ""
        elif char in "'\"":
            quote = char
        else:
            yield i, char


def _strip_comment(line: str) -> str:
    """``line`` up to its first ``#`` outside quotes."""
    return next((line[:i] for i, char in _unquoted(line) if char == "#"), line)


def _value(field_type: str, text: str) -> Any:
    array = _ARRAY.match(field_type)
    if array is None:
        return _scalar(_unbounded_number(field_type), text)
    base = _unbounded_number(array["base"])
    if not (text.startswith("[") and text.endswith("]")):
        raise ValueError("an array's default is a list in brackets")
    inner = text[1:-1].strip()
    items = [_scalar(base, item.strip()) for item in _split(inner)] if inner else []
    count = int(array["count"]) if array["count"] else 0
    if count and not array["bound"] and len(items) != count:
        raise ValueError(f"{len(items)} values for an array of {count}")
    if count and array["bound"] and len(items) > count:
        raise ValueError(f"{len(items)} values for a sequence of at most {count}")
    return tuple(items)  # (a field spec is hashable)


def _unbounded_number(base: str) -> str:
    """``base`` without a bound, except a string's (``string<=5``), which limits its default."""
    name, _, bound = base.partition("<=")
    return base if name in _STRINGS and bound else name


def _split(text: str) -> list[str]:
    """Comma-separated items, commas inside quotes kept."""
    cuts = [i for i, char in _unquoted(text) if char == ","]
    return [text[a + 1:b] for a, b in zip([-1, *cuts], [*cuts, len(text)])]


def _scalar(base: str, text: str) -> Any:
    if base.split("<=")[0] in _STRINGS:
        if len(text) >= 2 and text[0] == text[-1] and text[0] in "'\"":
            text = text[1:-1]
        bound = base.partition("<=")[2]
        if bound and len(text) > int(bound):
            raise ValueError(f"longer than its bound of {bound} characters")
        return text
    if base == "bool":
        lowered = text.lower()
        if lowered in ("true", "1"):
            return True
        if lowered in ("false", "0"):
            return False
        raise ValueError("a bool is true or false")
    if "/" in base or base[:1].isupper():
        raise ValueError("a field of a message type has no default")
    value = float(text) if base in _FLOATS else int(text)
    _check_fits(base, value)
    return value


def _check_fits(base: str, value: float) -> None:
    """ValueError unless ``value`` packs as ``base`` on the wire: the codec's own check, so a
    default is refused at registration exactly where serializing it would fail."""
    from ._schema import PRIMITIVE_FORMATS  # (here: _schema imports this module)

    fmt = PRIMITIVE_FORMATS.get(base)
    if fmt is None:
        return
    try:
        struct.pack("<" + fmt, value)
    except (struct.error, OverflowError) as exc:  # OverflowError: 1e300 in a float32
        raise ValueError(f"out of {base}'s range ({exc})") from None
