"""``node.get_logger()``: a :mod:`logging` logger that also takes rclpy's calls.

Code ported from rclpy logs with ``logger.info(msg, throttle_duration_sec=1.0)``, ``once=True``
or ``skip_first=True``, calls ``warn``, ``fatal``, ``get_child``, ``set_level`` and reads the
``bool`` a call returns (whether it logged). :class:`NodeLogger` keeps all of that over a standard
``logging.Logger`` named after the node, so handlers, levels and formats stay Python's: the
library adds no handler and writes nothing unless the application configures logging.

Filters follow rclpy's: they are kept per call site (a line, and a place within it), evaluated
only when the level is enabled, in the order throttle, skip-first, once; a throttled call site
logs its first call, then at most once per interval of the monotonic clock; a site whose filter
arguments change between calls raises ValueError, as in rclpy.
"""

from __future__ import annotations

import inspect
import logging
import threading
import time
from typing import Any

__all__ = ["NodeLogger"]

#: Attributes of the logging.Logger a user sets through the node's logger.
_LOGGER_SETTINGS = frozenset({"propagate", "disabled", "level", "handlers", "filters", "parent"})
#: rclpy's only throttle clock (``RCUTILS_STEADY_TIME``: Python's monotonic clock).
STEADY_TIME = "RCUTILS_STEADY_TIME"


class _Site:
    """One call site's filter state."""

    __slots__ = ("filters", "last_logged", "skipped", "logged_once")

    def __init__(self, filters: tuple[Any, ...]) -> None:
        self.filters = filters  # (throttle, skip_first, once), fixed at the site's first call
        self.last_logged: float | None = None
        self.skipped = False
        self.logged_once = False


