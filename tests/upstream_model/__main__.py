"""Run one model participant as a child process.

    python -m tests.upstream_model {pub,sub,legacy-pub,legacy-sub} --domain D --topic T
        --type pkg/msg/Name [options]

stdout carries two lines at most: ``READY`` once the endpoint's token is declared (a publisher:
and ``--wait-subs`` subscriptions are discovered), then ``RESULT <json>`` at the end. Logs go to
stderr. A subscription ends when stdin closes (unless ``--no-stdin``), after ``--timeout``
seconds, after ``--count`` samples, or on SIGTERM / SIGINT; a publisher once it has published
``--count`` messages (and, with ``--hold``, stdin closed). See README.md for the JSON.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import select
import signal
import sys
import time
from typing import Any

from tests.upstream_model import qos as qos_model
from tests.upstream_model.backends import parse_backend_options
from tests.upstream_model.messages import sample_message
from tests.upstream_model.peer import (BackendNotInstalled, Participant, Publisher, Subscription,
                                       make_config)

ROLES = ("pub", "sub", "legacy-pub", "legacy-sub")
log = logging.getLogger("upstream_model")


class _Stop(Exception):
    """SIGTERM: end the run cleanly."""


def _raise_stop(signum: int, frame: Any) -> None:
    raise _Stop


def _emit(line: str) -> None:
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m tests.upstream_model",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("role", choices=ROLES)
    parser.add_argument("--domain", type=int, required=True)
    parser.add_argument("--topic", required=True, help="fully qualified, e.g. /camera/image")
    parser.add_argument("--type", required=True, help="ROS type name, e.g. sensor_msgs/msg/Image")
    parser.add_argument("--node-name", help="default: upstream_model_<role>_<pid>")
    parser.add_argument("--namespace", default="/")
    parser.add_argument("--enclave", default="/")
    parser.add_argument("--backend", action="append", default=[], metavar="NAME[=METADATA]",
                        help="an installed fake backend (repeatable)")
    parser.add_argument("--reliability", choices=["reliable", "best_effort"], default="reliable")
    parser.add_argument("--durability", choices=["volatile", "transient_local"],
                        default="volatile")
    parser.add_argument("--history", choices=["keep_last", "keep_all"], default="keep_last")
    parser.add_argument("--depth", type=int, default=10)
    parser.add_argument("--zenoh-config", help="Zenoh JSON5 file (default: "
                        "$ZENOH_SESSION_CONFIG_URI, else loopback peer discovery)")
    parser.add_argument("--connect", action="append", default=[], metavar="ENDPOINT")
    parser.add_argument("--listen", action="append", default=[], metavar="ENDPOINT")
    parser.add_argument("--timeout", type=float, default=30.0,
                        help="pub: longest wait for --wait-subs / --go / --hold; sub: run time")
    parser.add_argument("--count", type=int, default=None,
                        help="pub: messages to publish (default 10); sub: stop after N samples")
    parser.add_argument("--no-stdin", action="store_true", help="do not watch stdin")
    parser.add_argument("--graph-token", action="append", default=[],
                        metavar="KIND:NAME=TYPE",
                        help="also declare this token alone (graph only): SS, SC, MP or MS, "
                             "e.g. SS:/node/get_parameters=rcl_interfaces/srv/GetParameters")
    pub = parser.add_argument_group("publisher")
    pub.add_argument("--rate", type=float, default=10.0, help="publishes per second")
    pub.add_argument("--size", type=int, default=1024, help="bytes in each buffer field")
    pub.add_argument("--wait-subs", type=int, default=0,
                     help="print READY once this many subscriptions are discovered")
    pub.add_argument("--buffer-backend", default="cpu",
                     help="installed fake backend the buffers live in (default cpu)")
    pub.add_argument("--go", action="store_true",
                     help="after READY, wait for a line on stdin before publishing")
    pub.add_argument("--linger", type=float, default=0.5,
                     help="seconds to stay after the last publish")
    pub.add_argument("--hold", action="store_true",
                     help="after publishing, stay until stdin closes (or --timeout)")
    sub = parser.add_argument_group("subscription")
    sub.add_argument("--acceptable-buffer-backends", default=None,
                     help="rmw_subscription_options_t.acceptable_buffer_backends (absent = NULL)")
    return parser


def _qos(args: argparse.Namespace) -> qos_model.QoS:
    return qos_model.QoS(
        history=qos_model.History[args.history.upper()], depth=args.depth,
        reliability=qos_model.Reliability[args.reliability.upper()],
        durability=qos_model.Durability[args.durability.upper()])


class _Stdin:
    """Non-blocking view of stdin: ``wait`` returns "line", "eof" or "timeout"."""

    def __init__(self, enabled: bool) -> None:
        self.fd = sys.stdin.fileno() if enabled and sys.stdin is not None else None

    def wait(self, seconds: float) -> str:
        if self.fd is None:
            time.sleep(max(seconds, 0.0))
            return "timeout"
        ready, _, _ = select.select([self.fd], [], [], max(seconds, 0.0))
        if not ready:
            return "timeout"
        return "line" if os.read(self.fd, 4096) else "eof"


def _run_pub(args: argparse.Namespace, participant: Participant, result: dict[str, Any]) -> None:
    stdin = _Stdin(not args.no_stdin)
    pub = Publisher(participant, args.topic, args.type, _qos(args),
                    buffer_backend=args.buffer_backend)
    result["endpoint"] = pub
    deadline = time.monotonic() + args.timeout
    while pub.discovered_count() < args.wait_subs:
        if time.monotonic() > deadline:
            raise TimeoutError(f"{pub.discovered_count()} of {args.wait_subs} subscriptions "
                               f"discovered in {args.timeout} s")
        time.sleep(0.02)
    _emit("READY")
    if args.go:
        while (event := stdin.wait(deadline - time.monotonic())) == "timeout":
            if time.monotonic() > deadline:
                raise TimeoutError("no go line on stdin")
        if event == "eof":
            return
    count = 10 if args.count is None else args.count
    period = 1.0 / args.rate if args.rate > 0 else 0.0
    start = time.monotonic()
    for index in range(count):
        pub.publish(sample_message(participant.store, args.type, index, args.size), index)
        time.sleep(max(0.0, start + (index + 1) * period - time.monotonic()))
    time.sleep(args.linger)
    if args.hold:
        end = time.monotonic() + args.timeout
        while time.monotonic() < end and stdin.wait(end - time.monotonic()) != "eof":
            pass


def _run_sub(args: argparse.Namespace, participant: Participant, result: dict[str, Any]) -> None:
    stdin = _Stdin(not args.no_stdin)
    sub = Subscription(participant, args.topic, args.type, _qos(args),
                       acceptable_buffer_backends=args.acceptable_buffer_backends)
    result["endpoint"] = sub
    _emit("READY")
    deadline = time.monotonic() + args.timeout
    while time.monotonic() < deadline:
        if args.count and sub.sample_count() >= args.count:
            return
        if stdin.wait(min(0.05, deadline - time.monotonic())) == "eof":
            return


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    signal.signal(signal.SIGINT, signal.default_int_handler)  # a background job ignores it
    signal.signal(signal.SIGTERM, _raise_stop)
    logging.basicConfig(stream=sys.stderr, level=os.environ.get("UPSTREAM_MODEL_LOG", "WARNING"),
                        format="upstream_model[%(process)d] %(levelname)s %(message)s")
    legacy = args.role.startswith("legacy-")
    result: dict[str, Any] = {"role": args.role, "error": None}
    participant = None
    code = 0
    try:
        participant = Participant(
            domain=args.domain, legacy=legacy, namespace=args.namespace, enclave=args.enclave,
            node_name=(args.node_name
                       or f"upstream_model_{args.role.replace('-', '_')}_{os.getpid()}"),
            config=make_config(args.zenoh_config, args.connect, args.listen),
            backends=parse_backend_options(args.backend))
        result.update(zid=participant.zid, node_token=participant.node.keyexpr,
                      node_gid=participant.node.gid_hex)
        for spec in args.graph_token:
            kind, _, rest = spec.partition(":")
            name, _, ros_type = rest.partition("=")
            participant.declare_graph_entity(kind, name, ros_type)
        (_run_pub if args.role.endswith("pub") else _run_sub)(args, participant, result)
    except _Stop:
        code = 0
    except KeyboardInterrupt:
        code = 130
    except (BackendNotInstalled, TimeoutError, ValueError, KeyError) as exc:
        print(f"upstream_model: {exc}", file=sys.stderr)
        result["error"] = str(exc)
        code = 2
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second SIGTERM must not cut RESULT
        endpoint = result.pop("endpoint", None)
        if participant is not None:
            participant.close()
        if endpoint is not None:
            result.update(endpoint.report())
        _emit("RESULT " + json.dumps(result, sort_keys=True))
    return code


if __name__ == "__main__":
    sys.exit(main())
