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


#: Private names read on purpose outside their module: third-party internals we must reach,
#: attributes this library sets on foreign objects for itself, and the generated message
#: classes' class attributes (underscored so they never collide with a message's field names),
#: and threading's exit hook that runs before the interpreter joins non-daemon threads (the one
#: concurrent.futures uses; buffer_pubsub._process closes open nodes there).
PRIVATE_READS_ALLOWED = {"_src", "_C", "_set_throw_on_mutable_data_ptr", "_warp_buffer_keep",
                         "_tensor_conversions_owner", "_rosidl_buffer_owner", "_schema",
                         "_buffer_fields", "_register_atexit"}


def private_reads_across_modules(package: str) -> list[str]:
    """``x._name`` in ``package`` where ``x`` is not ``self``/``cls``, ``_name`` is not defined
    or assigned in the same file, and ``x`` is not one of the package's private modules."""
    found = []
    for path in sorted((ROOT / package).rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        local: set[str] = set()
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                local.add(node.name)
            elif isinstance(node, ast.Name):
                local.add(node.id)
            elif isinstance(node, ast.alias):
                local.add(node.asname or node.name.split(".")[-1])
            elif isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) \
                    and node.value.id in ("self", "cls"):
                local.add(node.attr)
            elif isinstance(node, ast.Constant) and isinstance(node.value, str):
                local.add(node.value)  # __slots__ entries
        for node in ast.walk(tree):
            if not (isinstance(node, ast.Attribute) and node.attr.startswith("_")
                    and not node.attr.startswith("__")):
                continue
            owner = node.value
            if isinstance(owner, ast.Name) and owner.id in ("self", "cls"):
                continue
            if node.attr in local or node.attr in PRIVATE_READS_ALLOWED:
                continue
            found.append(f"{path.relative_to(ROOT)}:{node.lineno}: {ast.unparse(node)}")
    return found


@pytest.mark.parametrize("package", sorted(PROJECT_PACKAGES))
def test_no_module_reads_another_modules_private_attributes(package: str) -> None:
    """One owner per piece of state: what another module needs is its owner's public API."""
    assert private_reads_across_modules(package) == []
