"""Counting the Python frames a piece of work runs (``sys.setprofile``), for the per-message cost
of the warp path that :mod:`benchmarks.lane_stages` prints and a test bounds.

A frame is one Python function call (a ``"call"`` profile event: a function, a generator resumed,
a class body); C functions (``"c_call"``) are not frames. Work is counted on the calling thread
only. Frames of code the caller names in ``exclude`` (a benchmark's own wrappers and callback)
are not counted, nor is anything they run directly in C.
"""

from __future__ import annotations

import sys
from collections.abc import Iterable
from types import FrameType
from typing import Any

__all__ = ["FrameCounter"]


class FrameCounter:
    """Counts Python frames while it is started; ``count`` after :meth:`stop`.

    ``exclude``: file names whose frames are not counted (the measuring code itself).
    ``by_function`` keeps a tally per ``file:function`` for the last counted span, to find
    where the frames go.
    """

    def __init__(self, exclude: Iterable[str] = ()) -> None:
        self.exclude = frozenset(exclude) | {__file__}  # (its own stop() is not counted)
        self.count = 0
        self.by_function: dict[str, int] = {}
        self._previous: Any = None

    def _profile(self, frame: FrameType, event: str, arg: Any) -> None:
        if event == "call":
            code = frame.f_code
            if code.co_filename in self.exclude:
                return
            self.count += 1
            key = "/".join(code.co_filename.rsplit("/", 2)[-2:]) + ":" + code.co_name
            self.by_function[key] = self.by_function.get(key, 0) + 1

    def start(self) -> None:
        """Count from now on (this thread); resets the count."""
        self.count = 0
        self.by_function = {}
        self._previous = sys.getprofile()
        sys.setprofile(self._profile)

    def stop(self) -> int:
        """Stop counting; returns the count. Safe to call when not started."""
        if sys.getprofile() is self._profile or sys.getprofile() == self._profile:
            sys.setprofile(self._previous)
        self._previous = None
        return self.count

    def __enter__(self) -> FrameCounter:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
