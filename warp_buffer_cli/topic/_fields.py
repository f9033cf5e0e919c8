"""A received message as plain data, printed as ``ros2 topic echo`` prints it (YAML, or one CSV
line), with ``uint8[]`` buffers summarised (backend, size, first bytes) instead of listed."""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from typing import Any

import numpy as np

__all__ = ["BUFFER_PREVIEW", "csv_line", "pick", "to_plain", "yaml_lines"]

#: Bytes of a buffer shown by echo.
BUFFER_PREVIEW = 16
# What YAML 1.1's implicit resolvers (PyYAML's, which ``ros2 topic echo`` prints with) would
# read as something other than a string: such a string is quoted to stay one.
_NOT_A_STRING = re.compile(r"""^(?:
    yes|Yes|YES|no|No|NO|true|True|TRUE|false|False|FALSE|on|On|ON|off|Off|OFF
  | ~|null|Null|NULL|<<|=
  | [-+]?(?:0b[0-1_]+|0[0-7_]+|0|[1-9][0-9_]*|0x[0-9a-fA-F_]+|[1-9][0-9_]*(?::[0-5]?[0-9])+)
  | [-+]?[0-9][0-9_]*\.[0-9_]*(?:[eE][-+][0-9]+)? | \.[0-9][0-9_]*(?:[eE][-+][0-9]+)?
  | [-+]?[0-9][0-9_]*(?::[0-5]?[0-9])+\.[0-9_]* | [-+]?\.(?:inf|Inf|INF) | \.(?:nan|NaN|NAN)
  | [0-9]{4}-[0-9]{2}-[0-9]{2}
  | [0-9]{4}-[0-9]{1,2}-[0-9]{1,2}(?:[Tt]|[ \t]+)[0-9]{1,2}:[0-9]{2}:[0-9]{2}(?:\.[0-9]*)?
    (?:[ \t]*(?:Z|[-+][0-9]{1,2}(?::[0-9]{2})?))?
)$""", re.VERBOSE)
# A plain (unquoted) block scalar may not start with an indicator, hold ": " or " #", end with
# ":" or a space, or start with one.
_INDICATOR_START = re.compile(r"^(?:[#,\[\]{}&*!|>'\"%@`]|[-?:](?:\s|$)|\s)")
_INDICATOR_INSIDE = re.compile(r": | #|:$|\s$")


def _string(value: str) -> str:
    """``value`` as PyYAML's block style writes it: plain when it reads back as the same
    string, else single-quoted; double-quoted (escaped) when it holds a line break or a
    character a terminal would not show."""
    if not value.isprintable():
        return json.dumps(value, ensure_ascii=False)
    if (not value or _INDICATOR_START.match(value) or _INDICATOR_INSIDE.search(value)
            or _NOT_A_STRING.match(value)):
        return "'" + value.replace("'", "''") + "'"
    return value


def to_plain(value: Any, truncate: int) -> Any:
    """Messages become dicts (field order kept), buffers a summary, arrays lists (at most
    ``truncate`` items, then ``'...'``; 0: no limit)."""
    from rosidl_buffer import Buffer
    from rosidl_buffer.messages import Message, fields_of

    if isinstance(value, Message):
        return {spec.name: to_plain(getattr(value, spec.name), truncate)
                for spec in fields_of(type(value))}
    if isinstance(value, Buffer):  # (a --truncate-length shorter than the preview wins)
        shown = min(BUFFER_PREVIEW, truncate) if truncate else BUFFER_PREVIEW
        head = value.to_numpy()[:shown] if len(value) else np.zeros(0, np.uint8)
        return {"backend": value.get_backend_type(), "size": len(value),
                "first_bytes": [int(b) for b in head]}
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, (list, tuple)):
        items = list(value)
        shown = items if not truncate or len(items) <= truncate else items[:truncate]
        out = [to_plain(item, truncate) for item in shown]
        return out + ["..."] if len(shown) < len(items) else out
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, str) and truncate and len(value) > truncate:
        return value[:truncate] + "..."
    return value


def pick(plain: Any, path: str) -> Any:
    """The value at ``path`` (``header.stamp.sec``; list items by index: ``points.0.x``)."""
    for part in filter(None, path.split(".")):
        if isinstance(plain, dict) and part in plain:
            plain = plain[part]
        elif isinstance(plain, list) and part.isdecimal() and int(part) < len(plain):
            plain = plain[int(part)]
        else:
            raise KeyError(part)
    return plain


def _scalar(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, str):
        return _string(value)
    return str(value)


def yaml_lines(plain: Any, indent: str = "") -> Iterator[str]:
    """Block YAML, as ``ros2 topic echo`` prints it (lists of scalars one item a line)."""
    if isinstance(plain, dict):
        for key, value in plain.items():
            if isinstance(value, dict) and value:
                yield f"{indent}{key}:"
                yield from yaml_lines(value, indent + "  ")
            elif isinstance(value, list) and value:
                yield f"{indent}{key}:"
                yield from yaml_lines(value, indent)
            else:
                empty = "{}" if isinstance(value, dict) else "[]" if isinstance(value, list) \
                    else _scalar(value)
                yield f"{indent}{key}: {empty}"
    elif isinstance(plain, list):
        for item in plain:
            if isinstance(item, dict) and item:
                lines = list(yaml_lines(item, indent + "  "))
                yield f"{indent}- {lines[0].lstrip()}"
                yield from lines[1:]
            else:
                yield f"{indent}- {_scalar(item) if not isinstance(item, (dict, list)) else item}"
    else:
        yield f"{indent}{_scalar(plain)}"


def _flatten(plain: Any) -> Iterator[Any]:
    if isinstance(plain, dict):
        for value in plain.values():
            yield from _flatten(value)
    elif isinstance(plain, list):
        for item in plain:
            yield from _flatten(item)
    else:
        yield plain


def csv_line(plain: Any) -> str:
    """Every leaf value in field order, comma separated (``ros2 topic echo --csv``)."""
    return ",".join("" if v is None else str(v) for v in _flatten(plain))
