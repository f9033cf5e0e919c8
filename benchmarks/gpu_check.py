"""The GPU check: every CUDA path of the project, on one machine with an NVIDIA GPU, in one call.

Run ``benchmarks/gpu_check.sh`` (or ``python -m benchmarks.gpu_check``) from the repository root.
It installs what the machine lacks from wheels carried in ``.whl/`` (see :func:`install`), then
runs a list of named checks, each PASS, FAIL or SKIP with a reason, within a time budget
(default 450 s), prints a short table last and writes the full log and a JSON report to
``--out`` (default ``$OUT``, else ``benchmarks/results/gpu_check``). Exit status 1 if any check
failed.

Checks (see :data:`CHECKS`): device capabilities; ``copy_bytes`` against ``wp.copy`` (odd sizes,
offsets, bandwidth at 256 MiB); stream ordering (slow writer on stream A, reader on B, also under
a non-default torch stream); the reuse hazard; a child importing a CUDA export while the writer
is busy, twice, released and re-imported; failure injection (publisher gone, forged handles);
forced staging; end to end with ``Node`` (200 frames of 16 MiB to a warp and a cpu subscriber);
tensor_conversions with torch on the GPU; a short latency benchmark against ``cudaMemcpy``
device-to-host; the repository's cuda-marked tests (VMM, allocators); teardown. A check fails
on any ``Warp CUDA error`` its process printed, except the failure injections, whose errors are
expected.

Without a GPU (``--no-gpu``, or none found) it runs in plumbing mode: the install step into a
scratch directory, the child-process protocol, the stderr watch and the table, every GPU check
reported SKIP. ``tests/test_gpu_check.py`` runs that mode so CI keeps the script working.

The checks use the public APIs (``warp_buffer`` allocate/handles/``to_buffer``,
``buffer_pubsub.Node``, ``tensor_conversions.torch``) and :mod:`warp_buffer.cuda`, so they hold
across changes of the IPC core.

Carrying wheels to a machine without network (the warp-lang wheel, ~149 MB, is larger than one
call may carry): ``python -m benchmarks.gpu_check prepare DIR_OF_WHEELS`` splits them into parts
under ``.whl/`` (``.whl/part1`` ... of at most 56 MiB each), and prints the calls to make: each
call carries one part folder and copies it to ``/tmp/wb_wheel_parts`` on the (warm) machine;
the last one runs the check, which reassembles and verifies the parts (SHA-256) before
installing.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import gc
import hashlib
import json
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import traceback
import zlib
from collections.abc import Callable, Iterator
from typing import Any

ROOT = pathlib.Path(__file__).resolve().parent.parent
PART_BYTES = 56 << 20  # a call carries 64 MiB, the repository included
PARTS_STAGING = pathlib.Path("/tmp/wb_wheel_parts")
DEFAULT_BUDGET_S = 450.0
CUDA_ERROR = "Warp CUDA error"
TENSOR = "tensor_msgs/msg/ExperimentalTensor"
HEADER = 8


# =============================================================================== install
@dataclasses.dataclass
class InstallReport:
    target: str
    wheels: list[str]
    reassembled: list[str]
    entry_points: dict[str, list[str]]
    notes: list[str]


def split_wheels(source: pathlib.Path, dest: pathlib.Path, part_bytes: int = PART_BYTES) -> list[
        pathlib.Path]:
    """Copy the wheels of ``source`` into part folders ``dest/part1``, ``dest/part2`` ... of at
    most ``part_bytes`` each (first fit, largest first, so small wheels ride along with the last
    piece of a big one); a wheel larger than that is cut into ``NAME.whl.partK`` pieces with a
    ``NAME.whl.sha256`` beside the first. Returns the part folders."""
    parts: list[pathlib.Path] = []
    used: list[int] = []

    def folder(need: int) -> pathlib.Path:
        for index, size in enumerate(used):
            if size + need <= part_bytes:
                used[index] += need
                return parts[index]
        parts.append(dest / f"part{len(parts) + 1}")
        parts[-1].mkdir(parents=True, exist_ok=True)
        used.append(need)
        return parts[-1]

    for wheel in sorted(source.glob("*.whl"), key=lambda w: -w.stat().st_size):
        size = wheel.stat().st_size
        if size <= part_bytes:
            shutil.copy2(wheel, folder(size) / wheel.name)
            continue
        digest = hashlib.sha256(wheel.read_bytes()).hexdigest()
        with wheel.open("rb") as src:
            index = 0
            while chunk := src.read(part_bytes - 4096):
                index += 1
                target = folder(len(chunk) + (100 if index == 1 else 0))
                (target / f"{wheel.name}.part{index}").write_bytes(chunk)
                if index == 1:
                    (target / f"{wheel.name}.sha256").write_text(f"{digest} {size}\n")
    return parts


def reassemble(dirs: list[pathlib.Path], out: pathlib.Path) -> tuple[list[pathlib.Path], list[str]]:
    """Gather whole wheels and reassemble split ones from ``dirs`` into ``out``; a split wheel
    with a missing part or a wrong SHA-256 raises ``RuntimeError``. Returns (wheels, names of
    the reassembled ones)."""
    out.mkdir(parents=True, exist_ok=True)
    pieces: dict[str, dict[int, pathlib.Path]] = {}
    sums: dict[str, tuple[str, int]] = {}
    wheels: dict[str, pathlib.Path] = {}
    for directory in dirs:
        if not directory.is_dir():
            continue
        for path in sorted(directory.rglob("*")):
            name = path.name
            if name.endswith(".whl") and path.is_file():
                wheels.setdefault(name, path)
            elif ".whl.part" in name:
                base, _, number = name.rpartition(".part")
                pieces.setdefault(base, {})[int(number)] = path
            elif name.endswith(".whl.sha256"):
                digest, size = path.read_text().split()
                sums[name[: -len(".sha256")]] = (digest, int(size))
    rebuilt = []
    for base, parts in pieces.items():
        if base not in sums:
            raise RuntimeError(f"{base}: parts without their .sha256 file")
        numbers = sorted(parts)
        if numbers != list(range(1, len(numbers) + 1)):
            raise RuntimeError(f"{base}: parts {numbers} (one is missing: carry every part)")
        target = out / base
        digest = hashlib.sha256()
        with target.open("wb") as dst:
            for number in numbers:
                chunk = parts[number].read_bytes()
                digest.update(chunk)
                dst.write(chunk)
        want, size = sums[base]
        if digest.hexdigest() != want or target.stat().st_size != size:
            target.unlink()
            raise RuntimeError(f"{base}: reassembled wheel does not match its SHA-256")
        wheels[base] = target
        rebuilt.append(base)
    return sorted(wheels.values()), rebuilt


def _project_entry_points() -> dict[str, dict[str, str]]:
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    groups = {group: dict(entries) for group, entries in project.get("entry-points", {}).items()}
    groups["console_scripts"] = dict(project.get("scripts", {}))
    return groups


def register_project(target: pathlib.Path) -> dict[str, list[str]]:
    """Make the repository's packages and entry points (backends, interfaces) visible to
    ``importlib.metadata`` from ``target`` without building it: a ``.dist-info`` naming them,
    and a ``.pth`` file putting the repository root on the path."""
    groups = _project_entry_points()
    info = target / "warp_buffer_gpu_check-0.0.dist-info"
    info.mkdir(parents=True, exist_ok=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: warp-buffer-gpu-check\n"
                                   "Version: 0.0\n")
    lines = []
    for group, entries in groups.items():
        lines.append(f"[{group}]")
        lines += [f"{name} = {value}" for name, value in entries.items()]
        lines.append("")
    (info / "entry_points.txt").write_text("\n".join(lines))
    (target / "warp_buffer_repo.pth").write_text(str(ROOT) + "\n")
    return {group: sorted(entries) for group, entries in groups.items()}


def install(target: pathlib.Path, wheel_dirs: list[pathlib.Path] | None = None,
            pip: bool = True) -> InstallReport:
    """Install the carried wheels (``.whl/`` and ``/tmp/wb_wheel_parts``, split ones
    reassembled) into ``target`` with pip (no index, no dependencies), register the repository
    there, and put ``target`` first on ``sys.path``."""
    dirs = wheel_dirs if wheel_dirs is not None else [ROOT / ".whl", PARTS_STAGING]
    notes = []
    wheels, rebuilt = reassemble(dirs, target.parent / (target.name + "_wheels"))
    target.mkdir(parents=True, exist_ok=True)
    if wheels and pip:
        command = [sys.executable, "-m", "pip", "install", "-q", "--no-index", "--no-deps",
                   "--no-compile", "--no-cache-dir", "--upgrade", "--target", str(target),
                   *map(str, wheels)]
        result = subprocess.run(command, capture_output=True, text=True, timeout=300)
        if result.returncode != 0:
            raise RuntimeError(f"pip install failed: {result.stderr[-2000:]}")
    elif not wheels:
        notes.append("no wheels carried: using what the machine has")
    groups = register_project(target)
    if str(target) not in sys.path:
        sys.path.insert(0, str(target))
        import site

        site.addsitedir(str(target))  # reads the .pth
    os.environ["PYTHONPATH"] = os.pathsep.join(
        p for p in [str(target), str(ROOT), os.environ.get("PYTHONPATH", "")] if p)
    import importlib

    importlib.invalidate_caches()
    return InstallReport(str(target), [w.name for w in wheels], rebuilt, groups, notes)


# =============================================================================== checks
@dataclasses.dataclass
class Result:
    name: str
    status: str  # PASS, FAIL, SKIP
    reason: str = ""
    seconds: float = 0.0
    metrics: dict[str, Any] = dataclasses.field(default_factory=dict)


class Skip(Exception):
    """Raised by a check that cannot run here (the reason is reported)."""


class Fail(AssertionError):
    """Raised by a check whose outcome is wrong."""


def need(ok: bool, message: str) -> None:
    if not ok:
        raise Fail(message)


@dataclasses.dataclass
class Check:
    name: str
    run: Callable[[Context], dict[str, Any] | None]
    gpu: bool = True
    cuda_errors_expected: bool = False  # failure injection prints CUDA errors on purpose
    doc: str = ""


@dataclasses.dataclass
class Context:
    device: str
    gpu: bool
    out: pathlib.Path
    log: Callable[[str], None]
    deadline: float
    children: list[subprocess.Popen] = dataclasses.field(default_factory=list)
    baseline_free: int | None = None
    domain: int = 0
    quick: bool = False

    def left(self) -> float:
        return self.deadline - time.monotonic()


@contextlib.contextmanager
def capture_stderr(path: pathlib.Path) -> Iterator[pathlib.Path]:
    """Send this process's fd 2 (native code's stderr too) to ``path`` while the block runs."""
    sys.stderr.flush()
    saved = os.dup(2)
    with path.open("wb") as sink:
        os.dup2(sink.fileno(), 2)
        try:
            yield path
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)


def run_checks(checks: list[Check], ctx: Context) -> list[Result]:
    results = []
    for check in checks:
        if check.gpu and not ctx.gpu:
            results.append(Result(check.name, "SKIP", "no GPU (plumbing mode)"))
            continue
        if ctx.left() <= 5:
            results.append(Result(check.name, "SKIP", "time budget spent"))
            continue
        start = time.monotonic()
        stderr_path = ctx.out / f"stderr_{check.name}.txt"
        ctx.log(f"--- {check.name}: {check.doc}")
        try:
            with capture_stderr(stderr_path):
                metrics = check.run(ctx) or {}
            result = Result(check.name, "PASS", "", metrics=metrics)
        except Skip as exc:
            result = Result(check.name, "SKIP", str(exc))
        except Fail as exc:
            result = Result(check.name, "FAIL", str(exc))
        except Exception as exc:  # noqa: BLE001 - any error is a failed check
            result = Result(check.name, "FAIL", f"{type(exc).__name__}: {exc}")
            ctx.log(traceback.format_exc())
        result.seconds = time.monotonic() - start
        for proc in ctx.children:  # a failed check may leave its children: reap them now
            if proc.poll() is None:
                proc.kill()
                proc.wait()
                ctx.log(f"killed child {proc.pid} left by {check.name}")
        errors = stderr_path.read_text(errors="replace") if stderr_path.exists() else ""
        if errors.strip():
            ctx.log(f"[stderr of {check.name}]\n{errors}")
        if CUDA_ERROR in errors and not check.cuda_errors_expected and result.status != "SKIP":
            first = next(line for line in errors.splitlines() if CUDA_ERROR in line)
            result.status, result.reason = "FAIL", f"printed: {first[:160]}"
        ctx.log(f"{result.status} {check.name} ({result.seconds:.1f} s) {result.reason} "
                f"{json.dumps(result.metrics, default=str)}")
        results.append(result)
    return results


def table(results: list[Result]) -> str:
    """The short table printed last: one line per check."""
    width = max([len(r.name) for r in results] + [5])
    lines = [f"{'check':<{width}}  status  time    detail", "-" * (width + 40)]
    for r in results:
        detail = r.reason or ", ".join(f"{k}={v}" for k, v in list(r.metrics.items())[:4])
        lines.append(f"{r.name:<{width}}  {r.status:<6}  {r.seconds:5.1f}s  {detail[:110]}")
    counts = {s: sum(r.status == s for r in results) for s in ("PASS", "FAIL", "SKIP")}
    lines.append(f"{counts['PASS']} passed, {counts['FAIL']} failed, {counts['SKIP']} skipped")
    return "\n".join(lines)


# =============================================================================== plumbing checks
def check_install(ctx: Context) -> dict[str, Any]:
    from importlib import metadata

    names = {ep.name for ep in metadata.entry_points(group="rosidl_buffer.backends")}
    need("warp" in names, f"the 'warp' backend entry point is not visible (found {names})")
    import warp_buffer  # noqa: F401
    import warp_buffer.cuda  # noqa: F401

    return {"backends": sorted(names)}


def check_child_protocol(ctx: Context) -> dict[str, Any]:
    child = spawn(ctx, "echo", {"value": 42})
    result = finish(ctx, child, timeout=60)
    need(result.get("value") == 42, f"child answered {result}")
    return {"child_pid": child.pid}


def check_stderr_watch(ctx: Context) -> dict[str, Any]:
    probe = Check("probe", lambda c: os.write(2, f"{CUDA_ERROR} 999: probe\n".encode()) and None,
                  gpu=False)
    quiet = Context(ctx.device, ctx.gpu, ctx.out, lambda line: None, time.monotonic() + 60)
    [result] = run_checks([probe], quiet)
    need(result.status == "FAIL" and CUDA_ERROR in result.reason,
         f"a printed CUDA error was not caught: {result}")
    return {}


# =============================================================================== child processes
def spawn(ctx: Context, role: str, args: dict[str, Any], env: dict[str, str] | None = None
          ) -> subprocess.Popen:
    """Start ``python -m benchmarks.gpu_check child ROLE`` (JSON args); it prints ``READY`` and
    later one ``RESULT <json>`` line."""
    child_env = dict(os.environ)
    child_env["PYTHONPATH"] = os.pathsep.join(
        p for p in [str(ROOT), child_env.get("PYTHONPATH", "")] if p)
    child_env.update(env or {})
    proc = subprocess.Popen(
        [sys.executable, "-m", "benchmarks.gpu_check", "child", role, json.dumps(args)],
        cwd=ROOT, env=child_env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True)
    ctx.children.append(proc)
    return proc


def wait_ready(proc: subprocess.Popen, timeout: float = 90, word: str = "READY") -> None:
    """Read the child's stdout up to the line ``word`` (``READY``: its endpoints exist;
    ``MATCHED``: it discovered the publisher)."""
    deadline = time.monotonic() + timeout
    line = ""
    while time.monotonic() < deadline:
        line = _readline(proc, max(0.1, deadline - time.monotonic()))
        if not line or line.strip() == word:
            break
    if line.strip() != word:
        raise Fail(f"child {proc.pid} did not say {word}: {line!r} {_drain_stderr(proc)}")


def tell(proc: subprocess.Popen, line: str) -> None:
    proc.stdin.write(line + "\n")
    proc.stdin.flush()


def _readline(proc: subprocess.Popen, timeout: float) -> str:
    box: list[str] = []
    reader = threading.Thread(target=lambda: box.append(proc.stdout.readline()), daemon=True)
    reader.start()
    reader.join(timeout)
    return box[0] if box else ""


def _drain_stderr(proc: subprocess.Popen) -> str:
    if proc.poll() is None:
        return ""
    return (proc.stderr.read() or "")[-1500:]


def finish(ctx: Context, proc: subprocess.Popen, timeout: float = 120) -> dict[str, Any]:
    """Tell the child to stop, read its RESULT, reap it; its stderr goes to the log (and a
    ``Warp CUDA error`` there is re-printed on ours, so the check sees it)."""
    try:
        proc.stdin.write("stop\n")
        proc.stdin.flush()
    except (BrokenPipeError, OSError):
        pass
    line = ""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = _readline(proc, max(0.1, deadline - time.monotonic()))
        if not line or line.startswith("RESULT "):
            break
    try:
        proc.wait(timeout=max(1.0, deadline - time.monotonic()))
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    errors = proc.stderr.read() or ""
    if errors.strip():
        ctx.log(f"[child {proc.pid} stderr]\n{errors[-4000:]}")
        for bad in (ln for ln in errors.splitlines() if CUDA_ERROR in ln):
            os.write(2, (bad + "\n").encode())
    if not line.startswith("RESULT "):
        raise Fail(f"child {proc.pid} gave no result (exit {proc.returncode}): {errors[-600:]}")
    return json.loads(line[len("RESULT "):])


def _emit(text: str) -> None:
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


def _stop_event(timeout: float) -> threading.Event:
    stop = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.readline(), stop.set()), daemon=True).start()
    timer = threading.Timer(timeout, stop.set)
    timer.daemon = True
    timer.start()
    return stop


def child_main(role: str, args: dict[str, Any]) -> int:
    import warp as wp

    wp.config.quiet = True  # stdout carries the protocol
    handler = CHILD_ROLES[role]
    result = handler(args)
    _emit("RESULT " + json.dumps(result, default=str))
    return 0


def _child_echo(args: dict[str, Any]) -> dict[str, Any]:
    _emit("READY")
    _stop_event(30).wait()
    return {"value": args.get("value")}


# =============================================================================== GPU helpers
_kernels: dict[str, Any] = {}


def kernels() -> dict[str, Any]:
    """Warp kernels of the checks (defined on first use: plumbing mode never compiles them)."""
    if _kernels:
        return _kernels
    import warp as wp

    @wp.kernel
    def fill_pattern(out: wp.array(dtype=wp.uint8), seed: int, index: wp.int64, spins: int):
        """Byte j = (7 j + seed) mod 256, bytes 0..7 = index; ``spins`` makes it slow."""
        j = wp.tid()
        acc = float(j)
        for _ in range(spins):
            acc = acc * 0.999 + 1.0
        value = (j * 7 + seed) & 255
        if j < 8:
            value = int((index >> wp.int64(8 * j)) & wp.int64(255))
        if acc < -1.0:  # never true: keeps the spin loop alive
            value = 0
        out[j] = wp.uint8(value)

    @wp.kernel
    def slow_copy(dst: wp.array(dtype=wp.uint8), src: wp.array(dtype=wp.uint8), spins: int):
        """dst[j] = src[j] after a spin: a reader still busy when the block is re-leased."""
        j = wp.tid()
        acc = float(j)
        for _ in range(spins):
            acc = acc * 0.999 + 1.0
        value = src[j]
        if acc < -1.0:
            value = wp.uint8(0)
        dst[j] = value

    @wp.kernel
    def slow_fill(out: wp.array(dtype=wp.uint8), value: int, spins: int):
        """out[j] = value after a spin: a writer still busy."""
        j = wp.tid()
        acc = float(j)
        for _ in range(spins):
            acc = acc * 0.999 + 1.0
        v = value
        if acc < -1.0:
            v = 0
        out[j] = wp.uint8(v)

    _kernels.update(fill_pattern=fill_pattern, slow_copy=slow_copy, slow_fill=slow_fill)
    return _kernels


def expected_crc(nbytes: int, seed: int, index: int) -> int:
    import numpy as np

    data = ((np.arange(nbytes, dtype=np.uint64) * 7 + seed) & 255).astype(np.uint8)
    data[:HEADER] = np.frombuffer(int(index).to_bytes(8, "little"), np.uint8)[: min(HEADER, nbytes)]
    return zlib.crc32(data.tobytes())


def frame_crc(data: Any) -> tuple[int, int]:
    """(index from the header, CRC of the whole frame) of host bytes."""
    raw = bytes(memoryview(data).cast("B"))
    return int.from_bytes(raw[:HEADER], "little"), zlib.crc32(raw)


def _write_frame(buffer: Any, seed: int, index: int, spins: int, stream: Any = None) -> None:
    import warp as wp
    import warp_buffer

    with warp_buffer.from_output_buffer(buffer, stream=stream) as out:
        wp.launch(kernels()["fill_pattern"], dim=out.array.shape[0],
                  inputs=[out.array, seed, wp.int64(index), spins], device=out.array.device,
                  stream=out.stream)


def _host_bytes(buffer: Any, stream: Any = None) -> Any:
    import warp_buffer

    with warp_buffer.from_input_buffer(buffer, stream=stream) as view:
        return view.array.numpy() if stream is None else _to_host(view.array, stream)


def _to_host(array: Any, stream: Any) -> Any:
    import numpy as np
    import warp as wp

    host = wp.empty(array.shape[0], dtype=wp.uint8, device="cpu", pinned=True)
    wp.copy(host, array, stream=stream)
    wp.synchronize_stream(stream)
    return np.array(host.numpy(), copy=True)


def _need_cuda(ctx: Context) -> None:
    if not ctx.device.startswith("cuda"):
        raise Skip("needs a CUDA device (cpu rehearsal)")


def spins_for(device_name: str, nbytes: int, target_ms: float = 60.0) -> int:
    """Spin count that makes ``fill_pattern`` (and ``slow_fill``/``slow_copy``, the same loop)
    over ``nbytes`` take about ``target_ms`` on ``device_name`` (1 on cpu)."""
    import warp as wp

    if not device_name.startswith("cuda"):
        return 1
    device = wp.get_device(device_name)
    probe = wp.empty(nbytes, dtype=wp.uint8, device=device)
    spins = 256
    for _ in range(10):
        start, end = wp.Event(device, enable_timing=True), wp.Event(device, enable_timing=True)
        stream = device.stream
        stream.record_event(start)
        wp.launch(kernels()["fill_pattern"], dim=nbytes, inputs=[probe, 1, wp.int64(0), spins],
                  device=device)
        stream.record_event(end)
        wp.synchronize_stream(stream)
        ms = wp.get_event_elapsed_time(start, end)
        if ms >= target_ms / 4:
            return max(1, int(spins * target_ms / max(ms, 1e-3)))
        spins *= 4
    return spins


# =============================================================================== GPU checks
def check_capabilities(ctx: Context) -> dict[str, Any]:
    _need_cuda(ctx)
    import warp as wp

    from warp_buffer import cuda

    wp.init()
    need(wp.get_cuda_device_count() > 0, "no CUDA device")
    caps = cuda.capabilities(ctx.device)
    ctx.log(json.dumps(dataclasses.asdict(caps)))
    ctx.baseline_free = wp.get_device(ctx.device).free_memory
    # The wired core: peers are told the device by UUID (what the exporter matches, MIG-safe),
    # and a pool block is IPC-exportable whatever allocator the device uses.
    from warp_buffer_backend.backend import WarpBufferBackend, parse_metadata

    meta = parse_metadata(WarpBufferBackend().get_backend_metadata())
    need(caps.uuid in meta.cuda_uuids, f"the backend metadata does not advertise {caps.uuid}")
    from warp_buffer.buffer_impl import WarpBufferImpl

    from warp_buffer import pool

    block = WarpBufferImpl.allocate(4096, ctx.device).block
    if caps.vmm and caps.ipc:  # VMM blocks where the device exports POSIX fds
        need(isinstance(block, pool.VmmBlock), f"VMM is supported but the pool made a "
             f"{type(block).__name__} ({pool._vmm_refused.get(ctx.device)})")
    else:
        need(cuda.is_ipc_allocation(block.storage), "a pool block is not a whole "
             "default-allocator allocation (CUDA IPC cannot export it)")
    return {"blocks": type(block).__name__, "ipc": caps.ipc, "mempool": caps.mempool_supported,
            "vmm": caps.vmm,
            "uuid": caps.uuid, "name": caps.name, "advertised": sorted(meta.cuda_uuids),
            "driver": wp._src.context.runtime.driver_version}


def check_copy_bytes(ctx: Context) -> dict[str, Any]:
    _need_cuda(ctx)
    import numpy as np
    import warp as wp

    from warp_buffer import kernels as wk

    device = wp.get_device(ctx.device)
    rng = np.random.default_rng(5)
    for nbytes in [1, 15, 16, 17, 4095, 4099, (1 << 20) + 1, (7 << 20) + 13]:
        for src_off, dst_off in [(0, 0), (1, 0), (0, 3), (7, 9), (16, 32)]:
            data = rng.integers(0, 256, nbytes + 64, dtype=np.uint8)
            src = wp.array(data, dtype=wp.uint8, device=device)
            dst = wp.zeros(nbytes + 64, dtype=wp.uint8, device=device)
            ref = wp.zeros(nbytes + 64, dtype=wp.uint8, device=device)
            wk.copy_bytes(dst[dst_off:dst_off + nbytes], src[src_off:src_off + nbytes])
            wp.copy(ref, src, dest_offset=dst_off, src_offset=src_off, count=nbytes)
            need(np.array_equal(dst.numpy(), ref.numpy()),
                 f"copy_bytes differs from wp.copy: {nbytes} B, +{src_off} -> +{dst_off}")
    nbytes = 256 << 20
    src = wp.empty(nbytes, dtype=wp.uint8, device=device)
    dst = wp.empty(nbytes, dtype=wp.uint8, device=device)
    times = {}
    for name, fn in [("copy_bytes", lambda: wk.copy_bytes(dst, src)),
                     ("wp.copy", lambda: wp.copy(dst, src))]:
        fn()
        start, end = wp.Event(device, enable_timing=True), wp.Event(device, enable_timing=True)
        device.stream.record_event(start)
        for _ in range(20):
            fn()
        device.stream.record_event(end)
        wp.synchronize_device(device)
        times[name] = wp.get_event_elapsed_time(start, end) / 20
    gbps = {k: 2 * nbytes / (v / 1e3) / 1e9 for k, v in times.items()}
    ratio = gbps["copy_bytes"] / gbps["wp.copy"]
    need(ratio >= 0.9, f"copy_bytes at 256 MiB is {ratio:.2f}x wp.copy (goal >= 0.9)")
    return {"ratio_256MiB": round(ratio, 3), "copy_bytes_GBps": round(gbps["copy_bytes"]),
            "wp_copy_GBps": round(gbps["wp.copy"])}


def check_stream_order(ctx: Context) -> dict[str, Any]:
    _need_cuda(ctx)
    import warp as wp

    import warp_buffer

    device = wp.get_device(ctx.device)
    nbytes = 16 << 20
    spins = spins_for(ctx.device, nbytes)
    a, b = wp.Stream(device), wp.Stream(device)
    buffer = warp_buffer.allocate_buffer(nbytes, ctx.device)
    _write_frame(buffer, 3, 1, spins, stream=a)  # slow writer on A, handle released at once
    _, crc = frame_crc(_host_bytes(buffer, stream=b))  # reader on B
    need(crc == expected_crc(nbytes, 3, 1), "reader on stream B saw a half-written frame")
    metrics = {"spins": spins}
    try:
        import torch
    except ImportError as exc:
        raise Skip(f"warp streams ordered; torch missing for the torch-stream half: {exc}")
    s = torch.cuda.Stream(device=device.ordinal)
    with torch.cuda.stream(s):  # torch writes on a non-default stream
        torch.cuda._sleep(int(1e8))  # ~50-100 ms of GPU time before the write
        tensor = torch.full((nbytes,), 9, dtype=torch.uint8, device=f"cuda:{device.ordinal}")
        buffer = warp_buffer.allocate_buffer(nbytes, ctx.device)
        with warp_buffer.from_output_buffer(buffer) as out:
            warp_buffer.to_buffer(tensor, out)
    data = _host_bytes(buffer, stream=b)
    need(int(data.min()) == 9 == int(data.max()),
         "a write made under torch.cuda.stream(s) was read before it completed")
    metrics["torch_stream"] = "ordered"
    return metrics


def check_reuse_hazard(ctx: Context) -> dict[str, Any]:
    _need_cuda(ctx)
    import numpy as np
    import warp as wp

    import warp_buffer

    device = wp.get_device(ctx.device)
    nbytes = 16 << 20
    spins = spins_for(ctx.device, nbytes, target_ms=100)
    reader_stream, writer_stream = wp.Stream(device), wp.Stream(device)
    first = warp_buffer.allocate_buffer(nbytes, ctx.device)
    _write_frame(first, 1, 1, 1, stream=writer_stream)
    out = wp.zeros(nbytes, dtype=wp.uint8, device=device)
    with warp_buffer.from_input_buffer(first, stream=reader_stream) as view:
        wp.launch(kernels()["slow_copy"], dim=nbytes, inputs=[out, view.array, spins],
                  device=device, stream=reader_stream)  # a slow reader
        first_ptr = view.ptr
    del view, first
    gc.collect()
    second = warp_buffer.allocate_buffer(nbytes, ctx.device)  # may re-lease the same block
    with warp_buffer.from_output_buffer(second, stream=writer_stream) as handle:
        reused = handle.ptr == first_ptr
        wp.launch(kernels()["fill_pattern"], dim=nbytes, inputs=[handle.array, 2, wp.int64(2), 1],
                  device=device, stream=writer_stream)
    wp.synchronize_device(device)
    got = zlib.crc32(np.ascontiguousarray(out.numpy()).tobytes())
    need(got == expected_crc(nbytes, 1, 1),
         f"the slow reader saw the next write (block re-leased: {reused})")
    return {"block_reused": reused, "spins": spins}


def _node_env(ctx: Context) -> dict[str, Any]:
    ctx.domain += 1
    return {"domain": 100 + (os.getpid() % 50) * 3 + ctx.domain,
            "topic": f"/gpu_check_{os.getpid()}_{ctx.domain}"}


def _publish_frames(ctx: Context, where: dict[str, Any], frames: list[tuple[int, int, int]],
                    subscribers: list[subprocess.Popen], spins: int = 1, repeat: int = 1,
                    depth: int = 10, interval: float = 0.0, timeout: float = 120
                    ) -> list[dict[str, Any]]:
    """Publish (nbytes, seed, index) frames as warp buffers on the GPU (writer still busy when
    published with ``spins``), each ``repeat`` times, once every subscriber child matched; then
    collect every subscriber's result before the publisher's node closes (a subscriber still
    taking queued frames needs its publisher's endpoint info). Returns the results."""
    from buffer_pubsub import Node
    from rosidl_buffer.messages import get_message_type

    import warp_buffer

    tensor = get_message_type(TENSOR)
    with Node(f"gpu_check_pub_{os.getpid()}", domain_id=where["domain"]) as node:
        pub = node.create_publisher(tensor, where["topic"], depth=depth)
        need(pub.wait_for_subscriptions(len(subscribers), timeout=60), "subscribers not matched")
        for child in subscribers:
            wait_ready(child, 60, "MATCHED")
        for nbytes, seed, index in frames:
            buffer = warp_buffer.allocate_buffer(nbytes, ctx.device)
            _write_frame(buffer, seed, index, spins)
            for _ in range(repeat):
                pub.publish(tensor(dtype_code=1, dtype_bits=8, dtype_lanes=1,
                                   shape=[nbytes], data=buffer))
            if interval:
                time.sleep(interval)
        return [finish(ctx, child, timeout) for child in subscribers]


def _child_subscriber(args: dict[str, Any]) -> dict[str, Any]:
    """Subscribe, verify every frame's CRC, optionally release some buffers explicitly."""
    from buffer_pubsub import Node
    from rosidl_buffer.messages import get_message_type

    tensor = get_message_type(TENSOR)
    records: list[dict[str, Any]] = []
    crcs: dict[tuple[int, int], int] = {}
    with Node(f"gpu_check_sub_{os.getpid()}", domain_id=args["domain"]) as node:
        def on_msg(msg: Any, info: Any) -> None:
            if not records and args.get("hold_first_s"):
                time.sleep(args["hold_first_s"])  # let the publisher exit meanwhile
            buffer = msg.data
            record: dict[str, Any] = {"route": info.route, "backend": buffer.get_backend_type()}
            try:
                impl = buffer.get_impl()
                record["device"] = str(getattr(impl, "device", "cpu"))
                data = buffer.to_numpy()
                index, crc = frame_crc(data)
                nbytes, seed = int(data.shape[0]), int(args["seeds"][str(index)])
                key = (nbytes, index)
                if key not in crcs:
                    crcs[key] = expected_crc(nbytes, seed, index)
                record.update(index=index, ok=crc == crcs[key])
                if args.get("release") and hasattr(buffer, "release"):
                    buffer.release()
                    record["released"] = True
            except Exception as exc:  # noqa: BLE001 - reported to the parent
                from warp_buffer.errors import WarpBufferError

                record["error"] = f"{type(exc).__name__}: {exc}"
                record["typed"] = isinstance(exc, WarpBufferError)
            records.append(record)

        sub = node.create_subscription(tensor, args["topic"], on_msg, depth=args.get("depth", 10),
                                       acceptable_buffer_backends=args["accept"], with_info=True)
        _emit("READY")
        sub.wait_for_publishers(1, timeout=60)
        _emit("MATCHED")
        # "stop" means the publisher is done: keep taking what is still queued (up to
        # drain_s more), so a subscriber slower than its publisher is judged on every frame.
        stop = _stop_event(args.get("timeout", 200))
        drain_until = None
        while len(records) + sub.counters.errors < args["expect"]:
            if stop.is_set():
                drain_until = drain_until or time.monotonic() + args.get("drain_s", 30)
                if time.monotonic() > drain_until:
                    break
            time.sleep(0.01)
        time.sleep(0.2)
        counters = vars(sub.counters).copy()
        last_error = repr(sub.last_error) if sub.last_error is not None else ""
    return {"records": records, "counters": counters, "last_error": last_error}


#: A same-host descriptor delivery: over Zenoh's _buf/<gid> route or the iceoryx2 fast lane.
_SAME_HOST = ("buffer", "lane")


def _judge_subscriber(result: dict[str, Any], expect: int, route: str | tuple[str, ...] | None,
                      device: str | None) -> dict[str, Any]:
    records = result["records"]
    bad = [r for r in records if not r.get("ok")]
    need(not bad, f"{len(bad)} of {len(records)} frames wrong: {bad[:2]}")
    need(len(records) == expect, f"received {len(records)} of {expect}")
    need(result["counters"].get("errors", 0) == 0, f"subscription errors: {result['counters']} "
                                                    f"{result['last_error']}")
    routes = sorted({r["route"] for r in records})
    devices = sorted({r.get("device", "") for r in records})
    if route is not None:
        allowed = (route,) if isinstance(route, str) else route  # one route, any of these
        need(len(routes) == 1 and routes[0] in allowed,
             f"routes {routes}, expected {' or '.join(allowed)}")
    if device is not None:
        need(all(d.startswith(device) for d in devices), f"devices {devices}, expected {device}")
    return {"routes": routes, "devices": devices}


def check_ipc_child(ctx: Context) -> dict[str, Any]:
    where = _node_env(ctx)
    nbytes = 4 << 20
    spins = spins_for(ctx.device, nbytes, target_ms=80)
    frames = [(nbytes, 10 + i, i) for i in range(4)]
    seeds = {str(i): s for _, s, i in frames}
    child = spawn(ctx, "subscriber", {**where, "accept": "warp", "expect": 8, "seeds": seeds,
                                      "release": True})
    wait_ready(child)
    # Each frame published twice (imported twice), its writer still busy; the subscriber
    # releases each buffer explicitly and imports the next (release and re-import).
    [result] = _publish_frames(ctx, where, frames, [child], spins=spins, repeat=2)
    metrics = _judge_subscriber(result, 8, _SAME_HOST, ctx.device.split(":")[0])
    metrics["released"] = sum(bool(r.get("released")) for r in result["records"])
    return metrics


def _forged_handles(ctx: Context) -> bool:
    """Forged CUDA IPC handles raise StaleBufferError; returns whether Warp's own
    ``from_ipc_handle`` hands out (fresh) memory for one, for the record."""
    import warp as wp

    from warp_buffer import cuda
    from warp_buffer.errors import StaleBufferError

    device = wp.get_device(ctx.device)
    forged = os.urandom(cuda.IPC_HANDLE_SIZE)
    for opener in (lambda: cuda.open_ipc_memory(forged, 4096, device),
                   lambda: cuda.open_ipc_event(forged, device)):
        try:
            opener()
        except StaleBufferError:
            pass
        else:
            raise Fail("a forged CUDA IPC handle was opened without an error")
    try:
        return bool(wp.from_ipc_handle(forged, wp.uint8, (4096,), device=device).ptr)
    except Exception:  # noqa: BLE001
        return False


def check_failure_injection(ctx: Context) -> dict[str, Any]:
    warp_gives_fresh = None
    if ctx.device.startswith("cuda"):
        warp_gives_fresh = _forged_handles(ctx)
    # Publisher gone: a child publishes two frames and exits while a child subscriber still
    # holds them unread (its callback sleeps first). Legacy CUDA IPC memory dies with its
    # exporter: a typed error is fine, wrong bytes or an untyped error are not. (In children,
    # so a CUDA error cannot poison this process's context.)
    where = _node_env(ctx)
    nbytes = 1 << 20
    seeds = {"0": 5, "1": 5}
    sub = spawn(ctx, "subscriber", {**where, "accept": "warp", "expect": 2, "seeds": seeds,
                                    "hold_first_s": 3.0, "timeout": 60})
    pub = spawn(ctx, "publish_and_exit", {**where, "nbytes": nbytes, "count": 2,
                                          "device": ctx.device})
    wait_ready(sub)
    wait_ready(pub)
    wait_ready(sub, 60, "MATCHED")
    tell(pub, "go")
    finish(ctx, pub, timeout=60)
    result = finish(ctx, sub, timeout=90)
    records = result["records"]
    wrong = [r for r in records if "ok" in r and not r["ok"]]
    need(not wrong, f"bytes delivered after the publisher exited are wrong: {wrong}")
    untyped = [r for r in records if "error" in r and not r.get("typed")]
    need(not untyped, f"untyped errors after the publisher exited: {untyped}")
    outcome = sorted({"data" if r.get("ok") else "typed_error" for r in records})
    if result["counters"].get("errors"):
        need("Error" in result["last_error"], f"counted error {result['last_error']}")
        outcome.append("counted_error")
    return {"after_exit": outcome, "warp_from_ipc_handle_forged_gives_memory": warp_gives_fresh}


def _child_publish_and_exit(args: dict[str, Any]) -> dict[str, Any]:
    from buffer_pubsub import Node
    from rosidl_buffer.messages import get_message_type

    import warp_buffer

    tensor = get_message_type(TENSOR)
    with Node(f"gpu_check_gone_{os.getpid()}", domain_id=args["domain"]) as node:
        pub = node.create_publisher(tensor, args["topic"], depth=10)
        pub.wait_for_subscriptions(1, timeout=60)
        _emit("READY")
        sys.stdin.readline()  # "go": the subscriber has discovered us
        for index in range(args["count"]):
            buffer = warp_buffer.allocate_buffer(args["nbytes"], args["device"])
            _write_frame(buffer, 5, index, 1)
            pub.publish(tensor(dtype_code=1, dtype_bits=8, dtype_lanes=1, shape=[args["nbytes"]],
                               data=buffer))
        time.sleep(0.5)
    return {"published": args["count"]}


def check_vmm(ctx: Context) -> dict[str, Any]:
    """A child publishes a pool VMM block; another child imports it (its fd over the session's
    hand-off socket), reads it (CRC) and has a write kernel through it refused; we import it,
    the publisher exits, and our import still reads the same bytes, while the gone session's
    cached imports are dropped at once."""
    _need_cuda(ctx)
    from warp_buffer import cuda, descriptor, ipc

    if not cuda.vmm_supported(ctx.device):
        raise Skip("no VMM with POSIX fd export here: CUDA blocks use legacy CUDA IPC")
    nbytes, seed = 4 << 20, 21
    pub = spawn(ctx, "vmm_publish", {"device": ctx.device, "nbytes": nbytes, "seed": seed})
    line = _readline(pub, 120)
    need(line.startswith("DESC "), f"the publisher said {line!r} {_drain_stderr(pub)}")
    hexed = line.split()[1].strip()
    wait_ready(pub)
    exported = descriptor.unpack(bytes.fromhex(hexed))
    need(exported.kind == descriptor.KIND_CUDA_VMM, f"exported as kind {exported.kind}, not VMM")
    expected = expected_crc(nbytes, seed, 0)
    writer = spawn(ctx, "vmm_import", {"descriptor": hexed, "nbytes": nbytes})
    other = finish(ctx, writer, timeout=120)
    need(other["crc"] == expected, f"the child read CRC {other['crc']}, not {expected}")
    need(other["refused"], "a write kernel through a read-only VMM import was not refused")
    imported = ipc.import_buffer(exported)
    key = (exported.owner_pid, exported.session)
    before = frame_crc(imported.to_cpu().view())[1]
    finish(ctx, pub)  # the publisher exits (clean exit: it closes its hand-off connections)
    deadline = time.monotonic() + 5
    while any(k[0] == key for k in ipc._cuda_imports._strong["memory"]):
        need(time.monotonic() < deadline, "the gone session's cached imports were not dropped")
        time.sleep(0.05)
    after = frame_crc(imported.to_cpu().view())[1]
    imported.release()
    cuda.flush_releases(10)
    need(before == after == expected,
         f"CRC before/after the publisher exited {before}/{after}, expected {expected}")
    return {"child_crc_ok": True, "write_refused": True, "read_after_exit": True}


def _child_vmm_publish(args: dict[str, Any]) -> dict[str, Any]:
    import warp as wp

    import warp_buffer
    from warp_buffer import descriptor, ipc

    device = wp.get_device(args["device"])
    buffer = warp_buffer.allocate_buffer(args["nbytes"], device.alias)
    _write_frame(buffer, args["seed"], 0, 1)
    exported = ipc.export_buffer(buffer, peer_device_uuids={device.uuid})
    _emit("DESC " + descriptor.pack(exported).hex())
    _emit("READY")
    _stop_event(120).wait()
    return {"kind": exported.kind}


def _child_vmm_import(args: dict[str, Any]) -> dict[str, Any]:
    import warp as wp

    from warp_buffer import descriptor, ipc

    impl = ipc.import_buffer(descriptor.unpack(bytes.fromhex(args["descriptor"])))
    crc = frame_crc(impl.to_cpu().view())[1]
    target = wp.array(ptr=impl.array.ptr, dtype=wp.uint8, shape=(args["nbytes"],),
                      device=impl.array.device)
    refused = False
    try:  # a kernel writing through the read-only mapping must fault (this child's context)
        wp.launch(kernels()["slow_fill"], dim=args["nbytes"], inputs=[target, 7, 1],
                  device=target.device)
        wp.synchronize_device(target.device)
    except Exception:  # noqa: BLE001 - the expected outcome
        refused = True
    return {"crc": crc, "refused": refused, "device": str(impl.device)}


def check_forced_staging(ctx: Context) -> dict[str, Any]:
    _need_cuda(ctx)
    where = _node_env(ctx)
    nbytes = 4 << 20
    frames = [(nbytes, 20 + i, i) for i in range(6)]
    seeds = {str(i): s for _, s, i in frames}
    # The subscriber sees no GPU: the publisher must stage the bytes to host memory.
    child = spawn(ctx, "subscriber", {**where, "accept": "warp", "expect": 6, "seeds": seeds},
                  env={"CUDA_VISIBLE_DEVICES": ""})
    wait_ready(child)
    [result] = _publish_frames(ctx, where, frames, [child])
    return _judge_subscriber(result, 6, None, "cpu")


def check_end_to_end(ctx: Context) -> dict[str, Any]:
    where = _node_env(ctx)
    nbytes, count = 16 << 20, (40 if ctx.quick else 200)
    frames = [(nbytes, 30 + i % 4, i) for i in range(count)]
    seeds = {str(i): s for _, s, i in frames}
    common = {**where, "expect": count, "seeds": seeds, "depth": count, "timeout": 300}
    warp_sub = spawn(ctx, "subscriber", {**common, "accept": "warp"})
    cpu_sub = spawn(ctx, "subscriber", {**common, "accept": "cpu"})
    wait_ready(warp_sub)
    wait_ready(cpu_sub)
    start = time.monotonic()
    warp_result, cpu_result = _publish_frames(ctx, where, frames, [warp_sub, cpu_sub],
                                              depth=count, interval=0.002, timeout=240)
    seconds = time.monotonic() - start
    warp_metrics = _judge_subscriber(warp_result, count, _SAME_HOST, ctx.device.split(":")[0])
    cpu_metrics = _judge_subscriber(cpu_result, count, "cpu", None)
    return {"frames": count, "warp_route": warp_metrics["routes"],
            "cpu_route": cpu_metrics["routes"],
            "seconds": round(seconds, 1)}


def check_tensor_conversions(ctx: Context) -> dict[str, Any]:
    _need_cuda(ctx)
    try:
        import torch
    except ImportError as exc:
        raise Skip(f"torch missing: {exc}") from None
    import warp as wp

    import tensor_conversions
    import tensor_conversions.torch as tct

    syncs = []
    original = wp.synchronize_device
    wp.synchronize_device = lambda *a, **k: (syncs.append(a), original(*a, **k))[1]
    try:
        s = torch.cuda.Stream()
        with torch.cuda.stream(s):
            msg = tct.allocate_tensor_msg((256, 1024), torch.float32, backend="warp",
                                          device=ctx.device)
            out = tct.from_output_tensor_msg(msg)
            need(out.is_cuda, f"the output view is on {out.device}")
            torch.cuda._sleep(int(5e7))
            out.copy_(torch.arange(256 * 1024, dtype=torch.float32, device="cuda").view(256, 1024))
            del out
            tensor_conversions.release_output(msg)
            expect = torch.arange(256 * 1024, dtype=torch.float32, device="cuda").view(256, 1024)
            for clone in (True, False):
                back = tct.from_input_tensor_msg(msg, clone=clone)
                need(torch.equal(back, expect), f"input view (clone={clone}) differs")
            msg2 = tct.to_tensor_msg(expect * 2)
            need(torch.equal(tct.from_input_tensor_msg(msg2), expect * 2), "to_tensor_msg differs")
    finally:
        wp.synchronize_device = original
    need(not syncs, f"wp.synchronize_device ran {len(syncs)} times (a device-wide wait)")
    return {"device_syncs": len(syncs)}


def _child_latency(args: dict[str, Any]) -> dict[str, Any]:
    """Echo: import each frame, wait for it on a stream, answer with a tiny cpu message."""
    from buffer_pubsub import Node
    from rosidl_buffer.messages import get_message_type

    import warp as wp

    import warp_buffer

    import numpy as np

    tensor = get_message_type(TENSOR)
    count = 0
    with Node(f"gpu_check_lat_{os.getpid()}", domain_id=args["domain"]) as node:
        ack = node.create_publisher(tensor, args["topic"] + "_ack", depth=10)

        def on_msg(msg: Any) -> None:
            nonlocal count
            with warp_buffer.from_input_buffer(msg.data) as view:
                stream = view.stream
                if stream is not None:
                    wp.synchronize_stream(stream)  # the bytes are readable here
            count += 1
            ack.publish(tensor(dtype_code=1, dtype_bits=8, dtype_lanes=1, shape=[8],
                               data=np.zeros(8, np.uint8)))

        node.create_subscription(tensor, args["topic"], on_msg, depth=10,
                                 acceptable_buffer_backends=args.get("accept", "warp"))
        ack.wait_for_subscriptions(1, timeout=60)
        _emit("READY")
        _stop_event(200).wait()
    return {"echoed": count}


def check_benchmark(ctx: Context) -> dict[str, Any]:
    import statistics

    import numpy as np

    import warp as wp
    from buffer_pubsub import Node
    from rosidl_buffer.messages import get_message_type

    import warp_buffer

    device = wp.get_device(ctx.device)
    tensor = get_message_type(TENSOR)
    where = _node_env(ctx)
    child = spawn(ctx, "latency", where)
    acks: list[int] = []
    lock = threading.Condition()
    metrics: dict[str, Any] = {}
    with Node(f"gpu_check_bench_{os.getpid()}", domain_id=where["domain"]) as node:
        def on_ack(msg: Any) -> None:
            with lock:
                acks.append(time.perf_counter_ns())
                lock.notify_all()

        node.create_subscription(tensor, where["topic"] + "_ack", on_ack, depth=10)
        pub = node.create_publisher(tensor, where["topic"], depth=10)
        need(pub.wait_for_subscriptions(1, timeout=60), "latency child not matched")
        wait_ready(child)

        def round_trip(msg: Any) -> float:
            with lock:
                seen = len(acks)
                start = time.perf_counter_ns()
                pub.publish(msg)
                need(lock.wait_for(lambda: len(acks) > seen, timeout=20), "no ack")
                return (acks[seen] - start) / 1e3

        tiny = [round_trip(tensor(dtype_code=1, dtype_bits=8, dtype_lanes=1, shape=[8],
                                  data=np.zeros(8, np.uint8))) for _ in range(30)]
        ping = statistics.median(tiny[5:])
        metrics["cpu_ping_rtt_us"] = round(ping, 1)
        for nbytes, label in [(4 << 10, "4KiB"), (16 << 20, "16MiB"), (256 << 20, "256MiB")]:
            rounds = 30 if nbytes < (256 << 20) else 10
            samples = []
            buffer = warp_buffer.allocate_buffer(nbytes, ctx.device)
            _write_frame(buffer, 1, 0, 1)
            for _ in range(rounds):
                samples.append(round_trip(tensor(dtype_code=1, dtype_bits=8, dtype_lanes=1,
                                                 shape=[nbytes], data=buffer)))
            one_way = statistics.median(samples[2:]) - ping / 2  # minus the ack's way back
            metrics[f"warp_one_way_us_{label}"] = round(one_way, 1)
            if not device.is_cuda:
                continue
            host = wp.empty(nbytes, dtype=wp.uint8, device="cpu", pinned=True)
            src = wp.empty(nbytes, dtype=wp.uint8, device=device)
            d2h = []
            for _ in range(rounds):
                t0 = time.perf_counter_ns()
                wp.copy(host, src)
                wp.synchronize_stream(device.stream)
                d2h.append((time.perf_counter_ns() - t0) / 1e3)
            metrics[f"d2h_memcpy_us_{label}"] = round(statistics.median(d2h[1:]), 1)
    finish(ctx, child)
    return metrics


def check_cuda_tests(ctx: Context) -> dict[str, Any]:
    """The repository's cuda-marked tests (VMM, allocators, checked opens, streams, copies)."""
    _need_cuda(ctx)
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", "cuda and not slow",
         "tests/test_cuda_ipc.py", "tests/test_cuda_copy.py"],
        cwd=ROOT, capture_output=True, text=True, timeout=max(30.0, min(240.0, ctx.left() - 30)))
    ctx.log(f"[pytest -m cuda]\n{proc.stdout[-8000:]}\n{proc.stderr[-2000:]}")
    lines = proc.stdout.strip().splitlines()
    summary = lines[-1] if lines else "no output"
    failed = [line.split()[1] for line in lines if line.startswith("FAILED ")]
    need(proc.returncode == 0, f"{summary}; failed: {', '.join(failed)[:400]}")
    return {"summary": summary}


