"""``warp-buffer bench --quick`` runs and produces sane output (not timings)."""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import subprocess
import sys
import time

import pytest

from benchmarks import run as bench
from benchmarks.paths import PATH_MODULES
from benchmarks.report import merge_rounds, ratios
from benchmarks.stats import format_size, parse_size, summarize_latency

ROOT = pathlib.Path(__file__).resolve().parent.parent
# Peers that depend on nothing of ours: they must measure, not just be "unavailable".
ALWAYS_AVAILABLE = ("zenoh_copy", "zenoh_shm", "iceoryx2", "torch_mp")
QUICK_SIZES = "4K,1M"  # a smaller sweep keeps the test well inside the suite's budget


def _positive_finite(value: float) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value) and value > 0


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, str, pathlib.Path]:
    out = tmp_path_factory.mktemp("bench")
    process = subprocess.run(
        [sys.executable, "-m", "benchmarks.run", "--quick", "--sizes", QUICK_SIZES,
         "--out", str(out), "--no-copy-bandwidth", "--no-conversions", "--no-ipc-core",
         "--no-loans"],
        cwd=ROOT, capture_output=True, text=True, timeout=240)
    assert process.returncode == 0, process.stderr[-3000:]
    with open(out / "bench.json", encoding="utf-8") as handle:
        return json.load(handle), process.stdout, out


@pytest.mark.multiprocess
def test_quick_run_writes_json_png_and_table(quick_run: tuple[dict, str, pathlib.Path]) -> None:
    report, stdout, out = quick_run
    for key in ("machine", "method", "plan", "paths", "ratios", "mode"):
        assert key in report
    assert report["mode"] == "quick"
    machine = report["machine"]
    assert machine["cpu_model"] and machine["logical_cores"] >= 1 and machine["platform"]
    assert machine["versions"]["eclipse-zenoh"]
    assert set(report["paths"]) == set(PATH_MODULES)
    png = out / "latency.png"
    assert png.stat().st_size > 1000 and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "one-way p50" in stdout and "Ratios" in stdout
    assert f"wrote {out / 'bench.json'}" in stdout  # it says where the results are
    for entry in report["ratios"].values():
        assert entry["verdict"] in ("PASS", "MISS", "N/A", "INFO")


@pytest.mark.multiprocess
def test_quick_run_figures_are_positive_and_finite(
        quick_run: tuple[dict, str, pathlib.Path]) -> None:
    report, _, _ = quick_run
    sizes = [str(s) for s in report["plan"]["sizes"]]
    assert sizes == [str(parse_size(s)) for s in QUICK_SIZES.split(",")]
    for name, entry in report["paths"].items():
        if entry["status"] == "unavailable":
            assert name not in ALWAYS_AVAILABLE, entry["reason"]
            assert entry["reason"]
            continue
        assert entry["status"] == "ok", (name, entry.get("reason"), entry.get("errors"))
        for size in sizes:
            figures = entry["latency_us"][size]
            for stat in ("p50_us", "p90_us", "p99_us"):
                assert _positive_finite(figures[stat]), (name, size, stat)
            assert figures["p50_us"] <= figures["p90_us"] <= figures["p99_us"]
            assert figures["samples"] >= 3
        assert _positive_finite(entry["rate"]["msgs_per_s"])
        if entry["kind"] == "ours":
            for size in sizes:
                counted = entry["copies"][size]["bytes_copied_per_message"]
                assert isinstance(counted, int) and counted >= 0


@pytest.mark.multiprocess
def test_quick_run_leaves_no_children_or_shm(quick_run: tuple[dict, str, pathlib.Path]) -> None:
    report, _, _ = quick_run
    # Only this run's files: every iceoryx2 file of the run carries its run id in its prefix, and
    # other programs on the host (with iceoryx2's default prefix or another run's) are not ours.
    assert report["run_id"]
    leftovers = [n for n in os.listdir("/dev/shm") if report["run_id"] in n]
    assert leftovers == []
    ran = [e for e in report["paths"].values() if e["status"] == "ok"]
    assert ran and all(e["wall_s"] < report["plan"]["path_timeout_s"] for e in ran)


