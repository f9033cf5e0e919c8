"""``warp-buffer router``: a Zenoh router run from Python, so that several hosts (or ROS 2 nodes
on rmw_zenoh) need nothing outside pip to meet.

It starts with rmw_zenoh's router defaults (:data:`buffer_pubsub.config.ROUTER_DEFAULTS`: listen on
``tcp/[::]:7447``, multicast scouting off, gossip on), prints one line with its Zenoh id and
endpoints, and runs until SIGINT or SIGTERM, when it closes its session and exits 0. Nodes use
it with ``WARP_BUFFER_ZENOH_ROUTER=tcp/<this host>:7447`` (or ``Node(router=...)``).
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import threading

_log = logging.getLogger("warp_buffer_cli.router")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--listen", action="append", metavar="ENDPOINT",
                        help="Zenoh endpoint to listen on, repeatable "
                             "(default: tcp/[::]:7447, rmw_zenoh's; tcp/0.0.0.0:7447 for IPv4 "
                             "only; unixsock-stream/PATH for a Unix socket)")
    parser.add_argument("--connect", action="append", metavar="ENDPOINT",
                        help="another router to connect to, repeatable (default: none)")
    parser.add_argument("--config", metavar="FILE",
                        help="a Zenoh JSON5 router configuration instead of the defaults "
                             "(--listen / --connect still replace its endpoints)")


def run(args: argparse.Namespace) -> int:
    import zenoh

    from buffer_pubsub.config import make_router_config, zenoh_error_text
    from buffer_pubsub.errors import TransportConfigError

    try:
        config = make_router_config(args.listen, args.connect, args.config)
        session = zenoh.open(config)
    except TransportConfigError as exc:
        print(f"warp-buffer router: {exc}", file=sys.stderr)
        return 2
    except zenoh.ZError as exc:
        print(f"warp-buffer router: cannot start: {zenoh_error_text(exc)}", file=sys.stderr)
        return 1
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    try:
        listen = json.loads(config.get_json("listen/endpoints"))
        print(f"warp-buffer router {session.zid()} listening on {', '.join(listen)} "
              f"(Ctrl-C to stop)", flush=True)
        while not stop.wait(0.5):  # a short wait keeps signals handled promptly
            pass
    finally:
        session.close()
    _log.info("router stopped")
    return 0