def check_teardown(ctx: Context) -> dict[str, Any]:
    import warp as wp

    import warp_buffer

    gc.collect()
    trim = getattr(warp_buffer, "trim_pools", None)  # the pool's public "give memory back"
    if trim is not None:
        trim()
    gc.collect()
    alive = [p.pid for p in ctx.children if p.poll() is None]
    need(not alive, f"children still running: {alive}")
    mine = [p.name for p in pathlib.Path("/dev/shm").glob("warp_buffer*") if f".{os.getpid()}"
            in p.name or f".{os.getpid()}-" in p.name]
    need(not mine, f"exports left in /dev/shm: {mine[:5]}")
    memfds = 0
    for fd in pathlib.Path("/proc/self/fd").iterdir():
        try:
            memfds += os.readlink(fd).startswith("/memfd:")
        except OSError:
            pass
    metrics: dict[str, Any] = {"children": len(ctx.children), "memfds_open": memfds}
    if ctx.baseline_free is not None and ctx.device.startswith("cuda"):
        wp.synchronize_device(ctx.device)
        free = wp.get_device(ctx.device).free_memory
        lost = ctx.baseline_free - free
        metrics["device_bytes_not_returned"] = lost
        need(lost <= (64 << 20), f"{lost >> 20} MiB of device memory not returned")
    return metrics


