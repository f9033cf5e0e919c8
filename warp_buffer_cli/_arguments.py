"""argparse types the ``warp-buffer`` commands share: bounded numbers and ROS 2 topic names
(a bad value is a usage error naming the option, exit 2)."""

from __future__ import annotations

import argparse
import math
from typing import Any


def topic_name(text: str) -> str:
    """A valid ROS 2 topic name, as given (relative names stay relative)."""
    from buffer_pubsub.errors import InvalidNameError
    from buffer_pubsub.names import validate_topic_name

    try:
        return validate_topic_name(text)
    except InvalidNameError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def absolute_topic_name(text: str) -> str:
    """A valid ROS 2 topic name, a relative one taken from the root (``frames``: ``/frames``),
    as the graph lists topics."""
    return topic_name(text if text.startswith(("/", "~")) else "/" + text)


def number(kind: type, low: float, inclusive: bool = True, high: float = math.inf,
           zero: bool = False) -> Any:
    """A ``kind`` number >= ``low`` (> ``low`` unless ``inclusive``) and <= ``high``; ``zero``:
    0 is allowed too (a special value)."""
    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a{'n integer' if kind is int else ' number'}") from None
        if zero and value == 0:
            return value
        if not (value >= low if inclusive else value > low) or value != value or value > high:
            show = (lambda v: str(int(v))) if kind is int else (lambda v: f"{v:g}")
            above = f"{'>=' if inclusive else '>'} {show(low)}"
            raise argparse.ArgumentTypeError(
                f"{text} is out of range: must be {above}" +
                (f" and <= {show(high)}" if high != math.inf else "") + (" (or 0)" if zero else ""))
        return value

    return parse