def test_ratios_pass_miss_and_missing() -> None:
    def path(p50_by_size: dict[int, float]) -> dict:
        return {"status": "ok", "latency_us": {str(s): {"p50_us": v} for s, v in
                                               p50_by_size.items()}}

    paths = {"warp_zero_copy": path({4096: 10.0, 16 << 20: 11.0, 64 << 20: 13.0}),
             "zenoh_copy": path({16 << 20: 1100.0}), "iceoryx2": path({16 << 20: 2.0})}
    result = ratios(paths)
    assert result["speedup_vs_zenoh_copy_16MiB"]["verdict"] == "PASS"
    assert result["speedup_vs_zenoh_copy_16MiB"]["value"] == pytest.approx(100.0)
    assert result["slowdown_vs_iceoryx2_16MiB"]["verdict"] == "MISS"
    assert result["flatness_64MiB_over_4KiB"]["verdict"] == "MISS"
    del paths["iceoryx2"]
    assert ratios(paths)["slowdown_vs_iceoryx2_16MiB"]["verdict"] == "N/A"


def test_each_warp_lane_bar_shows_the_lane_alone_beside_it() -> None:
    """A missed warp zero-copy bar is shown beside its floor in the same run: the lane alone
    (wake-up and doorbell, no message work)."""
    def path(p50: float, p99: float) -> dict:
        return {"status": "ok", "latency_us": {"4096": {"p50_us": p50, "p99_us": p99}}}

    paths = {"warp_zero_copy": path(80.0, 130.0), "lane": path(42.0, 60.0),
             "iceoryx2_listener": path(35.0, 70.0), "zenoh_copy": path(112.0, 180.0)}
    result = ratios(paths)
    p50 = result["warp_lane_worst_p50_over_40us"]
    assert p50["verdict"] == "MISS" and p50["value"] == pytest.approx(2.0)
    assert p50["detail"] == "the lane alone, its floor here: 1.05x"
    assert result["warp_lane_vs_iceoryx2_listener_4KiB"]["detail"].endswith(": 1.20x")
    assert result["warp_lane_worst_p99_over_120us"]["detail"].endswith(": 0.50x")
    assert result["lane_worst_p50_over_40us"]["detail"] == ""  # (the floor itself)
    del paths["lane"]
    assert ratios(paths)["warp_lane_worst_p50_over_40us"]["detail"] == ""


def test_default_out_dir_follows_xdg_state_home(monkeypatch: pytest.MonkeyPatch,
                                                tmp_path: pathlib.Path) -> None:
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path))
    assert bench.default_out_dir() == str(tmp_path / "warp-buffer" / "bench")
    monkeypatch.delenv("XDG_STATE_HOME")
    assert bench.default_out_dir() == os.path.expanduser("~/.local/state/warp-buffer/bench")


def test_stats_helpers() -> None:
    summary = summarize_latency([1000, 2000, 3000, 4000])
    assert summary["p50_us"] == pytest.approx(2.5) and summary["samples"] == 4
    assert parse_size("16M") == 16 << 20 and parse_size("4KiB") == 4096
    assert format_size(64 << 20) == "64 MiB"
    with pytest.raises(ValueError):
        parse_size("0")


