"""warp-buffer: move Warp (GPU or cpu) buffers between processes over Zenoh, ROS 2 style."""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import signal
import sys
from typing import Any

from rosidl_buffer.errors import RosidlBufferError

VERBOSE_ENV = "WARP_BUFFER_VERBOSE"  # read by warp_buffer.startup (not imported here: cost)

# subcommand -> (module, help). Modules load lazily: `info` must not pay for torch or Zenoh.
_COMMANDS = {
    "info": ("warp_buffer_cli.info", "list buffer backends, Warp devices and IPC support"),
    "demo": ("warp_buffer_cli.demo",
             "run the publisher / warp subscriber / CPU subscriber demo over Zenoh"),
    "bench": ("benchmarks.run", "measure latency, rate and copies against peer transports"),
    "router": ("warp_buffer_cli.router",
               "run a Zenoh router (rmw_zenoh's defaults) for nodes on several hosts"),
    # Groups of subcommands (warp_buffer_cli._groups): one module each, its leaves beside it.
    "topic": ("warp_buffer_cli.topic",
              "list topics, show their endpoints and routes, echo, measure rate and bandwidth"),
    "node": ("warp_buffer_cli.node", "list the nodes of the domain, show one's endpoints"),
    "bag": ("warp_buffer_cli.bag",
            "record topics to a rosbag2 bag (MCAP or sqlite3), play one back, describe one"),
}


def _configure_output(verbose: bool) -> None:
    """Logs (ours, Warp's, Zenoh's warnings) go to stderr; stdout is the command's own report.
    ``--verbose`` shows INFO logs and Warp's own banner and messages (env WARP_BUFFER_VERBOSE,
    which child processes inherit)."""
    if verbose:
        os.environ[VERBOSE_ENV] = "1"
    verbose = verbose or os.environ.get(VERBOSE_ENV, "").strip().lower() in ("1", "true", "yes",
                                                                              "on")
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, stream=sys.stderr,
                        format="%(name)s: %(levelname)s: %(message)s")


class StdoutWriteError(OSError):
    """The command's report could not be written to stdout (a full disk, an I/O error)."""


class _GuardedStdout:
    """``sys.stdout`` while a command runs: a write or flush that fails raises
    :class:`StdoutWriteError`, told apart from the command's own ``OSError`` (one line, not a
    traceback); a reader that left stays ``BrokenPipeError``."""

    def __init__(self, stream: Any) -> None:
        self._stream = stream

    def write(self, text: str) -> int:
        return self._guarded(self._stream.write, text)

    def flush(self) -> None:
        self._guarded(self._stream.flush)

    @staticmethod
    def _guarded(call: Any, *args: Any) -> Any:
        try:
            return call(*args)
        except BrokenPipeError:
            raise
        except OSError as exc:
            raise StdoutWriteError(exc.errno, exc.strerror) from None

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


def _silence_stdout() -> None:
    """Point descriptor 1 at /dev/null: the interpreter's last flush must not fail again."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)


def main(argv: list[str] | None = None) -> int:
    """Run one ``warp-buffer`` command; its exit status."""
    stream = sys.stdout
    # A closed descriptor 1 (`>&-`) leaves sys.stdout None: the report goes nowhere, as
    # print() does then, rather than failing at the first flush.
    sys.stdout = _GuardedStdout(stream if stream is not None else open(os.devnull, "w"))
    try:
        return _main(argv)
    finally:
        sys.stdout = stream


def _main(argv: list[str] | None) -> int:
    parser = argparse.ArgumentParser(prog="warp-buffer", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true",
                        help="log at INFO on stderr and let Warp print its own start-up banner "
                             "(same as env WARP_BUFFER_VERBOSE=1)")
    subcommands = parser.add_subparsers(dest="command", required=True)
    argv = sys.argv[1:] if argv is None else argv
    chosen = next((a for a in argv if not a.startswith("-")), None)
    for name, (module_name, help_text) in _COMMANDS.items():
        sub = subcommands.add_parser(name, help=help_text)
        if name == chosen:
            module = importlib.import_module(module_name)
            module.add_arguments(sub)
            if hasattr(module, "run"):  # a group's leaves set their own
                sub.set_defaults(run=module.run)
    args = parser.parse_args(argv)
    _configure_output(args.verbose)
    # Ctrl-C ends a command even when it was started from a background job (nohup, &, a CI
    # runner), which hands it an ignored SIGINT: as ros2's tools do (rclpy installs its handler
    # whatever it inherited).
    inherited = signal.signal(signal.SIGINT, signal.default_int_handler)
    name = getattr(args, "command_name", f"warp-buffer {args.command}")
    try:
        status = int(args.run(args))
        sys.stdout.flush()  # a report that cannot be written fails here, not at exit
        return status
    except StdoutWriteError as exc:
        print(f"{name}: cannot write to stdout: {exc.strerror}", file=sys.stderr)
        _silence_stdout()
        return 1
    except RosidlBufferError as exc:  # bad input the command found: one line, no traceback
        text = " ".join(str(exc).split())  # one line, whatever the message (a YAML parser's)
        print(f"{name}: {type(exc).__name__}: {text}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # Ctrl-C: one line, not a traceback (children were reaped)
        print(f"{name}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # stdout's reader left (| head -1): nothing more to write there
        _silence_stdout()
        return 141
    except OSError as exc:  # the system refused (a path it may not read): one line
        logging.getLogger("warp_buffer_cli").info("%s failed", name, exc_info=True)  # (-v)
        print(f"{name}: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    finally:
        signal.signal(signal.SIGINT, inherited)  # main() called in a program leaves it as found


if __name__ == "__main__":
    sys.exit(main())
