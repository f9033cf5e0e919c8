"""Child-process entry: ``python -m benchmarks.child --role send|recv|both --spec JSON``.

The sending (or single, for ``both``) child prints one JSON line on stdout with every figure it
measured; progress goes to stderr. Control and acknowledgement pipes come as inherited file
descriptors (``--ctrl-fd`` / ``--ack-fd``) from the runner, or are made here for ``both``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing
import os
import sys
import threading
import traceback
from multiprocessing.connection import Connection
from typing import Any

from benchmarks.paths import PathSettings, PathUnavailable, load_path
from benchmarks.protocol import (
    ReceiverUnavailable,
    SenderDriver,
    progress,
    serve_receiver,
)
from benchmarks.shm import mapped_shm_files, note_mapped_shm_files
from benchmarks.stats import format_size, summarize_latency


def receiver_entry(settings: PathSettings, shared: Any, ctrl: Connection, ack: Connection) -> None:
    """Build the path's receiver and serve the sender until it says stop."""
    try:
        receiver = load_path(settings.name).make_receiver(settings, shared)
    except Exception as error:  # reported to the sender, which records the path as unavailable
        ack.send_bytes(json.dumps({"unavailable": _reason(error)}).encode())
        return
    serve_receiver(receiver, ctrl, ack)


def _reason(error: BaseException) -> str:
    if isinstance(error, PathUnavailable):
        return str(error)
    return f"{type(error).__name__}: {error}"


def _measure(settings: PathSettings, plan: dict, driver: SenderDriver) -> dict:
    """Run the latency phase for every size, then the rate phase."""
    result: dict[str, Any] = {"latency": {}, "errors": []}
    for nbytes in plan["sizes"]:
        try:
            samples = driver.latency(nbytes, plan["iterations"], plan["warmup"], plan["budget_s"])
        except ReceiverUnavailable:
            raise
        except Exception as error:  # noqa: BLE001 - recorded in the report
            result["errors"].append(f"{format_size(nbytes)}: {_reason(error)}")
            progress(f"  [{settings.name}] {format_size(nbytes):>8}: FAILED ({_reason(error)})")
            break  # larger sizes would fail the same way; the rate phase still runs
        summary = summarize_latency(samples)
        result["latency"][str(nbytes)] = summary
        progress(f"  [{settings.name}] {format_size(nbytes):>8}: p50 {summary['p50_us']:10.1f} us"
                 f"  p99 {summary['p99_us']:10.1f} us  (n={summary['samples']})")
    rate = plan["rate"]
    try:
        result["rate"] = driver.rate(rate["nbytes"], rate["count"], rate["window"],
                                     rate["budget_s"])
        progress(f"  [{settings.name}] rate {format_size(rate['nbytes'])}: "
                 f"{result['rate']['msgs_per_s']:.0f} msg/s")
    except ReceiverUnavailable:
        raise
    except Exception as error:  # noqa: BLE001 - recorded in the report
        result["errors"].append(f"rate: {_reason(error)}")
    return result


def run_sender(settings: PathSettings, plan: dict, shared: Any, ctrl: Connection,
               ack: Connection) -> dict:
    """Build the sender, measure, stop the receiver; the result dict (or its unavailability)."""
    try:
        sender = load_path(settings.name).make_sender(settings, shared)
    except Exception as error:
        SenderDriver(_NullSender(), ctrl, ack).stop(timeout_s=2.0)
        return {"unavailable": _reason(error)}
    driver = SenderDriver(sender, ctrl, ack, timeout_s=plan["timeout_s"])
    try:
        result = _measure(settings, plan, driver)
        note_mapped_shm_files()
        copies = getattr(sender, "report", None)
        result["sender_report"] = dict(copies()) if callable(copies) else {}
    except ReceiverUnavailable as error:
        return {"unavailable": str(error)}
    finally:
        receiver_report = driver.stop()
        sender.close()
    if "unavailable" in receiver_report:
        return {"unavailable": receiver_report["unavailable"]}
    result["receiver_report"] = receiver_report
    return result


class _NullSender:
    """Stands in for a sender that could not be built, to stop the receiver cleanly."""

    def prepare(self, nbytes: int) -> None: ...
    def send(self, seq: int) -> None: ...
    def close(self) -> None: ...


def _run_both(settings: PathSettings, plan: dict, topology: str) -> dict:
    """Sender here, receiver on a thread (``thread``) or in a spawned process (``spawn``)."""
    module = load_path(settings.name)
    if topology == "spawn":
        try:
            context, shared = module.make_shared(settings)
        except Exception as error:
            return {"unavailable": _reason(error)}
    else:
        context, shared = multiprocessing.get_context("spawn"), None
    ctrl_recv, ctrl_send = context.Pipe(duplex=False)
    ack_recv, ack_send = context.Pipe(duplex=False)
    args = (settings, shared, ctrl_recv, ack_send)
    worker: threading.Thread | multiprocessing.Process
    if topology == "spawn":
        worker = context.Process(target=receiver_entry, args=args, daemon=True)
    else:
        worker = threading.Thread(target=receiver_entry, args=args, daemon=True)
    worker.start()
    try:
        return run_sender(settings, plan, shared, ctrl_send, ack_recv)
    finally:
        worker.join(timeout=10.0)
        if isinstance(worker, multiprocessing.process.BaseProcess) and worker.is_alive():
            worker.kill()
            worker.join(timeout=5.0)


def main(argv: list[str] | None = None) -> int:
    """Parse the role and spec, run that role; the sending role prints its JSON result."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.child")
    parser.add_argument("--role", choices=("send", "recv", "both"), required=True)
    parser.add_argument("--spec", required=True, help="JSON: settings and plan")
    parser.add_argument("--ctrl-fd", type=int)
    parser.add_argument("--ack-fd", type=int)
    args = parser.parse_args(argv)
    spec = json.loads(args.spec)
    settings = PathSettings(**spec["settings"])
    plan = spec["plan"]
    try:
        if args.role == "recv":
            receiver_entry(settings, None, Connection(args.ctrl_fd, writable=False),
                           Connection(args.ack_fd, readable=False))
            result = {}
        elif args.role == "send":
            result = run_sender(settings, plan, None, Connection(args.ctrl_fd, readable=False),
                                Connection(args.ack_fd, writable=False))
        else:
            result = _run_both(settings, plan, spec["topology"])
    except Exception:
        traceback.print_exc()
        result = {"error": traceback.format_exc(limit=3).strip().splitlines()[-1]}
    result["shm_files"] = mapped_shm_files()
    result["pid"] = os.getpid()
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
