"""The ``WARP_BUFFER_*`` environment switches, read one way everywhere."""

from __future__ import annotations

import math
import os

__all__ = ["env_flag", "env_float"]

_ON = ("1", "true", "yes", "on")
_OFF = ("0", "false", "no", "off")


def env_flag(name: str, default: bool) -> bool:
    """``name`` as a switch: 1/true/yes/on or 0/false/no/off (any case); unset or anything
    else: ``default``."""
    value = os.environ.get(name, "").strip().lower()
    if value in _ON:
        return True
    if value in _OFF:
        return False
    return default


def env_float(name: str, default: float) -> float:
    """``name`` as a finite number; unset, not a number, NaN or infinite: ``default``."""
    try:
        value = float(os.environ.get(name, default))
    except ValueError:
        return default
    return value if math.isfinite(value) else default
