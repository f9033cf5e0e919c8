"""Two "hosts" on one machine for ``tests/test_two_hosts.py``: Linux namespaces joined by a router.

``python -m tests._two_hosts_helpers host ...`` runs as the first process of fresh network, UTS,
IPC and mount namespaces (started by ``unshare``). It makes them look like another machine to the
library -- a private ``/dev/shm`` (tmpfs), its own host name and ``/etc/machine-id`` (the two
inputs of :func:`rosidl_buffer.local_host_id`), a private iceoryx2 directory, loopback up -- and
then starts its roles (``python -m tests._two_hosts_helpers role ...``), which inherit the
namespaces. No IP address joins the hosts: every node is a Zenoh client of one
``warp-buffer router`` listening on a Unix socket in a directory both hosts see.

Roles coordinate through files in that shared directory: ``<role>.ready`` once a subscriber has
matched every publisher, ``<role>.json`` with its result when done.
"""

from __future__ import annotations

import argparse
import fcntl
import json
import os
import pathlib
import socket
import struct
import subprocess
import sys
import time
from typing import Any

ROOT = pathlib.Path(__file__).resolve().parent.parent
TOPIC = "/two_hosts/frames"
SETUP_ERROR = "setup_error.txt"
_SIOCGIFFLAGS, _SIOCSIFFLAGS, _IFF_UP = 0x8913, 0x8914, 0x1


# --------------------------------------------------------------------------- host set-up
def _loopback_up() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        request = struct.pack("16sh", b"lo", 0)
        flags = struct.unpack("16sh", fcntl.ioctl(sock, _SIOCGIFFLAGS, request)[:18])[1]
        fcntl.ioctl(sock, _SIOCSIFFLAGS, struct.pack("16sh", b"lo", flags | _IFF_UP))


def _mount(*argv: str) -> None:
    done = subprocess.run(["mount", *argv], capture_output=True, text=True)
    if done.returncode != 0:
        raise OSError(f"mount {' '.join(argv)}: {done.stderr.strip()}")


def enter_host(name: str, machine_id: str, workdir: pathlib.Path) -> None:
    """Turn the current (freshly unshared) namespaces into host ``name``."""
    _mount("-t", "tmpfs", "-o", "mode=1777,size=512m", "tmpfs", "/dev/shm")
    os.makedirs("/tmp/iceoryx2", exist_ok=True)  # iceoryx2 keeps node files here, beside /dev/shm
    _mount("-t", "tmpfs", "-o", "mode=1777,size=16m", "tmpfs", "/tmp/iceoryx2")
    if os.path.exists("/etc/machine-id"):
        id_file = workdir / f"machine-id.{name}"
        id_file.write_text(machine_id + "\n")
        _mount("--bind", str(id_file), "/etc/machine-id")
    socket.sethostname(name)
    _loopback_up()


def run_host(args: argparse.Namespace) -> int:
    workdir = pathlib.Path(args.dir)
    try:
        enter_host(args.name, args.machine_id, workdir)
    except OSError as exc:
        (workdir / f"{args.name}.{SETUP_ERROR}").write_text(str(exc))
        return 3
    env = {k: v for k, v in os.environ.items() if not k.startswith("WARP_BUFFER_TEST_")}
    env["WARP_BUFFER_ZENOH_ROUTER"] = args.router
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH", "")) if p)
    children = []
    for role in args.roles.split(","):
        argv = [sys.executable, "-m", "tests._two_hosts_helpers", "role", role, "--dir",
                args.dir, "--domain", str(args.domain), "--count", str(args.count),
                "--timeout", str(args.timeout)]
        children.append(subprocess.Popen(argv, cwd=ROOT, env=env))
    deadline = time.monotonic() + args.timeout + 15
    codes = []
    for child in children:
        try:
            codes.append(child.wait(timeout=max(deadline - time.monotonic(), 0.1)))
        except subprocess.TimeoutExpired:
            child.kill()
            codes.append(child.wait())
    return max(codes, default=0)


# --------------------------------------------------------------------------- roles
def _write(workdir: pathlib.Path, name: str, data: Any) -> None:
    tmp = workdir / f".{name}.tmp"
    tmp.write_text(json.dumps(data))
    tmp.rename(workdir / name)  # readers never see half a file


def _identity() -> dict[str, Any]:
    from rosidl_buffer import local_host_id

    return {"host_id": local_host_id(), "hostname": socket.gethostname(),
            "shm": sorted(os.listdir("/dev/shm"))}


def run_subscriber(role: str, args: argparse.Namespace) -> int:
    from buffer_pubsub import Node
    from tests._pubsub_helpers import TENSOR, check_frame

    workdir = pathlib.Path(args.dir)
    records: list[dict[str, Any]] = []
    with Node(f"sub_{role}", domain_id=args.domain) as node:
        sub = node.create_subscription(TENSOR, TOPIC, lambda msg: records.append(check_frame(msg)),
                                       depth=2 * args.count, acceptable_buffer_backends="warp")
        matched = sub.wait_for_publishers(2, timeout=args.timeout)
        _write(workdir, f"{role}.ready", {"matched": matched})
        deadline = time.monotonic() + args.timeout
        while len(records) < 2 * args.count and time.monotonic() < deadline:
            time.sleep(0.02)
        time.sleep(0.2)  # a duplicate would land in this window
        result = {"matched": matched, "records": list(records), **_identity()}
    _write(workdir, f"{role}.json", result)
    return 0


def _wait_for(workdir: pathlib.Path, names: list[str], timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if all((workdir / name).exists() for name in names):
            return True
        time.sleep(0.05)
    return False


def run_publisher(role: str, args: argparse.Namespace) -> int:
    from buffer_pubsub import Node
    from tests._pubsub_helpers import TENSOR, make_frame

    workdir = pathlib.Path(args.dir)
    pub_id = 1 if role == "pub_a" else 2
    with Node(f"pub_{role}", domain_id=args.domain) as node:
        pub = node.create_publisher(TENSOR, TOPIC, depth=2 * args.count)
        matched = pub.wait_for_subscriptions(2, timeout=args.timeout)
        ready = _wait_for(workdir, ["sub_a.ready", "sub_b.ready"], args.timeout)
        for index in range(args.count):
            pub.publish(make_frame(pub_id, index, 4096, "warp"))
            time.sleep(0.01)
        # Keep the exported blocks alive until both subscribers have read every frame.
        _wait_for(workdir, ["sub_a.json", "sub_b.json"], args.timeout)
        result = {"matched": matched, "ready": ready, "pub_id": pub_id, **_identity()}
    _write(workdir, f"{role}.json", result)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="tests._two_hosts_helpers")
    parser.add_argument("kind", choices=["host", "role"])
    parser.add_argument("name", help="host: its host name; role: pub_a, pub_b, sub_a or sub_b")
    parser.add_argument("--dir", required=True)
    parser.add_argument("--domain", type=int, required=True)
    parser.add_argument("--count", type=int, default=10)
    parser.add_argument("--timeout", type=float, default=30.0)
    parser.add_argument("--router", default="")
    parser.add_argument("--machine-id", default="")
    parser.add_argument("--roles", default="")
    args = parser.parse_args(argv)
    if args.kind == "host":
        return run_host(args)
    if args.name.startswith("sub_"):
        return run_subscriber(args.name, args)
    return run_publisher(args.name, args)


if __name__ == "__main__":
    sys.exit(main())