class NodeLogger(logging.LoggerAdapter):  # type: ignore[type-arg]
    """A node's logger: ``logging.Logger``'s methods and attributes (forwarded to the logger it
    wraps, ``.logger``), plus rclpy's filters and names.

    ``debug/info/warning/warn/error/fatal/critical(msg, *args, throttle_duration_sec=None,
    throttle_time_source_type="RCUTILS_STEADY_TIME", skip_first=False, once=False, **kwargs)``
    return whether the message was logged. ``log(level, msg, ...)`` is Python's; rclpy's
    ``log(msg, severity, ...)`` (the message first) is taken too. Levels are rclpy's severities
    and Python's alike (DEBUG 10, INFO 20, WARN 30, ERROR 40, FATAL 50)."""

    def __init__(self, logger: logging.Logger) -> None:
        super().__init__(logger, {})
        self._sites: dict[tuple[Any, ...], _Site] = {}
        self._lock = threading.Lock()

    # The logging.Logger underneath answers for what an adapter lacks (handlers, filters,
    # getChild, ...), and takes the settings a user assigns (propagate, disabled).
    def __getattr__(self, name: str) -> Any:
        if name.startswith("__") or name in ("logger", "_sites", "_lock"):
            raise AttributeError(name)
        return getattr(self.logger, name)

    def __setattr__(self, name: str, value: Any) -> None:
        if name in _LOGGER_SETTINGS:
            setattr(self.logger, name, value)
        else:
            object.__setattr__(self, name, value)

    def process(self, msg: Any, kwargs: Any) -> tuple[Any, Any]:
        return msg, kwargs  # no extra context: records are the logger's own

    # -- rclpy's names ---------------------------------------------------------------------------
    def get_child(self, name: str) -> NodeLogger:
        """The logger ``<this name>.<name>`` (rclpy's ``get_child``)."""
        if not name:
            raise ValueError("a child logger needs a name")
        return NodeLogger(self.logger.getChild(name))

    def set_level(self, level: int | str) -> None:
        """``setLevel``: an rclpy severity, a :mod:`logging` level or its name."""
        self.logger.setLevel(level)

    def get_effective_level(self) -> int:
        return self.logger.getEffectiveLevel()

    def is_enabled_for(self, severity: int) -> bool:
        return self.logger.isEnabledFor(severity)

    # -- logging ---------------------------------------------------------------------------------
    def debug(self, msg: Any, *args: Any, **kwargs: Any) -> bool:  # type: ignore[override]
        return self._log_filtered(logging.DEBUG, msg, args, kwargs)

    def info(self, msg: Any, *args: Any, **kwargs: Any) -> bool:  # type: ignore[override]
        return self._log_filtered(logging.INFO, msg, args, kwargs)

    def warning(self, msg: Any, *args: Any, **kwargs: Any) -> bool:  # type: ignore[override]
        return self._log_filtered(logging.WARNING, msg, args, kwargs)

    def warn(self, msg: Any, *args: Any, **kwargs: Any) -> bool:  # type: ignore[override]
        """rclpy's spelling of :meth:`warning` (no deprecation warning: ported code uses it)."""
        return self._log_filtered(logging.WARNING, msg, args, kwargs)

    def error(self, msg: Any, *args: Any, **kwargs: Any) -> bool:  # type: ignore[override]
        return self._log_filtered(logging.ERROR, msg, args, kwargs)

    def exception(self, msg: Any, *args: Any, exc_info: Any = True,  # type: ignore[override]
                  **kwargs: Any) -> bool:
        return self._log_filtered(logging.ERROR, msg, args, dict(kwargs, exc_info=exc_info))

    def critical(self, msg: Any, *args: Any, **kwargs: Any) -> bool:  # type: ignore[override]
        return self._log_filtered(logging.CRITICAL, msg, args, kwargs)

    def fatal(self, msg: Any, *args: Any, **kwargs: Any) -> bool:
        """rclpy's FATAL: :meth:`critical`."""
        return self._log_filtered(logging.CRITICAL, msg, args, kwargs)

    def log(self, level: Any, msg: Any, *args: Any,  # type: ignore[override]
            **kwargs: Any) -> bool:
        if isinstance(level, str) and isinstance(msg, int):  # rclpy: log(message, severity)
            level, msg = msg, level
        if not isinstance(level, int) or isinstance(level, bool):
            raise TypeError(f"a log level is an int, got {type(level).__name__}")
        return self._log_filtered(level, msg, args, kwargs)

    def _log_filtered(self, level: int, msg: Any, args: tuple[Any, ...],
                      kwargs: dict[str, Any]) -> bool:
        throttle = kwargs.pop("throttle_duration_sec", None)
        clock = kwargs.pop("throttle_time_source_type", STEADY_TIME)
        skip_first = bool(kwargs.pop("skip_first", False))
        once = bool(kwargs.pop("once", False))
        if clock != STEADY_TIME:
            raise ValueError(f"throttle_time_source_type {clock!r}: only {STEADY_TIME!r} "
                             "(the monotonic clock) is supported, as in rclpy")
        if throttle is not None and (isinstance(throttle, bool) or not isinstance(
                throttle, (int, float)) or not throttle >= 0):
            raise ValueError(f"throttle_duration_sec must be a number >= 0, got {throttle!r}")
        if not self.logger.isEnabledFor(level):
            return False
        if throttle or skip_first or once:
            # the user's frame: it called debug/info/..., which called this method
            caller = inspect.currentframe().f_back.f_back  # type: ignore[union-attr]
            key = (caller.f_code, caller.f_lasti)
            if not self._passes(key, throttle, skip_first, once):
                return False
        kwargs.setdefault("stacklevel", 1)
        kwargs["stacklevel"] += 2  # the record names the user's line, not this module's
        self.logger.log(level, msg, *args, **kwargs)
        return True

    def _passes(self, key: tuple[Any, ...], throttle: float | None, skip_first: bool,
                once: bool) -> bool:
        # rclpy's order: throttle, then skip-first, then once; a filter that refuses ends it
        # (the later ones keep their state, as rcutils' macros do).
        filters = (throttle, skip_first, once)
        with self._lock:
            site = self._sites.get(key)
            if site is None:
                site = self._sites[key] = _Site(filters)
            elif site.filters != filters:  # rclpy refuses it too: the site keeps one state
                raise ValueError(f"a call site's logging filters cannot change between calls "
                                 f"(throttle, skip_first, once: {site.filters} then {filters})")
            if throttle:
                now = time.monotonic()
                if site.last_logged is not None and now < site.last_logged + throttle:
                    return False
                site.last_logged = now
            if skip_first and not site.skipped:
                site.skipped = True
                return False
            if once:
                if site.logged_once:
                    return False
                site.logged_once = True
            return True

    def __repr__(self) -> str:
        return f"NodeLogger({self.logger.name!r})"

