"""ROS 2 name rules for node names, namespaces and topics (as ``rclpy.validate_*``).

A bad name raises :class:`~buffer_pubsub.errors.InvalidNameError` (a ``ValueError``) saying which
rule it breaks, before anything is declared on the network.

- node name: ``[A-Za-z_][A-Za-z0-9_]*``, at most 255 characters;
- namespace: empty or absolute, tokens of ``[A-Za-z0-9_]`` not starting with a digit, separated by
  single ``/``, no trailing ``/`` (``"ns"`` is taken as ``"/ns"``, as rclpy does);
- topic: the same tokens, absolute (``/a/b``), relative to the namespace (``a/b``) or private to
  the node (``~`` or ``~/a``); substitutions ``{node}`` and ``{ns}``/``{namespace}`` are expanded.
"""

from __future__ import annotations

import re

from .errors import InvalidNameError

__all__ = ["expand_topic_name", "validate_namespace", "validate_node_name", "validate_topic_name"]

MAX_NODE_NAME_LENGTH = 255
#: rmw's limit on a fully qualified topic name (RMW_TOPIC_MAX_NAME_LENGTH less the DDS prefix).
MAX_TOPIC_NAME_LENGTH = 247

_NODE_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_SUBSTITUTION = re.compile(r"\{([^{}]*)\}")


def validate_node_name(name: object) -> str:
    """``name`` if it is a valid ROS 2 node name, else :class:`InvalidNameError`."""
    if not isinstance(name, str) or not name:
        raise InvalidNameError(f"node name must be a non-empty str, got {name!r}")
    if len(name) > MAX_NODE_NAME_LENGTH:
        raise InvalidNameError(f"node name longer than {MAX_NODE_NAME_LENGTH} characters")
    if not _NODE_NAME.fullmatch(name):
        raise InvalidNameError(
            f"invalid node name {name!r}: use letters, digits and '_', not starting with a digit")
    return name


def _check_tokens(name: str, what: str, original: str) -> None:
    body = name[1:] if name.startswith("/") else name  # one leading '/' (absolute); no more
    for token in body.split("/") if body else ():  # (callers refuse a trailing '/')
        if not token:
            raise InvalidNameError(f"invalid {what} {original!r}: contains '//'")
        if not _TOKEN.fullmatch(token):
            raise InvalidNameError(
                f"invalid {what} {original!r}: token {token!r} must be letters, digits and '_', "
                "not starting with a digit")


def validate_namespace(namespace: object) -> str:
    """The absolute form of a valid namespace (``""`` for the root), else InvalidNameError."""
    if not isinstance(namespace, str):
        raise InvalidNameError(f"namespace must be a str, got {namespace!r}")
    if namespace in ("", "/"):
        return ""
    if namespace.endswith("/"):
        raise InvalidNameError(f"invalid namespace {namespace!r}: ends with '/'")
    absolute = namespace if namespace.startswith("/") else "/" + namespace
    _check_tokens(absolute, "namespace", namespace)
    return absolute


def validate_topic_name(topic: object) -> str:
    """``topic`` if it is a valid (not yet expanded) ROS 2 topic name, else InvalidNameError."""
    if not isinstance(topic, str) or not topic:
        raise InvalidNameError(f"topic name must be a non-empty str, got {topic!r}")
    if topic.endswith("/"):
        raise InvalidNameError(f"invalid topic name {topic!r}: ends with '/'")
    if "~" in topic[1:] or (topic.startswith("~") and topic not in ("~",)
                             and not topic.startswith("~/")):
        raise InvalidNameError(f"invalid topic name {topic!r}: '~' only as '~' or '~/...'")
    body = _SUBSTITUTION.sub("x", topic.lstrip("~"))
    if "{" in body or "}" in body:
        raise InvalidNameError(f"invalid topic name {topic!r}: unbalanced '{{' or '}}'")
    _check_tokens(body, "topic name", topic)
    return topic


def expand_topic_name(topic: str, node_name: str, namespace: str) -> str:
    """The fully qualified form of a valid ``topic`` for a node ``node_name`` in ``namespace``
    (absolute, ``""`` for the root), as rcl expands it."""
    validate_topic_name(topic)

    def substitute(match: re.Match[str]) -> str:
        key = match.group(1)
        if key == "node":
            return node_name
        if key in ("ns", "namespace"):
            return namespace.strip("/")
        raise InvalidNameError(f"invalid topic name {topic!r}: unknown substitution {{{key}}}")

    expanded = _SUBSTITUTION.sub(substitute, topic)
    if expanded.startswith("~"):
        expanded = f"{namespace}/{node_name}{expanded[1:]}"
    elif not expanded.startswith("/"):
        expanded = f"{namespace}/{expanded}"
    expanded = "/" + expanded.strip("/")
    _check_tokens(expanded, "topic name", topic)
    if len(expanded) > MAX_TOPIC_NAME_LENGTH:
        raise InvalidNameError(
            f"topic name {expanded!r} longer than {MAX_TOPIC_NAME_LENGTH} characters")
    return expanded
