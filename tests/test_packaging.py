"""What a user installing the project meets: the distributions carry the licence and the
whole suite, the packages tell type checkers they are typed, a missing optional framework or
compiler names what to install."""

from __future__ import annotations

import os
import pathlib
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parent.parent
PACKAGES = ("rosidl_buffer", "warp_buffer", "warp_buffer_backend", "tensor_conversions",
            "buffer_pubsub", "warp_buffer_cli")


def test_every_package_is_marked_typed() -> None:
    """PEP 561: without py.typed, mypy skipped every package but rosidl_buffer."""
    for package in PACKAGES:
        assert (ROOT / package / "py.typed").is_file(), package
    assert '"py.typed"' in (ROOT / "pyproject.toml").read_text()  # shipped in the wheel


def test_the_distributions_carry_the_license_and_the_whole_suite() -> None:
    """No licence file shipped (Apache-2.0 asks for its text), and the sdist held 78 of the
    tests without their conftest and helpers."""
    assert (ROOT / "LICENSE").read_text().lstrip().startswith("Apache License")
    assert 'license-files = ["LICENSE"]' in (ROOT / "pyproject.toml").read_text()
    manifest = (ROOT / "MANIFEST.in").read_text().splitlines()
    assert {"graft tests", "graft docs", "graft examples"} <= set(manifest)


def test_the_torch_module_names_its_extra_when_torch_is_missing(tmp_path) -> None:
    (tmp_path / "torch.py").write_text("raise ImportError('No module named torch')\n")
    done = subprocess.run([sys.executable, "-c", "import tensor_conversions.torch"],
                          cwd=ROOT, env={"PYTHONPATH": str(tmp_path)}, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 1
    assert "pip install 'warp-buffer[torch]'" in done.stderr, done.stderr[-1500:]


def test_a_machine_without_a_compiler_is_told_what_to_install(tmp_path) -> None:
    """setuptools' generic build error named nothing the user could install."""
    env = dict(os.environ, CC="/bin/false")
    done = subprocess.run([sys.executable, "setup.py", "build_ext", "-b", str(tmp_path / "lib"),
                           "-t", str(tmp_path / "tmp"), "--force"], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode != 0
    assert "need a C compiler and Python's headers" in done.stderr, done.stderr[-2000:]
    assert "apt install gcc python3-dev" in done.stderr
