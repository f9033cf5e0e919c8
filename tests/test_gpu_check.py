"""benchmarks/gpu_check.py in its plumbing mode (no GPU): the install step (wheel parts, pip,
entry points), the child protocol, the stderr watch, the check runner and the table. Keeps the
one-call GPU check working where CI has no GPU."""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys
import time
import zipfile
from importlib import metadata

import pytest

from benchmarks import gpu_check

ROOT = pathlib.Path(__file__).resolve().parent.parent


def _wheel(directory: pathlib.Path, name: str = "wbprobe", payload: int = 0) -> pathlib.Path:
    """A minimal pure-Python wheel; ``payload`` random bytes make it large (incompressible)."""
    path = directory / f"{name}-0.1-py3-none-any.whl"
    info = f"{name}-0.1.dist-info"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as archive:
        archive.writestr(f"{name}/__init__.py", "VALUE = 42\n")
        if payload:
            archive.writestr(f"{name}/blob.bin", os.urandom(payload))
        archive.writestr(f"{info}/METADATA", f"Metadata-Version: 2.1\nName: {name}\nVersion: 0.1\n")
        archive.writestr(f"{info}/WHEEL", "Wheel-Version: 1.0\nGenerator: test\n"
                                          "Root-Is-Purelib: true\nTag: py3-none-any\n")
        archive.writestr(f"{info}/RECORD", "")
    return path


def test_split_and_reassemble_round_trip(tmp_path: pathlib.Path) -> None:
    source = tmp_path / "wheels"
    source.mkdir()
    big = _wheel(source, "wbbig", payload=300_000)
    small = _wheel(source, "wbsmall")
    parts = gpu_check.split_wheels(source, tmp_path / "parts", part_bytes=100_000)
    assert len(parts) >= 3
    assert all(sum(f.stat().st_size for f in p.iterdir()) <= 100_000 for p in parts)
    wheels, rebuilt = gpu_check.reassemble(parts, tmp_path / "out")
    assert rebuilt == [big.name]
    assert sorted(w.name for w in wheels) == sorted([big.name, small.name])
    assert (tmp_path / "out" / big.name).read_bytes() == big.read_bytes()


def test_reassemble_refuses_a_missing_or_damaged_part(tmp_path: pathlib.Path) -> None:
    source = tmp_path / "wheels"
    source.mkdir()
    big = _wheel(source, "wbbig", payload=250_000)
    parts = gpu_check.split_wheels(source, tmp_path / "parts", part_bytes=100_000)
    pieces = sorted(tmp_path.joinpath("parts").rglob(f"{big.name}.part*"))
    damaged = pieces[1].read_bytes()
    pieces[1].write_bytes(b"\0" + damaged[1:])
    with pytest.raises(RuntimeError, match="SHA-256"):
        gpu_check.reassemble(parts, tmp_path / "out1")
    pieces[1].unlink()
    with pytest.raises(RuntimeError, match="missing"):
        gpu_check.reassemble(parts, tmp_path / "out2")


