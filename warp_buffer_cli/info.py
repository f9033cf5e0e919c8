"""``warp-buffer info``: registered backends with their metadata, Warp devices and IPC support."""

from __future__ import annotations

import argparse
import json
from typing import Any

from rosidl_buffer import registry


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print machine-readable JSON")


def collect() -> dict[str, Any]:
    """Everything ``info`` reports, as plain data."""
    backends: list[dict[str, Any]] = [{"name": "cpu", "metadata": "", "status": "built in"}]
    loaded, errors = registry.load_backends()
    for name in registry.get_backend_names()[1:]:
        if name in loaded:
            backends.append({"name": name, "metadata": loaded[name].get_backend_metadata(),
                             "status": "loaded"})
        else:
            backends.append({"name": name, "metadata": "", "status": f"error: {errors[name]}"})
    return {"backends": backends, "warp_devices": _warp_devices(), "fast_lane": _fast_lane()}


def _fast_lane() -> dict[str, Any]:
    """Whether the same-host lane (a ring per route, native) runs here, and why not."""
    from buffer_pubsub import fast_lane

    state = fast_lane.status()
    return {"available": state.available, "reason": state.reason,
            "resource_prefix": fast_lane.resource_prefix() if state.available else ""}


def _warp_devices() -> list[dict[str, Any]]:
    try:
        from warp_buffer import init_warp  # quiet: the report lists the devices itself

        wp = init_warp()
    except Exception as exc:  # info must still list the backends
        return [{"name": "unavailable", "error": str(exc)}]
    devices = []
    for device in wp.get_devices():
        entry: dict[str, Any] = {"name": str(device.alias), "is_cuda": bool(device.is_cuda)}
        if device.is_cuda:
            entry["ipc"] = "cuda ipc" if getattr(device, "is_ipc_supported", False) else "host staging"
        else:
            entry["ipc"] = "shared memory (mmap)"
        devices.append(entry)
    return devices


def run(args: argparse.Namespace) -> int:
    report = collect()
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    print("Buffer backends:")
    for backend in report["backends"]:
        metadata = f"  metadata: {backend['metadata']}" if backend["metadata"] else ""
        print(f"  {backend['name']:<8} {backend['status']}{metadata}")
    print("Warp devices:")
    for device in report["warp_devices"]:
        if "error" in device:
            print(f"  (Warp unavailable: {device['error']})")
        else:
            print(f"  {device['name']:<8} IPC: {device['ipc']}")
    lane = report["fast_lane"]
    print("Same-host fast lane: " + (
        f"available (abstract sockets {lane['resource_prefix']}*)" if lane["available"]
        else f"off: {lane['reason']}"))
    return 0
