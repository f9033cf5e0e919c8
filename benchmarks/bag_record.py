"""``warp-buffer bag record`` against the demo's publisher rate, side by side per backend.

A publisher process sends ``tensor_msgs/msg/ExperimentalTensor`` frames in warp storage (the
demo's: ``--size`` bytes, 16 MiB by default, at ``--rate`` frames/s, the demo's default 50) for
``--seconds``; ``warp-buffer bag record`` runs in another process, once with ``--backend warp``
(zero-copy import, one copy to the host at the recorder) and once with ``--backend cpu`` (the
publisher serializes CDR bytes, Zenoh carries them). For each it reports frames published,
recorded, dropped because the disk could not keep up (the recorder's cache was full) and lost
before the recorder, the MiB/s recorded (bytes in the bag over the span of their receive
stamps), the recorder's CPU time per frame recorded (from its subscription on, start-up not
counted), and how long it took to finish writing after Ctrl-C. Bags go to ``--dir`` (default: a temporary directory on the same disk as /tmp) and are
deleted after their figures are taken.

    python -m benchmarks.bag_record [--seconds 5] [--size 16M] [--rate 50] [--storage mcap]
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import resource
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from typing import Any

from benchmarks.stats import format_size, parse_size

ROOT = pathlib.Path(__file__).resolve().parent.parent
TENSOR = "tensor_msgs/msg/ExperimentalTensor"
DEMO_RATE = 50.0  # warp-buffer demo's default --rate
MIB = float(1 << 20)


# --------------------------------------------------------------------------- publisher child
def publish(domain: int, topic: str, size: int, rate: float, seconds: float) -> int:
    """The child: warp frames of ``size`` bytes at ``rate`` for ``seconds`` once matched."""
    import numpy as np

    from warp_buffer import init_warp

    init_warp()
    from buffer_pubsub import Node
    from tensor_conversions import numpy as tcn

    frames = max(1, int(rate * seconds))
    with Node("bag_bench_publisher", domain_id=domain) as node:
        pub = node.create_publisher(TENSOR, topic, depth=10)  # the demo's keep-last
        print("READY", flush=True)
        if not pub.wait_for_subscriptions(1, timeout=60):
            print("RESULT " + json.dumps({"error": "no recorder"}), flush=True)
            return 1
        time.sleep(0.5)  # the route settles (the lane opens) before the first frame
        started = time.monotonic()
        for index in range(frames):
            msg = tcn.allocate_tensor_msg((size // 4,), np.float32, backend="warp", device="cpu")
            tcn.from_output_tensor_msg(msg)[:] = float(index)  # NumPy fills at memory speed
            pub.publish(msg)
            del msg
            due = started + (index + 1) / rate
            time.sleep(max(0.0, due - time.monotonic()))
        elapsed = time.monotonic() - started
        print("RESULT " + json.dumps({"published": frames, "seconds": elapsed}), flush=True)
        sys.stdin.readline()  # frames stay alive until the recorder has them
    return 0


# --------------------------------------------------------------------------- one measurement
def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _cpu_s(pid: int) -> float:
    """CPU seconds process ``pid`` used so far (user + system)."""
    with open(f"/proc/{pid}/stat", encoding="ascii") as stat:
        fields = stat.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def measure(backend: str, args: argparse.Namespace, where: pathlib.Path) -> dict[str, Any]:
    """Record the publisher's frames with ``--backend backend``; the figures."""
    domain = 100 + (os.getpid() + (backend == "cpu")) % 100
    topic = f"/bag_bench/{backend}_{os.getpid()}"
    bag = where / f"bag_{backend}"
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
    publisher = subprocess.Popen(
        [sys.executable, "-m", "benchmarks.bag_record", "--publish", "--domain", str(domain),
         "--topic", topic, "--size", str(args.size), "--rate", str(args.rate),
         "--seconds", str(args.seconds)],
        cwd=ROOT, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    recorder = None
    try:
        assert publisher.stdout is not None and publisher.stdin is not None
        assert publisher.stdout.readline().strip() == "READY"
        recorder = subprocess.Popen(
            [sys.executable, "-m", "warp_buffer_cli.main", "bag", "record", topic, "-o",
             str(bag), "--storage", args.storage, "--backend", backend,
             "--max-cache-size", str(args.max_cache_size)],
            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert recorder.stdout is not None
        first = recorder.stdout.readline()  # "recording ...": subscribed, start-up done
        if not first.startswith("recording "):
            raise RuntimeError(f"bag record did not start: {first.strip()}")
        # The recorder's CPU while it records (its start-up, imports included, is not counted).
        cpu_before = _children_cpu_s() + _cpu_s(recorder.pid)
        line = publisher.stdout.readline()
        published = json.loads(line[len("RESULT "):])
        if "error" in published:
            raise RuntimeError(published["error"])
        time.sleep(1.0)  # the last frames reach the recorder
        stopped = time.monotonic()
        recorder.send_signal(signal.SIGINT)
        out, err = recorder.communicate(timeout=600)
        out = first + out
        finish_s = time.monotonic() - stopped
        recorder_cpu_s = _children_cpu_s() - cpu_before
        publisher.stdin.write("done\n")
        publisher.stdin.flush()
        publisher.wait(timeout=60)
        if recorder.returncode != 0:
            raise RuntimeError(f"bag record exited {recorder.returncode}: {err.strip()}")
        return {"backend": backend, **published, **_bag_figures(bag), "report": out.strip(),
                "finish_s": finish_s, "recorder_cpu_s": recorder_cpu_s,
                "dropped": _counted(out, "because the disk"), "lost": _counted(out, "lost before")}
    finally:
        for proc in (recorder, publisher):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait()
        shutil.rmtree(bag, ignore_errors=True)


def _counted(report: str, words: str) -> int:
    """A count from the recorder's last line, e.g. ``0 because the disk ...``."""
    last = report.splitlines()[-1]
    head = last.split(words)[0].split(",")[-1].split(":")[-1].split()
    return int(head[-1])


def _bag_figures(bag: pathlib.Path) -> dict[str, Any]:
    from rosbags.rosbag2 import Reader

    stamps, nbytes = [], 0
    with Reader(bag) as reader:
        for _, timestamp, raw in reader.messages():
            stamps.append(timestamp)
            nbytes += len(raw)
    span = (max(stamps) - min(stamps)) / 1e9 if len(stamps) > 1 else 0.0
    return {"recorded": len(stamps), "bytes": nbytes, "span_s": span,
            "bag_bytes": sum(p.stat().st_size for p in bag.iterdir())}


# --------------------------------------------------------------------------- report
COLUMNS = ("published", "recorded", "dropped", "lost", "MiB/s", "pub/s", "CPU ms/frame",
           "finish s")


def figures(row: dict[str, Any]) -> dict[str, float]:
    """One measurement's table columns."""
    return {"published": row["published"], "recorded": row["recorded"],
            "dropped": row["dropped"], "lost": row["lost"],
            "MiB/s": row["bytes"] / MIB / row["span_s"] if row["span_s"] else 0.0,
            "pub/s": row["published"] / row["seconds"],
            "CPU ms/frame": 1e3 * row["recorder_cpu_s"] / max(row["recorded"], 1),
            "finish s": row["finish_s"]}


def header(args: argparse.Namespace) -> str:
    offered = args.rate * args.size / MIB
    return (f"bag record: {format_size(args.size)} frames offered at {args.rate:g}/s "
            f"({offered:.0f} MiB/s) for {args.seconds:g} s, {args.storage}, cache "
            f"{format_size(args.max_cache_size)}\n"
            f"{'':<14}" + " ".join(f"{c:>12}" for c in COLUMNS))


def line(label: str, values: dict[str, float]) -> str:
    return f"{label:<14}" + " ".join(
        f"{values[c]:>12.{2 if c == 'finish s' else 1 if '/' in c else 0}f}" for c in COLUMNS)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bag_record",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=5.0, help="publishing time (5)")
    parser.add_argument("--size", type=parse_size, default=16 << 20, help="frame bytes (16M)")
    parser.add_argument("--rate", type=float, default=DEMO_RATE, help="frames/s (the demo's 50)")
    parser.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap")
    parser.add_argument("--backends", default="warp,cpu", help="recorder backends (warp,cpu)")
    parser.add_argument("--rounds", type=int, default=3,
                        help="measurements per backend, in turn; medians reported (3)")
    parser.add_argument("--max-cache-size", type=int, default=512 << 20,
                        help="the recorder's cache, bytes (its default, 512 MiB)")
    parser.add_argument("--dir", type=pathlib.Path, default=None,
                        help="where bags are written (default: a temporary directory)")
    parser.add_argument("--json", type=pathlib.Path, default=None,
                        help="also write every figure to this file")
    parser.add_argument("--publish", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--domain", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--topic", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.publish:
        return publish(args.domain, args.topic, args.size, args.rate, args.seconds)
    rows = []
    backends = args.backends.split(",")
    print(header(args), flush=True)
    with tempfile.TemporaryDirectory(prefix="bag_record_", dir=args.dir) as where:
        for round_ in range(1, args.rounds + 1):  # backends in turn: the load drifts
            for backend in backends:
                rows.append(measure(backend, args, pathlib.Path(where)))
                print(line(f"{backend} #{round_}", figures(rows[-1])), flush=True)
    for backend in backends:
        mine = [figures(r) for r in rows if r["backend"] == backend]
        print(line(f"{backend} median", {c: statistics.median(f[c] for f in mine)
                                          for c in COLUMNS}))
    if args.json is not None:
        args.json.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()},
                                         "rows": rows}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
