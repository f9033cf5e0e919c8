"""What an in-process subscription receives: the message as it was when it was published.

A subscription in the publisher's process gets no serialized copy, but it must not get the
publisher's object either: rclpy code reuses one message (``msg.data = ...; pub.publish(msg)``
in a loop), and a subscriber still holding, or with queued, an earlier publish would then read
values that were never published, or a value another subscriber wrote into it.

:func:`snapshot` makes a new message object per subscription whose fields are the published
values: nested messages and lists are snapshots of their own, everything immutable (numbers,
strings) is shared, and so are the payloads: buffers (``uint8[]`` fields: zero-copy, a
reader's share of the published ``Buffer`` each, see :data:`rosidl_buffer.buffer.set_origin`,
whose ``release()`` ends that subscription's hold alone) and NumPy arrays (a list of numbers
is copied). Writing *into* those after publish is seen by in-process subscribers, as a write
into a loan's memory would be (see README, "Loans"). The copier is compiled once per message
type from its schema (a line per field, no per-field dispatch), as the CDR codec and the
validator are.
"""

from __future__ import annotations

import keyword
from collections.abc import Callable
from typing import Any

from rosidl_buffer import Buffer
from rosidl_buffer.buffer import impl_of, set_impl, set_origin
from rosidl_buffer.messages import FieldKind, Message, get_schema

__all__ = ["copier", "snapshot"]

_copiers: dict[type, Callable[[Any], Any]] = {}


def snapshot(msg: Message) -> Message:
    """A new message of ``msg``'s type holding ``msg``'s values (see the module docstring)."""
    return copier(type(msg))(msg)  # type: ignore[no-any-return]


def copier(cls: type) -> Callable[[Any], Any]:
    """The compiled :func:`snapshot` of messages of exactly ``cls`` (a publisher keeps its
    type's: one call per subscription on the publish path instead of two)."""
    function = _copiers.get(cls)
    if function is None:
        function = _copiers[cls] = _compile(cls)
    return function


def _slot(cls: type, name: str) -> Any:
    """The slot descriptor of field ``name``: on the generated class, which a user's subclass
    of it inherits."""
    for klass in cls.__mro__:
        if name in klass.__dict__:
            return klass.__dict__[name]
    raise AttributeError(f"{cls.__name__} has no field {name!r}")


def _compile(cls: type) -> Callable[[Any], Any]:
    scope: dict[str, Any] = {"cls": cls, "new": cls.__new__, "snapshot": snapshot,
                             "Buffer": Buffer, "new_buffer": Buffer.__new__, "impl_of": impl_of,
                             "set_impl": set_impl, "set_origin": set_origin}
    lines = ["def copy(m):", "    n = new(cls)"]
    for i, spec in enumerate(get_schema(cls.__msgtype__).fields):
        name = spec.name
        read = f"m.{name}" if name.isidentifier() and not keyword.iskeyword(name) \
            else f"getattr(m, {name!r})"
        scope[f"set{i}"] = _slot(cls, name).__set__  # the slot itself: no __setattr__
        if spec.kind is FieldKind.MESSAGE:  # (validated before: the values are messages)
            if spec.is_collection:
                lines.append(f"    set{i}(n, [snapshot(x) for x in {read}])")
            else:
                lines.append(f"    set{i}(n, snapshot({read}))")
        elif spec.is_buffer:  # a reader's share of the Buffer (set_origin), no call per field
            lines += [f"    v = {read}", "    if type(v) is Buffer:",
                      "        b = new_buffer(Buffer); set_impl(b, impl_of(v)); set_origin(b, v)",
                      "        v = b", f"    set{i}(n, v)"]
        elif spec.is_collection and spec.kind is FieldKind.STRING:
            lines.append(f"    set{i}(n, list({read}))")
        elif spec.is_collection and not spec.is_buffer:  # a list of numbers is copied too
            lines += [f"    v = {read}", f"    set{i}(n, list(v) if type(v) is list else v)"]
        else:
            lines.append(f"    set{i}(n, {read})")
    if cls.__dictoffset__:  # a user's subclass with attributes of its own
        lines.append("    n.__dict__.update(m.__dict__)")
    lines.append("    return n")
    exec("\n".join(lines) + "\n", scope)  # noqa: S102 - built from the schema's field names
    return scope["copy"]  # type: ignore[no-any-return]
