"""Loading the project's native extensions (the per-message cores compiled from C at install).

Each package imports its extension through :func:`load_extension`, so a tree whose extensions
were never built (a checkout used without ``pip install``, a wheel for another Python) fails at
import with one clear, typed error that says what to do, instead of an ``AttributeError`` later.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from .errors import NativeExtensionMissingError

__all__ = ["REMEDY", "load_extension"]

REMEDY = ("build it with `pip install -e .` (or `pip install .`) on a machine with a C compiler "
          "and Python's headers (Debian: gcc python3-dev), or install a prebuilt wheel; "
          "see docs/native.md")


def load_extension(qualified_name: str) -> ModuleType:
    """The extension module ``qualified_name`` (e.g. ``"buffer_pubsub._ring"``).

    Raises:
        NativeExtensionMissingError: it is not built or does not load here.
    """
    try:
        return importlib.import_module(qualified_name)
    except ImportError as error:
        raise NativeExtensionMissingError(
            f"the native extension {qualified_name} is missing ({error}): {REMEDY}"
        ) from error