CHILD_ROLES: dict[str, Callable[[dict[str, Any]], dict[str, Any]]] = {
    "echo": _child_echo,
    "subscriber": _child_subscriber,
    "publish_and_exit": _child_publish_and_exit,
    "latency": _child_latency,
    "vmm_publish": _child_vmm_publish,
    "vmm_import": _child_vmm_import,
}

CHECKS: list[Check] = [
    Check("install", check_install, gpu=False, doc="carried wheels installed, entry points seen"),
    Check("child_protocol", check_child_protocol, gpu=False, doc="child start/READY/RESULT/reap"),
    Check("stderr_watch", check_stderr_watch, gpu=False, doc="a printed Warp CUDA error fails"),
    Check("capabilities", check_capabilities, doc="IPC, mempool, VMM, uuid"),
    Check("copy_bytes", check_copy_bytes, doc="odd sizes/offsets vs wp.copy; 256 MiB bandwidth"),
    Check("stream_order", check_stream_order, doc="slow writer on A, reader on B; torch stream"),
    Check("reuse_hazard", check_reuse_hazard, doc="slow reader, block re-leased, new write"),
    Check("ipc_child", check_ipc_child, doc="child imports while the writer runs; twice; release"),
    Check("failure_injection", check_failure_injection, cuda_errors_expected=True,
          doc="forged handles, publisher exited: typed errors, no wrong data"),
    Check("vmm", check_vmm, cuda_errors_expected=True,
          doc="VMM block: child import (CRC), write refused, import outlives the publisher"),
    Check("forced_staging", check_forced_staging, doc="subscriber without the GPU gets cpu bytes"),
    Check("end_to_end", check_end_to_end, doc="Node, 200 x 16 MiB to warp and cpu subscribers"),
    Check("tensor_conversions", check_tensor_conversions, doc="torch on the GPU, no device sync"),
    Check("benchmark", check_benchmark, doc="one-way latency vs cudaMemcpy D2H"),
    Check("cuda_tests", check_cuda_tests, cuda_errors_expected=True,
          doc="pytest -m cuda: VMM, allocators, checked opens, streams (own process)"),
    Check("teardown", check_teardown, doc="no exports, no children, device memory returned"),
]


