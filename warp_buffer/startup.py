"""Start Warp without writing to the application's stdout.

Warp prints a start-up banner and its kernel-module load times to **stdout** and, from its native
library, a "could not load the CUDA driver" warning to file descriptor 2. A library must leave
stdout to the application (its stdout may be data), so :func:`init_warp`, called once when
``warp_buffer`` is imported, routes Warp's messages into :mod:`logging` (logger ``"warp"``) and
initialises the runtime with fd 2 captured, logging the CUDA-driver line at INFO
(logger ``"warp_buffer"``) and writing anything else it caught back to stderr.

Set ``WARP_BUFFER_VERBOSE=1`` (the ``warp-buffer --verbose`` flag sets it) to leave Warp's own
output unfiltered (its start-up banner then goes to stderr, never to stdout). A logger the
application installed with ``wp.set_logger`` is never replaced.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import tempfile
import threading
import warnings
from collections.abc import Iterator
from typing import Any

from ._env import env_flag

__all__ = ["VERBOSE_ENV", "init_warp", "verbose_requested"]

VERBOSE_ENV = "WARP_BUFFER_VERBOSE"
_CUDA_DRIVER_LINE = "Could not find or load the NVIDIA CUDA driver"

_log = logging.getLogger("warp_buffer")
_lock = threading.Lock()
_done = False


def verbose_requested() -> bool:
    """True when env ``WARP_BUFFER_VERBOSE`` asks for Warp's own output (1/true/yes/on)."""
    return env_flag(VERBOSE_ENV, False)


class _LoggingWarpLogger:
    """Warp's ``Logger`` protocol on top of :mod:`logging` (Warp's default writes to stdout)."""

    def __init__(self) -> None:
        self._log = logging.getLogger("warp")

    def debug(self, message: str) -> None:
        self._log.debug(message)

    def info(self, message: str) -> None:
        self._log.info(message)

    def warning(self, message: str, category: Any = None, stacklevel: int = 1) -> None:
        warnings.warn(message, category, stacklevel=stacklevel + 1)  # stderr, filterable

    def error(self, message: str) -> None:
        self._log.error(message)


def init_warp() -> Any:
    """Import and initialise Warp quietly (see the module docstring); returns the module.

    Idempotent and cheap after the first call. Safe when the application initialised Warp first.
    """
    global _done
    import warp as wp

    if _done:
        return wp
    with _lock:
        if _done:
            return wp
        if verbose_requested():
            # Warp's own output, unfiltered, but on stderr: stdout is the application's (a
            # `warp-buffer --verbose info --json` stays JSON)
            with contextlib.redirect_stdout(sys.stderr):
                wp.init()
        else:
            if type(wp.get_logger()).__name__ == "LoggerBasic":  # Warp's default: stdout
                wp.set_logger(_LoggingWarpLogger())
            with _captured_fd2() as captured:
                wp.init()
            _replay(captured())
        _done = True
    return wp


@contextlib.contextmanager
def _captured_fd2() -> Iterator[Any]:
    """Redirect file descriptor 2 into a temporary file; yields a function that reads it."""
    text = ""
    try:
        saved = os.dup(2)
    except OSError:  # no stderr at all (a daemon): nothing to capture
        yield lambda: text
        return
    with tempfile.TemporaryFile(mode="w+b") as sink:
        try:
            sys.stderr.flush()
        except (AttributeError, OSError, ValueError):  # sys.stderr None or closed
            pass
        try:
            os.dup2(sink.fileno(), 2)
            yield lambda: text
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            text = sink.read().decode("utf-8", "replace")


def _replay(text: str) -> None:
    for line in text.splitlines():
        if _CUDA_DRIVER_LINE in line:
            _log.info("%s (Warp runs on its cpu device only)", line.strip())
        elif line.strip() and sys.stderr is not None:
            sys.stderr.write(line + "\n")  # not ours to judge: hand it back where it was going
