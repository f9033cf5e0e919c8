"""The machine a run measured: platform, CPU, memory, package versions."""

from __future__ import annotations

import os
import platform
import sys
from importlib import metadata
from typing import Any

PACKAGES = ("warp-buffer", "warp-lang", "numpy", "eclipse-zenoh", "iceoryx2", "torch", "rosbags",
            "matplotlib")


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as cpuinfo:
            for line in cpuinfo:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def _memory_gib() -> float | None:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / (1 << 30)
    except (ValueError, OSError, AttributeError):
        return None


def _version(package: str) -> str | None:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return None


def machine_info() -> dict[str, Any]:
    """Everything needed to tell which machine produced a result file."""
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {
        "platform": platform.platform(),
        "python": sys.version.split()[0],
        "cpu_model": _cpu_model(),
        "logical_cores": os.cpu_count(),
        "usable_cores": usable,
        "memory_gib": _memory_gib(),
        "nvidia_gpu_present": os.path.exists("/dev/nvidia0"),
        "versions": {name: _version(name) for name in PACKAGES},
    }


def describe(info: dict[str, Any]) -> str:
    """One line: CPU, cores, memory, OS, Python."""
    memory = f", {info['memory_gib']:.0f} GiB" if info.get("memory_gib") else ""
    return (f"{info['cpu_model']} ({info['usable_cores']} usable cores{memory}), "
            f"{info['platform']}, Python {info['python']}")