def test_install_runs_pip_and_registers_the_project(tmp_path: pathlib.Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    wheels = tmp_path / "wheels"
    wheels.mkdir()
    _wheel(wheels)
    monkeypatch.setattr(sys, "path", list(sys.path))
    monkeypatch.setenv("PYTHONPATH", os.environ.get("PYTHONPATH", ""))
    target = tmp_path / "site"
    report = gpu_check.install(target, [wheels])
    assert report.wheels == ["wbprobe-0.1-py3-none-any.whl"]
    assert (target / "wbprobe" / "__init__.py").exists()
    assert "warp" in report.entry_points["rosidl_buffer.backends"]
    # The registered entry points are what the backend registry reads.
    [info] = target.glob("warp_buffer_gpu_check-*.dist-info")
    dist = metadata.PathDistribution(info)
    backends = {ep.name: ep.value for ep in dist.entry_points
                if ep.group == "rosidl_buffer.backends"}
    assert backends == {"warp": "warp_buffer_backend:WarpBufferBackend"}
    probe = subprocess.run([sys.executable, "-c", "import wbprobe; print(wbprobe.VALUE)"],
                           env={**os.environ, "PYTHONPATH": str(target)}, capture_output=True,
                           text=True, timeout=60)
    assert probe.stdout.strip() == "42"


def _ctx(tmp_path: pathlib.Path, gpu: bool = False) -> gpu_check.Context:
    return gpu_check.Context("cuda:0", gpu, tmp_path, lambda line: None, time.monotonic() + 60)


def test_runner_reports_pass_fail_skip_and_printed_cuda_errors(tmp_path: pathlib.Path) -> None:
    def prints_error(ctx: gpu_check.Context) -> None:
        os.write(2, b"Warp CUDA error 1: invalid argument\n")

    def skips(ctx: gpu_check.Context) -> None:
        raise gpu_check.Skip("not here")

    def fails(ctx: gpu_check.Context) -> None:
        gpu_check.need(False, "wrong bytes")

    def crashes(ctx: gpu_check.Context) -> None:
        raise KeyError("boom")

    checks = [
        gpu_check.Check("ok", lambda c: {"x": 1}, gpu=False),
        gpu_check.Check("err", prints_error, gpu=False),
        gpu_check.Check("err_expected", prints_error, gpu=False, cuda_errors_expected=True),
        gpu_check.Check("skips", skips, gpu=False),
        gpu_check.Check("fails", fails, gpu=False),
        gpu_check.Check("crashes", crashes, gpu=False),
        gpu_check.Check("needs_gpu", lambda c: None),
    ]
    results = {r.name: r for r in gpu_check.run_checks(checks, _ctx(tmp_path))}
    assert results["ok"].status == "PASS" and results["ok"].metrics == {"x": 1}
    assert results["err"].status == "FAIL" and "Warp CUDA error" in results["err"].reason
    assert results["err_expected"].status == "PASS"
    assert results["skips"].status == "SKIP" and results["skips"].reason == "not here"
    assert results["fails"].status == "FAIL" and results["fails"].reason == "wrong bytes"
    assert results["crashes"].status == "FAIL" and "KeyError" in results["crashes"].reason
    assert results["needs_gpu"].status == "SKIP"
    text = gpu_check.table(list(results.values()))
    assert text.splitlines()[-1] == "2 passed, 3 failed, 2 skipped"


def test_runner_stops_starting_checks_when_the_budget_is_spent(tmp_path: pathlib.Path) -> None:
    ctx = _ctx(tmp_path)
    ctx.deadline = time.monotonic()
    [result] = gpu_check.run_checks([gpu_check.Check("late", lambda c: None, gpu=False)], ctx)
    assert result.status == "SKIP" and "budget" in result.reason


def test_every_check_is_named_once_and_documented() -> None:
    names = [c.name for c in gpu_check.CHECKS]
    assert len(names) == len(set(names))
    assert all(c.doc for c in gpu_check.CHECKS)
    for required in ["capabilities", "copy_bytes", "stream_order", "reuse_hazard", "ipc_child",
                     "failure_injection", "forced_staging", "end_to_end", "tensor_conversions",
                     "benchmark", "teardown"]:
        assert required in names


def test_plumbing_mode_end_to_end(tmp_path: pathlib.Path) -> None:
    out = tmp_path / "out"
    env = {**os.environ, "OUT": str(out), "PYTHON": sys.executable}
    proc = subprocess.run(["bash", str(ROOT / "benchmarks" / "gpu_check.sh"), "--no-gpu"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    lines = proc.stdout.strip().splitlines()
    assert lines[-1].endswith("skipped") and " 0 failed" in lines[-1]
    report = json.loads((out / "gpu_check.json").read_text())
    assert report["mode"] == "plumbing"
    status = {r["name"]: r["status"] for r in report["results"]}
    assert status["install"] == status["child_protocol"] == status["stderr_watch"] == "PASS"
    assert {status[c.name] for c in gpu_check.CHECKS if c.gpu} == {"SKIP"}
    assert (out / "gpu_check.log").stat().st_size > 0
    assert (out / "console.log").exists()
    table_start = next(i for i, line in enumerate(lines) if line.startswith("check "))
    assert len(lines) - table_start == len(gpu_check.CHECKS) + 3  # header, rule, rows, counts


@pytest.mark.multiprocess
def test_cpu_rehearsal_of_a_node_check(tmp_path: pathlib.Path) -> None:
    """``--device cpu`` runs the Node/child checks on the cpu device: their child protocol,
    matching, CRC judging, explicit release and teardown stay working without a GPU."""
    out = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, "-m", "benchmarks.gpu_check", "--device", "cpu", "--quick", "--only",
         "ipc_child,teardown", "--out", str(out)],
        cwd=ROOT, capture_output=True, text=True, timeout=180)
    report = json.loads((out / "gpu_check.json").read_text())
    status = {r["name"]: (r["status"], r["reason"]) for r in report["results"]}
    assert status["ipc_child"][0] == "PASS", status
    assert status["teardown"][0] == "PASS", status
    assert proc.returncode == 0
