"""Progress of ``bag record`` / ``bag play``: one line on stderr, rewritten in place, shown only
when stderr is a terminal (a log file or a pipe gets nothing, as ``ros2 bag`` keeps quiet there).
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

def size_text(nbytes: float) -> str:
    """``nbytes`` in the largest binary unit it reaches, as ``ros2 bag info`` prints a size:
    whole bytes below 1 KiB, else one decimal (``512 B``, ``1.5 KiB``, ``23.1 MiB``)."""
    units = ("B", "KiB", "MiB", "GiB", "TiB")
    unit = 0
    while nbytes >= 1024 and unit < len(units) - 1:
        nbytes /= 1024
        unit += 1
    return f"{nbytes:.{0 if unit == 0 else 1}f} {units[unit]}"


class Progress:
    """Counts of a running recording or playback, printed at most every ``interval_s``."""

    def __init__(self, verb: str, stream: TextIO | None = None, interval_s: float = 0.5) -> None:
        self.verb = verb
        self.stream = sys.stderr if stream is None else stream
        self.enabled = bool(getattr(self.stream, "isatty", lambda: False)())
        self.interval_s = interval_s
        self.started = time.monotonic()
        self._last = 0.0
        self._width = 0

    def update(self, messages: int, nbytes: int, dropped: int | None = None,
               force: bool = False) -> None:
        """Show the counts so far (messages, size, rates, and drops when counted)."""
        now = time.monotonic()
        if not self.enabled or (not force and now - self._last < self.interval_s):
            return
        self._last = now
        elapsed = max(now - self.started, 1e-9)
        line = (f"{self.verb} {messages} messages, {size_text(nbytes)}, "
                f"{messages / elapsed:.1f} msg/s, {size_text(nbytes / elapsed)}/s")
        if dropped is not None:
            line += f", dropped {dropped}"
        self.stream.write("\r" + line.ljust(self._width))
        self.stream.flush()
        self._width = len(line)

    def close(self) -> None:
        """End the progress line (the command's report goes to stdout after it)."""
        if self.enabled and self._width:
            self.stream.write("\n")
            self.stream.flush()
