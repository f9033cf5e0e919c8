"""warp-buffer: move Warp (GPU or cpu) buffers between processes over Zenoh, ROS 2 style."""

from __future__ import annotations

import argparse
import importlib
import sys

# subcommand -> (module, help). Modules load lazily: `info` must not pay for torch or Zenoh.
_COMMANDS = {
    "info": ("warp_buffer_cli.info", "list buffer backends, Warp devices and IPC support"),
    "demo": ("warp_buffer_cli.demo",
             "run the publisher / warp subscriber / CPU subscriber demo over Zenoh"),
    "bench": ("benchmarks.run", "measure latency, rate and copies against peer transports"),
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="warp-buffer", description=__doc__)
    subcommands = parser.add_subparsers(dest="command", required=True)
    argv = sys.argv[1:] if argv is None else argv
    chosen = argv[0] if argv and argv[0] in _COMMANDS else None
    for name, (module_name, help_text) in _COMMANDS.items():
        sub = subcommands.add_parser(name, help=help_text)
        if name == chosen:
            module = importlib.import_module(module_name)
            module.add_arguments(sub)
            sub.set_defaults(run=module.run)
    args = parser.parse_args(argv)
    return int(args.run(args))


if __name__ == "__main__":
    sys.exit(main())
