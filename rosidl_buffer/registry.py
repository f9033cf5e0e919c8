"""The backend registry: buffer backend plugins found through Python entry points.

This plays pluginlib's role. A distribution registers a backend with::

    [project.entry-points."rosidl_buffer.backends"]
    warp = "warp_buffer_backend:WarpBufferBackend"

The entry point name is the backend's short name; the object is a :class:`BufferBackend`
subclass (or a zero-argument factory returning an instance). ``"cpu"`` is built in and always
listed. A plugin that fails to import or to construct is reported with :class:`BackendLoadError`
when it is asked for, and never prevents the other backends from loading.
"""

from __future__ import annotations

import logging
import threading
from importlib import metadata

from .backend import BufferBackend
from .buffer_impl import CPU_BACKEND
from .errors import BackendLoadError, UnknownBackendError

__all__ = [
    "ENTRY_POINT_GROUP",
    "get_backend_names",
    "create_backend_instance",
    "load_backends",
    "refresh",
]

ENTRY_POINT_GROUP = "rosidl_buffer.backends"

_log = logging.getLogger(__name__)
_lock = threading.Lock()
_entry_points: dict[str, metadata.EntryPoint] | None = None


def _plugins() -> dict[str, metadata.EntryPoint]:
    global _entry_points
    with _lock:
        if _entry_points is None:
            found: dict[str, metadata.EntryPoint] = {}
            for entry_point in metadata.entry_points(group=ENTRY_POINT_GROUP):
                if entry_point.name == CPU_BACKEND:
                    _log.warning("ignoring plugin %r: 'cpu' is built in", entry_point.value)
                    continue
                if entry_point.name in found and found[entry_point.name].value != entry_point.value:
                    _log.warning(
                        "backend %r registered twice (%s, %s); using the first",
                        entry_point.name, found[entry_point.name].value, entry_point.value,
                    )
                    continue
                found[entry_point.name] = entry_point
            _entry_points = found
        return _entry_points


def refresh() -> None:
    """Forget the cached plugin list (after installing a plugin at run time, or in tests)."""
    global _entry_points
    with _lock:
        _entry_points = None


def get_backend_names() -> list[str]:
    """Names of every registered backend, ``"cpu"`` first. Listing loads no plugin code."""
    return [CPU_BACKEND, *sorted(_plugins())]


def create_backend_instance(name: str) -> BufferBackend:
    """Load the plugin ``name`` and return a new instance of its backend.

    Raises :class:`UnknownBackendError` if no plugin has that name (``"cpu"`` included: the CPU
    path is plain serialization and has no plugin object) and :class:`BackendLoadError` if the
    plugin is registered but broken.
    """
    plugins = _plugins()
    if name == CPU_BACKEND:
        raise UnknownBackendError("'cpu' is the built-in CPU path and has no backend instance")
    entry_point = plugins.get(name)
    if entry_point is None:
        raise UnknownBackendError(
            f"no buffer backend named {name!r}; registered: {get_backend_names()}"
        )
    try:
        factory = entry_point.load()
    except Exception as exc:  # a broken plugin must not take the caller down
        raise BackendLoadError(f"backend {name!r} ({entry_point.value}) failed to import: {exc}") from exc
    try:
        backend = factory()
    except Exception as exc:
        raise BackendLoadError(f"backend {name!r} ({entry_point.value}) failed to start: {exc}") from exc
    if not isinstance(backend, BufferBackend):
        raise BackendLoadError(
            f"backend {name!r} ({entry_point.value}) is a {type(backend).__name__}, "
            "not a rosidl_buffer.BufferBackend"
        )
    if backend.get_backend_type() != name:
        raise BackendLoadError(
            f"backend registered as {name!r} reports get_backend_type() == "
            f"{backend.get_backend_type()!r}"
        )
    return backend


def load_backends(
    names: list[str] | None = None,
) -> tuple[dict[str, BufferBackend], dict[str, BackendLoadError]]:
    """Instantiate every (or the named) plugin; broken ones are returned apart, not raised.

    Returns ``(backends, errors)``: the loaded instances by name, and the load error of each
    plugin that failed. ``"cpu"`` is skipped (it has no instance).
    """
    loaded: dict[str, BufferBackend] = {}
    errors: dict[str, BackendLoadError] = {}
    for name in names if names is not None else get_backend_names():
        if name == CPU_BACKEND:
            continue
        try:
            loaded[name] = create_backend_instance(name)
        except BackendLoadError as exc:
            _log.debug("%s", exc)
            errors[name] = exc
        except UnknownBackendError as exc:
            errors[name] = BackendLoadError(str(exc))
    return loaded, errors
