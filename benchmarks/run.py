"""``warp-buffer bench``: measure every path on this machine, print a table, write JSON and a plot.

Each path runs in child processes of its own (``python -m benchmarks.child``), one path after the
other, so they never compete for the two cores; every child is reaped and the shared memory it
left is removed. Results: ``<out>/bench.json`` (every figure and the machine) and
``<out>/latency.png``.
"""

from __future__ import annotations

import argparse
import datetime
import importlib.util
import json
import os
import subprocess
import sys
import time
import uuid
from typing import Any

from benchmarks.machine import describe, machine_info
from benchmarks.paths import PATH_MODULES, PathSettings, load_path
from benchmarks.processes import free_tcp_port, run_path
from benchmarks.protocol import METHOD, progress
from benchmarks.report import (
    format_table,
    merge_rounds,
    path_entry,
    ratios,
    transport_ratios,
)
from benchmarks.stats import format_size, parse_size

DEFAULT_SIZES = "4K,64K,1M,16M,64M,256M"
QUICK_SIZES = "4K,1M,16M,64M"
MAX_ROUNDS = 20

# mode -> measurement plan (sizes come from --sizes or the mode's default)
PLANS: dict[str, dict[str, Any]] = {
    "default": {"iterations": 300, "warmup": 5, "budget_s": 2.0, "timeout_s": 15.0,
                "rate": {"nbytes": 4096, "count": 5000, "window": 8, "budget_s": 2.0},
                "path_timeout_s": 150.0},
    # quick: up to 200 samples within the budget, so fast paths (the lane, iceoryx2) get a
    # stable median; slow ones stop at the budget as before (3 samples at least).
    "quick": {"iterations": 200, "warmup": 2, "budget_s": 0.4, "timeout_s": 8.0,
              "rate": {"nbytes": 4096, "count": 1000, "window": 8, "budget_s": 0.3},
              "path_timeout_s": 45.0},
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``warp-buffer bench``."""
    parser.add_argument("--quick", action="store_true",
                        help=f"fewer sizes ({QUICK_SIZES}) and iterations: under a minute")
    parser.add_argument("--out", default=default_out_dir(),
                        help="directory for bench.json and latency.png, created if missing "
                             "(default: %(default)s, i.e. $XDG_STATE_HOME/warp-buffer/bench)")
    parser.add_argument("--sizes", default=None, type=_sizes_option,
                        help=f"comma-separated payload sizes, e.g. 4K,1M,16M (default: "
                             f"{DEFAULT_SIZES}; quick: {QUICK_SIZES})")
    parser.add_argument("--paths", default=",".join(PATH_MODULES), type=_paths_option,
                        help="comma-separated paths to run (default: all): %(default)s")
    parser.add_argument("--rounds", default=1, type=_rounds_option,
                        help="run the paths this many times in turn and report each figure's "
                             "median over the rounds: ratios of paths measured seconds apart "
                             "drift with the machine's load, rounds spread every path over the "
                             "whole run (default: %(default)s)")
    parser.add_argument("--no-copy-bandwidth", action="store_true",
                        help="skip the copy-kernel bandwidth measurement")
    parser.add_argument("--no-conversions", action="store_true",
                        help="skip the tensor_conversions per-frame cost measurement")
    parser.add_argument("--no-loans", action="store_true",
                        help="skip the loaned-messages section (benchmarks.loans)")
    parser.add_argument("--no-ipc-core", action="store_true",
                        help="skip the IPC core section (benchmarks.ipc_core)")


def _sizes_option(text: str) -> str:
    """``--sizes``: checked at parse time (a usage error, not a traceback after measuring)."""
    try:
        sizes = [parse_size(s) for s in text.split(",") if s.strip()]
    except (ValueError, OverflowError):  # OverflowError: infK, 1e400K
        raise argparse.ArgumentTypeError(
            f"{text!r}: use comma-separated positive sizes like 4K,1M,16M") from None
    if not sizes:
        raise argparse.ArgumentTypeError("no size given")
    return text


def _rounds_option(text: str) -> int:
    """argparse type of ``--rounds``: a count from 1 to MAX_ROUNDS."""
    try:
        rounds = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if not 1 <= rounds <= MAX_ROUNDS:
        raise argparse.ArgumentTypeError(f"must be 1 to {MAX_ROUNDS}, got {rounds}")
    return rounds


def _paths_option(text: str) -> str:
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in PATH_MODULES]
    if not names or unknown:
        raise argparse.ArgumentTypeError(
            f"{'unknown path ' + repr(unknown[0]) if unknown else 'no path given'}; "
            f"known: {', '.join(PATH_MODULES)}")
    return text


def prepare_out_dir(path: str) -> None:
    """Create ``--out`` (and check it takes files) before anything is measured: a run must not
    end by losing its results to a directory it cannot write."""
    try:
        os.makedirs(path, exist_ok=True)
        probe = os.path.join(path, f".write_test_{os.getpid()}")
        with open(probe, "w", encoding="utf-8"):
            pass
        os.remove(probe)
    except OSError as exc:
        raise SystemExit(f"warp-buffer bench: --out {path!r} is not a writable directory: "
                         f"{exc.strerror or exc}") from None


def default_out_dir() -> str:
    """Where results go without ``--out``: ``$XDG_STATE_HOME/warp-buffer/bench`` (XDG's place
    for data a program keeps between runs; ``~/.local/state`` when unset), never the current
    directory, so a run from anywhere leaves no files behind in it. A relative
    ``XDG_STATE_HOME`` is ignored, as the XDG specification says."""
    state = os.environ.get("XDG_STATE_HOME", "")
    if not os.path.isabs(state):
        state = os.path.join(os.path.expanduser("~"), ".local", "state")
    return os.path.join(state, "warp-buffer", "bench")


def _plan(args: argparse.Namespace) -> dict[str, Any]:
    plan = dict(PLANS["quick" if args.quick else "default"])
    text = args.sizes or (QUICK_SIZES if args.quick else DEFAULT_SIZES)
    plan["sizes"] = sorted({parse_size(s) for s in text.split(",") if s.strip()})
    return plan


def _section(module: str, title: str, quick: bool, timeout_s: float) -> dict[str, Any]:
    """Run ``benchmarks.<module>.main`` in a child (a benchmark that is another module's job), so
    its Warp kernels and threads do not disturb the latency runs; keep what it printed."""
    import importlib.util

    if importlib.util.find_spec(f"benchmarks.{module}") is None:
        return {"status": "unavailable", "reason": f"benchmarks/{module}.py not present"}
    argv = ["--quick"] if quick else []
    code = (f"import sys, benchmarks.{module} as m; "
            f"sys.exit(m.main({argv!r}) or 0)")
    progress(f"{title}: benchmarks.{module} " + " ".join(argv))
    process = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True,
                               cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    try:
        out, err = process.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        process.kill()
        process.communicate()
        return {"status": "error", "reason": f"timed out after {timeout_s:.0f} s"}
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    if process.returncode != 0:
        return {"status": "error", "reason": (err.strip().splitlines() or ["failed"])[-1]}
    return {"status": "ok", "text": out.rstrip()}


def _stages(timeout_s: float) -> dict[str, Any]:
    """``benchmarks.stages`` in a child (its Zenoh sessions and threads stay out of the runs)."""
    progress("stages: python -m benchmarks.stages --json")
    try:
        process = subprocess.run([sys.executable, "-m", "benchmarks.stages", "--json"],
                                 capture_output=True, text=True, timeout=timeout_s,
                                 cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    except subprocess.TimeoutExpired:
        return {"status": "error", "reason": f"timed out after {timeout_s:.0f} s"}
    if process.returncode != 0:
        return {"status": "error",
                "reason": (process.stderr.strip().splitlines() or ["failed"])[-1]}
    return {"status": "ok", **json.loads(process.stdout.strip().splitlines()[-1])}


def measure(args: argparse.Namespace) -> dict[str, Any]:
    """Run every selected path; the full report (not yet written)."""
    plan = _plan(args)
    names = [n.strip() for n in args.paths.split(",") if n.strip()]
    for name in names:
        load_path(name)  # unknown names fail before anything runs
    run_id = uuid.uuid4().hex[:10]
    info = machine_info()
    report: dict[str, Any] = {
        "schema": 1, "tool": "warp-buffer bench", "run_id": run_id,
        "started": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "mode": "quick" if args.quick else "default", "method": METHOD,
        "machine": info, "machine_line": describe(info), "plan": plan, "paths": {},
    }
    started = time.monotonic()
    progress(f"warp-buffer bench ({report['mode']}): {len(names)} paths x "
             f"{', '.join(format_size(s) for s in plan['sizes'])} on {report['machine_line']}")
    rounds: dict[str, list[dict[str, Any]]] = {name: [] for name in names}
    for round_index in range(args.rounds):
        if args.rounds > 1:
            progress(f"round {round_index + 1}/{args.rounds}")
        for index, name in enumerate(names, 1):
            if rounds[name] and rounds[name][-1]["status"] == "unavailable":
                continue  # it cannot run here (a missing package): not in a later round either
            module = load_path(name)
            progress(f"[{index}/{len(names)}] {module.LABEL} ({name})")
            settings = PathSettings(name=name, run_id=f"{run_id}_{round_index}_{index}",
                                    max_nbytes=max(plan["sizes"]), port=free_tcp_port(),
                                    domain_id=100 + int(run_id[:4], 16) % 100)
            raw = run_path(settings, plan, plan["path_timeout_s"])
            entry = path_entry(name, module, raw)
            rounds[name].append(entry)
            if entry["status"] in ("unavailable", "error"):
                progress(f"  [{name}] {entry['status']}: {entry['reason']}")
    report["plan"]["rounds"] = args.rounds
    report["paths"] = {name: merge_rounds(entries) for name, entries in rounds.items()}
    if not args.no_copy_bandwidth:
        report["copy_bandwidth"] = _section("copy_bandwidth", "copy bandwidth", args.quick,
                                            60.0 if args.quick else 180.0)
    if not args.no_conversions:
        report["conversions"] = _section("conversions", "tensor conversions", args.quick,
                                         60.0 if args.quick else 180.0)
    if not args.no_loans:
        report["loans"] = _section("loans", "loans", args.quick, 90.0 if args.quick else 240.0)
    if not args.no_ipc_core:
        report["ipc_core"] = _section("ipc_core", "IPC core", args.quick,
                                      120.0 if args.quick else 300.0)
    report["ratios"] = ratios(report["paths"])
    if any(r["verdict"] == "MISS" for r in transport_ratios(report["paths"]).values()):
        report["stages"] = _stages(60.0)  # a transport target missed: show where time goes
    report["wall_s"] = time.monotonic() - started
    return report


#: What the ``bench`` extra installs that a run needs (the plot, the peers, the conversions)
BENCH_MODULES = ("matplotlib", "torch", "iceoryx2")


def missing_bench_modules() -> list[str]:
    """The modules of the ``bench`` extra that are not installed here."""
    return [name for name in BENCH_MODULES if importlib.util.find_spec(name) is None]


def run(args: argparse.Namespace) -> int:
    """Measure, print the table, write ``bench.json`` and ``latency.png`` into ``--out``."""
    missing = missing_bench_modules()
    if missing:  # said before minutes of measuring, not in a traceback after them
        print(f"warp-buffer bench needs the 'bench' extra, which is not installed here "
              f"(missing: {', '.join(missing)}): pip install 'warp-buffer[bench]'",
              file=sys.stderr)
        return 2
    prepare_out_dir(args.out)
    report = measure(args)
    json_path = os.path.join(args.out, "bench.json")
    png_path = os.path.join(args.out, "latency.png")
    report["outputs"] = {"json": json_path, "png": png_path}
    from benchmarks.plot import plot_latency

    plot_latency(report, png_path)
    with open(json_path, "w", encoding="utf-8") as handle:
        json.dump(report, handle, indent=2)
    print(format_table(report))
    print(f"\nwrote {json_path} and {png_path} in {report['wall_s']:.0f} s")
    ran = [e for e in report["paths"].values() if e["status"] in ("ok", "partial")]
    return 0 if ran else 1


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks.run``."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.run", description=__doc__)
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
