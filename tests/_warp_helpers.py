"""Child-process programs and shared helpers for the warp_buffer / warp backend tests.

Run a child as ``python -m tests._warp_helpers <command> <json argument>`` from the repository
root (the module keeps one stable name, so its Warp kernel is compiled once per machine).
Protocol on stdout: one line ``RESULT <json>``; a holding child then waits until the parent
writes a line to its stdin (or kills it).

Commands:
- ``import``: import an export record (``{"record": ...}``) or a CDR-serialized descriptor
  (``{"cdr": hex, "publisher": {...}}``), report its checksum and the zero-copy evidence (the
  array's address lies in a mapping of the export's /dev/shm file), then hold it until told.
- ``publish``: allocate a buffer, fill it with :func:`fill_pattern` (a Warp kernel), export it,
  report the record, then hold until told (or SIGKILLed).
"""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys
import time
import zlib
from typing import Any

import numpy as np
import warp as wp

ROOT = pathlib.Path(__file__).resolve().parent.parent
MODULE = "tests._warp_helpers"


@wp.kernel
def _pattern_kernel(out: wp.array(dtype=wp.uint32), seed: wp.uint32):
    i = wp.tid()
    out[i] = wp.uint32(i) * wp.uint32(2654435761) + seed


def fill_pattern(array: wp.array, seed: int) -> None:
    """Write the test pattern into a uint8 ``wp.array`` whose length is a multiple of 4."""
    words = wp.array(ptr=array.ptr, dtype=wp.uint32, shape=(array.shape[0] // 4,),
                     device=array.device)
    wp.launch(_pattern_kernel, dim=words.shape[0], inputs=[words, wp.uint32(seed)],
              device=array.device)


def expected_pattern(nbytes: int, seed: int) -> np.ndarray:
    words = (np.arange(nbytes // 4, dtype=np.uint64) * 2654435761 + seed) & 0xFFFFFFFF
    return words.astype("<u4").view(np.uint8)


def checksum(data: np.ndarray) -> int:
    return zlib.crc32(np.ascontiguousarray(data).view(np.uint8))


def mapping_of(address: int) -> str | None:
    """The file backing ``address`` in this process's address space, from /proc/self/maps."""
    with open("/proc/self/maps") as maps:
        for line in maps:
            parts = line.split(maxsplit=5)
            start, end = (int(x, 16) for x in parts[0].split("-"))
            if start <= address < end:
                return parts[5].strip() if len(parts) == 6 else ""
    return None


# --------------------------------------------------------------------------- parent side
class Child:
    """A helper child process; always use as a context manager (reaps it, even on failure)."""

    def __init__(self, command: str, argument: dict[str, Any], env: dict[str, str] | None = None):
        full_env = dict(os.environ)
        full_env.update(env or {})
        self.process = subprocess.Popen(
            [sys.executable, "-m", MODULE, command, json.dumps(argument)],
            cwd=ROOT, env=full_env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
            stderr=subprocess.PIPE, text=True,
        )

    def result(self, timeout: float = 60.0) -> dict[str, Any]:
        """The child's RESULT line (raises with its stderr if it died or timed out)."""
        deadline = time.monotonic() + timeout
        assert self.process.stdout is not None
        while time.monotonic() < deadline:
            line = self.process.stdout.readline()
            if not line:
                break
            if line.startswith("RESULT "):
                return json.loads(line[len("RESULT "):])
        self.process.kill()
        _, err = self.process.communicate(timeout=10)
        raise AssertionError(f"child gave no result (rc={self.process.returncode}): {err[-2000:]}")

    def finish(self, timeout: float = 30.0) -> int:
        """Tell a holding child to exit and reap it."""
        try:
            assert self.process.stdin is not None
            self.process.stdin.write("exit\n")
            self.process.stdin.flush()
        except (BrokenPipeError, OSError):
            pass
        return self.process.wait(timeout=timeout)

    def kill(self) -> None:
        self.process.kill()
        self.process.wait(timeout=30)

    def __enter__(self) -> Child:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.process.poll() is None:
            self.process.kill()
        self.process.wait(timeout=30)
        for stream in (self.process.stdin, self.process.stdout, self.process.stderr):
            if stream is not None:
                stream.close()


# --------------------------------------------------------------------------- child side
def _report(payload: dict[str, Any]) -> None:
    sys.stdout.write("RESULT " + json.dumps(payload) + "\n")
    sys.stdout.flush()


def _hold() -> None:
    sys.stdin.readline()


def _cmd_import(argument: dict[str, Any]) -> None:
    from warp_buffer import ipc
    from warp_buffer.errors import WarpBufferError

    try:
        if "record" in argument:
            impl = ipc.import_export(ipc.ExportRecord.from_dict(argument["record"]))
        else:
            from rosidl_buffer import EndpointInfo, EndpointType
            from rosidl_buffer.messages import deserialize_message
            from warp_buffer_backend import WarpBufferBackend

            publisher = dict(argument["publisher"])
            publisher["gid"] = bytes.fromhex(publisher["gid"])
            publisher["endpoint_type"] = EndpointType(publisher["endpoint_type"])
            msg = deserialize_message(bytes.fromhex(argument["cdr"]), argument["type"],
                                      backends={"warp": WarpBufferBackend()},
                                      endpoint_info=EndpointInfo(**publisher))
            impl = getattr(msg, argument["field"]).get_impl()
    except WarpBufferError as exc:
        _report({"error": type(exc).__name__, "message": str(exc)})
        return
    from warp_buffer import from_input_buffer
    from rosidl_buffer import Buffer

    buffer = Buffer(impl)
    with from_input_buffer(buffer) as view:
        data = view.array.numpy()
        _report({
            "backend": buffer.get_backend_type(),
            "size": len(buffer),
            "crc": checksum(data),
            "mapping": mapping_of(view.ptr),
            "device": view.device,
        })
    _hold()


def _cmd_publish(argument: dict[str, Any]) -> None:
    from warp_buffer import allocate_buffer, from_output_buffer, ipc

    buffer = allocate_buffer(argument["nbytes"], "cpu")
    with from_output_buffer(buffer) as out:
        fill_pattern(out.array, argument["seed"])
    record = ipc.export_buffer(buffer)
    _report({"record": record.to_dict(), "crc": checksum(buffer.to_numpy())})
    _hold()


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    wp.config.log_level = wp.LOG_WARNING  # keep stdout for the protocol
    command, argument = argv[0], json.loads(argv[1])
    {"import": _cmd_import, "publish": _cmd_publish}[command](argument)


if __name__ == "__main__":
    main()