# =============================================================================== main
def _gpu_present() -> bool:
    try:
        import warp as wp

        wp.init()
        return wp.get_cuda_device_count() > 0
    except Exception:  # noqa: BLE001
        return False


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["child"]:
        return child_main(argv[1], json.loads(argv[2]))
    if argv[:1] == ["prepare"]:
        parser = argparse.ArgumentParser(prog="gpu_check prepare")
        parser.add_argument("wheels", type=pathlib.Path)
        parser.add_argument("--dest", type=pathlib.Path, default=ROOT / ".whl")
        ns = parser.parse_args(argv[1:])
        parts = split_wheels(ns.wheels, ns.dest)
        for index, part in enumerate(parts, 1):
            rel = part.relative_to(ROOT) if part.is_relative_to(ROOT) else part
            last = index == len(parts)
            command = (f"mkdir -p {PARTS_STAGING} && cp {rel}/* {PARTS_STAGING}/"
                       + (" && bash benchmarks/gpu_check.sh" if last else ""))
            print(f"call {index}: carry=['{rel}'] command: {command}")
        return 0
    parser = argparse.ArgumentParser(prog="gpu_check", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=pathlib.Path, default=None)
    parser.add_argument("--device", default="cuda:0",
                        help="CUDA device; 'cpu' rehearses the checks that can run on cpu")
    parser.add_argument("--no-gpu", action="store_true", help="plumbing mode")
    parser.add_argument("--only", default="", help="comma-separated check names")
    parser.add_argument("--budget-s", type=float, default=DEFAULT_BUDGET_S)
    parser.add_argument("--quick", action="store_true", help="fewer frames (a smoke run)")
    parser.add_argument("--target", type=pathlib.Path, default=None,
                        help="install directory (default: a scratch one)")
    ns = parser.parse_args(argv)
    out = ns.out or pathlib.Path(os.environ.get("OUT") or ROOT / "benchmarks/results/gpu_check")
    out.mkdir(parents=True, exist_ok=True)
    log_file = (out / "gpu_check.log").open("w")
    start = time.monotonic()

    def log(line: str) -> None:
        log_file.write(f"[{time.monotonic() - start:7.1f}s] {line}\n")
        log_file.flush()

    target = ns.target or pathlib.Path(tempfile.mkdtemp(prefix="wb_gpu_check_site_"))
    try:
        report = install(target)
        log(f"install: {json.dumps(dataclasses.asdict(report))}")
    except Exception as exc:  # noqa: BLE001 - reported by the install check
        log(f"install failed: {exc}")
    os.environ.setdefault("WARP_CACHE_PATH", str(ROOT / ".warp_cache"))
    try:
        import warp as wp

        wp.config.quiet = True  # the table is the last thing printed
    except ImportError:
        pass
    # --device cpu rehearses the GPU checks on the cpu device (those that need CUDA skip).
    gpu = not ns.no_gpu and (ns.device == "cpu" or _gpu_present())
    ctx = Context(ns.device, gpu, out, log, start + ns.budget_s, quick=ns.quick)
    log(f"mode: {'gpu' if gpu else 'plumbing'} device={ns.device} python={sys.version.split()[0]}")
    selected = [c for c in CHECKS if not ns.only or c.name in ns.only.split(",")]
    try:
        results = run_checks(selected, ctx)
    finally:
        for proc in ctx.children:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    text = table(results)
    log(text)
    (out / "gpu_check.json").write_text(json.dumps(
        {"mode": "gpu" if gpu else "plumbing", "seconds": round(time.monotonic() - start, 1),
         "results": [dataclasses.asdict(r) for r in results]}, indent=1, default=str))
    log_file.close()
    if ns.target is None:
        shutil.rmtree(target, ignore_errors=True)
        shutil.rmtree(target.parent / (target.name + "_wheels"), ignore_errors=True)
    print(text)
    return 1 if any(r.status == "FAIL" for r in results) else 0


if __name__ == "__main__":
    sys.exit(main())