def test_without_the_bench_extra_the_bench_says_so_before_measuring(
        monkeypatch: pytest.MonkeyPatch, tmp_path: pathlib.Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    """A plain ``pip install`` lacks matplotlib (and torch, iceoryx2): the bench measured for
    minutes, then ended in a traceback at the plot."""
    monkeypatch.setattr(bench, "BENCH_MODULES", ("matplotlib", "no_such_module_of_the_extra"))
    monkeypatch.setattr(bench, "measure", lambda args: pytest.fail("measured without the extra"))
    out = tmp_path / "out"
    assert bench.run(argparse.Namespace(out=str(out))) == 2
    err = capsys.readouterr().err
    assert "missing: no_such_module_of_the_extra" in err and "warp-buffer[bench]" in err
    assert "matplotlib" not in err.split("missing:")[1]  # installed: not named
    assert not out.exists()


def test_a_relative_xdg_state_home_is_ignored(monkeypatch) -> None:
    """XDG: relative paths are invalid; it made the bench write into the current directory."""
    monkeypatch.setenv("XDG_STATE_HOME", "rel")
    assert os.path.isabs(bench.default_out_dir())
    monkeypatch.setenv("XDG_STATE_HOME", "/tmp/state_here")
    assert bench.default_out_dir() == "/tmp/state_here/warp-buffer/bench"


def test_add_arguments_defaults() -> None:
    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    args = parser.parse_args([])
    assert args.out == bench.default_out_dir() and not args.quick
    assert parser.parse_args(["--quick", "--sizes", "4K"]).sizes == "4K"


@pytest.mark.multiprocess
@pytest.mark.parametrize("options", [[], ["--spin", "--busy-poll", "0.001"]],
                         ids=["blocking", "all-warm"])
def test_lane_stages_reports_every_stage(options: list[str]) -> None:
    from benchmarks.lane_stages import STAGES

    process = subprocess.run(
        [sys.executable, "-m", "benchmarks.lane_stages", "--count", "40", *options],
        cwd=ROOT, capture_output=True, text=True, timeout=120)
    if "cannot run the lane" in process.stderr:
        pytest.skip("no same-host lane here")
    assert process.returncode == 0, process.stderr[-3000:]
    rows = {}
    for line in process.stdout.splitlines()[2:]:
        name, p50, p99 = line.rsplit(None, 2)
        rows[name.strip()] = (float(p50), float(p99))
    for name, _start, _end in STAGES["lane"]:
        assert name in rows, (name, process.stdout)
    total = rows["one-way total (loan -> readable view)"]
    assert 0 < total[0] <= total[1]
    assert any(name.startswith("lane alone") for name in rows)


def test_side_by_side_puts_each_stage_beside_its_warm_self() -> None:
    from benchmarks.lane_stages import side_by_side

    text = side_by_side([("loan", 30.0, 90.0), ("wake-up", 25.0, 40.0), ("view", 12.0, 20.0),
                         ("early", -3.0, 5.0)],
                        [("loan", 10.0, 20.0), ("wake-up", 0.2, 1.0), ("early", 2.0, 4.0)])
    header, loan, wake, view, early = text.splitlines()
    assert header.split()[-5:] == ["idle", "p50", "warm", "p50", "ratio"]
    assert loan.split()[-3:] == ["30.0", "10.0", "3.0x"]
    assert wake.split()[-3:] == ["25.0", "0.2", "-"]  # no wake-up to divide by when warm
    assert view.split()[-3:] == ["12.0", "-", "-"]
    assert early.split()[-3:] == ["-3.0", "2.0", "-"]  # a stage read below 0: no ratio


@pytest.mark.multiprocess
def test_lane_stages_warm_prints_both_medians_of_every_stage() -> None:
    from benchmarks.lane_stages import STAGES

    process = subprocess.run(
        [sys.executable, "-m", "benchmarks.lane_stages", "--count", "30", "--warm", "--frames",
         "0", "--syscalls", "0"], cwd=ROOT, capture_output=True, text=True, timeout=180)
    if "cannot run the lane" in process.stderr:
        pytest.skip("no same-host lane here")
    assert process.returncode == 0, process.stderr[-3000:]
    lines = process.stdout.splitlines()
    assert lines[1].split()[-5:] == ["idle", "p50", "warm", "p50", "ratio"]
    rows = {line.rsplit(None, 3)[0].strip(): line.rsplit(None, 3)[1:] for line in lines[2:]}
    for name, _start, _end in STAGES["lane"]:  # (a wake-up can read below 0: the subscriber
        idle, warm, _ratio = rows[name]        # may enter before the write call returned)
        assert float(idle) == float(idle) and float(warm) == float(warm), (name, process.stdout)
    idle, warm, ratio = rows["one-way total (loan -> readable view)"]
    assert float(idle) > 0 and float(warm) > 0
    assert float(ratio.rstrip("x")) == pytest.approx(float(idle) / float(warm), abs=0.051)


@pytest.mark.parametrize("argv", [["--sizes", "0,abc"], ["--sizes", ","], ["--paths", "nosuch"],
                                  ["--paths", ","], ["--rounds", "0"], ["--rounds", "two"],
                                  ["--sizes", "infK"], ["--sizes", "1e400K"],
                                  ["--rounds", str(bench.MAX_ROUNDS + 1)]])
def test_bad_bench_options_are_usage_errors(argv: list[str], capsys: pytest.CaptureFixture[str]
                                             ) -> None:
    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    with pytest.raises(SystemExit) as exit_info:
        parser.parse_args(argv)
    assert exit_info.value.code == 2 and argv[0] in capsys.readouterr().err


def test_an_unwritable_out_dir_is_refused_before_anything_is_measured(tmp_path) -> None:
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    started = time.monotonic()
    process = subprocess.run(
        [sys.executable, "-m", "benchmarks.run", "--quick", "--sizes", "4K", "--paths",
         "zenoh_copy", "--no-copy-bandwidth", "--no-conversions", "--no-loans", "--no-ipc-core",
         "--out", str(blocker / "out")], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert process.returncode != 0 and "not a writable directory" in process.stderr
    assert time.monotonic() - started < 30  # refused up front


def _round(p50_us: float, rate: float, status: str = "ok") -> dict:
    return {"label": "x", "status": status, "errors": [] if status == "ok" else ["1 MiB: late"],
            "wall_s": 1.0, "shm_removed": [], "rate": {"nbytes": 4096, "msgs_per_s": rate},
            "latency_us": {"4096": {"p50_us": p50_us, "p99_us": 2 * p50_us, "samples": 200,
                                    "min_us": p50_us, "max_us": p50_us}}}


def test_rounds_merge_to_the_median_of_each_figure() -> None:
    merged = merge_rounds([_round(10.0, 300.0), _round(30.0, 100.0, "partial"),
                           _round(20.0, 200.0)])
    assert merged["latency_us"]["4096"]["p50_us"] == 20.0
    assert merged["latency_us"]["4096"]["p99_us"] == 40.0
    assert merged["latency_us"]["4096"]["samples"] == 600
    assert merged["rounds_p50_us"] == {"4096": [10.0, 30.0, 20.0]}
    assert merged["rate"]["msgs_per_s"] == 200.0
    assert merged["latency_us"]["4096"]["min_us"] == 10.0  # extremes of all samples
    assert merged["latency_us"]["4096"]["max_us"] == 30.0
    assert merged["status"] == "partial" and merged["errors"] == ["1 MiB: late"]
    assert merged["wall_s"] == 3.0
    single = _round(10.0, 300.0)
    assert merge_rounds([single]) is single  # one round: the entry as measured
    unavailable = {"label": "x", "status": "unavailable", "reason": "no iceoryx2"}
    assert merge_rounds([unavailable]) is unavailable
    timed_out = {"label": "x", "status": "error", "reason": "timed out after 45 s"}
    merged = merge_rounds([_round(10.0, 300.0), timed_out])
    assert merged["status"] == "partial" and merged["latency_us"]["4096"]["p50_us"] == 10.0
    assert merged["errors"] == ["round 2: error: timed out after 45 s"]


@pytest.mark.multiprocess
def test_rounds_run_each_path_in_turn(tmp_path) -> None:
    process = subprocess.run(
        [sys.executable, "-m", "benchmarks.run", "--quick", "--sizes", "4K", "--paths",
         "zenoh_copy,cpu_codec_floor", "--rounds", "2", "--no-copy-bandwidth",
         "--no-conversions", "--no-loans", "--no-ipc-core", "--out", str(tmp_path)],
        cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert process.returncode == 0, process.stderr[-3000:]
    report = json.loads((tmp_path / "bench.json").read_text())
    assert report["plan"]["rounds"] == 2 and "Rounds: 2" in process.stdout
    for name in ("zenoh_copy", "cpu_codec_floor"):
        per_round = report["paths"][name]["rounds_p50_us"]["4096"]
        assert len(per_round) == 2 and all(_positive_finite(v) for v in per_round)
    floor = report["ratios"]["cpu_codec_floor_over_zenoh_4KiB"]
    assert floor["verdict"] == "INFO" and _positive_finite(floor["value"])
    # the progress lines show both rounds, the paths in turn within each
    order = [line for line in process.stderr.splitlines() if line.startswith(("round", "["))]
    assert [line.split()[0] for line in order if line.startswith("round")] == ["round", "round"]


@pytest.mark.multiprocess
def test_intra_stages_reports_every_stage_in_both_modes() -> None:
    from benchmarks.intra_stages import BARE_LABEL, STAGES

    process = subprocess.run(
        [sys.executable, "-m", "benchmarks.intra_stages", "--count", "30", "--pause-us", "200",
         "--json"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert process.returncode == 0, process.stderr[-3000:]
    report = json.loads(process.stdout.strip().splitlines()[-1])
    assert set(report["modes"]) == {"hot", "after a pause"}
    for figures in report["modes"].values():
        for label, _start, _end in STAGES:
            assert math.isfinite(figures[label]) and figures[label] >= 0, (label, figures)
        total = figures["one-way total (publish -> callback)"]
        assert total > 0 and _positive_finite(figures[BARE_LABEL])
        # the stages before the notify are parts of the total
        assert figures["publish: validate fields, seal + backends"] < total
