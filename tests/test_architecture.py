"""Dependencies point one way: rosidl_buffer <- warp_buffer <- warp_buffer_backend, the buffer
layers <- tensor_conversions, and the transport knows backends only through rosidl_buffer."""

from __future__ import annotations

import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
PROJECT_PACKAGES = {"rosidl_buffer", "warp_buffer", "warp_buffer_backend", "tensor_conversions",
                    "buffer_pubsub", "warp_buffer_cli"}

# package -> project packages (and third-party backends' libraries) it must never import
FORBIDDEN = {
    "rosidl_buffer": PROJECT_PACKAGES - {"rosidl_buffer"} | {"warp", "torch", "zenoh"},
    "warp_buffer": {"warp_buffer_backend", "tensor_conversions", "buffer_pubsub",
                    "warp_buffer_cli", "zenoh"},
    "warp_buffer_backend": {"tensor_conversions", "buffer_pubsub", "warp_buffer_cli", "zenoh"},
    "tensor_conversions": {"warp_buffer_backend", "buffer_pubsub", "warp_buffer_cli", "zenoh"},
    "buffer_pubsub": {"warp_buffer", "warp_buffer_backend", "tensor_conversions",
                      "warp_buffer_cli", "warp", "torch"},
}


def imported_top_level_modules(package: str) -> dict[str, set[str]]:
    """Top-level module name -> files of ``package`` that import it (absolute imports only)."""
    found: dict[str, set[str]] = {}
    for path in (ROOT / package).rglob("*.py"):
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                found.setdefault(name.split(".")[0], set()).add(str(path.relative_to(ROOT)))
    return found


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_package_imports_point_one_way(package: str) -> None:
    imports = imported_top_level_modules(package)
    assert imports, f"no imports found in {package}: the scan is broken"
    violations = {name: sorted(files) for name, files in imports.items()
                  if name in FORBIDDEN[package]}
    assert not violations, f"{package} imports what it must not: {violations}"
