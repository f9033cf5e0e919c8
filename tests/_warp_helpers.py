"""Child-process programs and shared helpers for the warp_buffer / warp backend tests.

Run a child as ``python -m tests._warp_helpers <command> <json argument>`` from the repository
root (the module keeps one stable name, so its Warp kernel is compiled once per machine).
Protocol on stdout: ``RESULT <json>`` lines; a child then waits for a line on stdin (or is
killed). ``nofile`` on :class:`Child` runs it under ``ulimit -n`` of that many fds.

Commands:
- ``import``: import descriptors (``{"descriptors": [hex of warp_buffer.descriptor.pack]}``) or a
  CDR-serialized message (``{"cdr": hex, "publisher": {...}}``), report each one's checksum and
  the zero-copy evidence (the mapping behind its address), then hold them until told.
- ``publish``: allocate ``count`` buffers, fill buffer i with :func:`fill_pattern` (seed + i),
  export each (for the delivery slot of ``peer_pid`` when given), report the descriptors, then
  hold until told, or exit cleanly at once (``"exit": true``).
- ``flood``: publish ``count`` numbered frames for ``peer_pid``, dropping each at once (so only
  delivery accounting and holds keep their blocks), appending the descriptors to ``path``; then
  on each ``more <n>`` line publish n more; report fds and pool counters each time.
- ``shrink``: fetch the arena of ``owner_pid``/``session`` as a peer does and try to shrink,
  grow and re-seal it; report each attempt's errno.
- ``holdall``: on a first stdin line, import every descriptor in ``path`` and keep them all;
  report fds and whether every frame is intact; on each ``check`` line verify them again.
"""

from __future__ import annotations

import json
import os
import pathlib
import resource
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

    def __init__(self, command: str, argument: dict[str, Any], env: dict[str, str] | None = None,
                 nofile: int | None = None):
        full_env = dict(os.environ)
        full_env.update(env or {})

        def limit() -> None:  # runs in the child before exec
            if nofile is not None:
                resource.setrlimit(resource.RLIMIT_NOFILE, (nofile, nofile))

        self.process = subprocess.Popen(
            [sys.executable, "-m", MODULE, command, json.dumps(argument)],
            cwd=ROOT, env=full_env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
            stderr=subprocess.PIPE, text=True, preexec_fn=limit,
        )

    def send(self, line: str) -> None:
        assert self.process.stdin is not None
        self.process.stdin.write(line + "\n")
        self.process.stdin.flush()

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


def fd_count() -> int:
    return len(os.listdir("/proc/self/fd"))


def frame_fill(data: np.ndarray, index: int) -> None:
    """Frame ``index`` of a flood: its number in the first 8 bytes, ``index % 251`` after."""
    data[8:] = index % 251
    data[:8] = np.frombuffer(np.uint64(index).tobytes(), np.uint8)


def frame_ok(data: np.ndarray, index: int) -> bool:
    return (int(data[:8].view(np.uint64)[0]) == index and int(data[8]) == index % 251
            and int(data[-1]) == index % 251)


def _descriptors(argument: dict[str, Any]) -> list[Any]:
    from warp_buffer import descriptor

    return [descriptor.unpack(bytes.fromhex(h)) for h in argument["descriptors"]]


def _cmd_import(argument: dict[str, Any]) -> None:
    from rosidl_buffer import Buffer
    from warp_buffer import from_input_buffer, ipc
    from warp_buffer.errors import WarpBufferError

    try:
        if "descriptors" in argument:
            impls = [ipc.import_buffer(d) for d in _descriptors(argument)]
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
            impls = [getattr(msg, argument["field"]).get_impl()]
    except WarpBufferError as exc:
        _report({"error": type(exc).__name__, "message": str(exc)})
        return
    records = []
    for impl in impls:
        buffer = Buffer(impl)
        with from_input_buffer(buffer) as view:
            records.append({"backend": buffer.get_backend_type(), "size": len(buffer),
                            "crc": checksum(view.array.numpy()), "mapping": mapping_of(view.ptr),
                            "device": view.device})
    _report({**records[0], "records": records, "fds": fd_count()})
    _hold()


def _cmd_publish(argument: dict[str, Any]) -> None:
    from warp_buffer import allocate_buffer, descriptor, from_output_buffer, ipc

    peer = None
    if argument.get("peer_pid"):
        peer = ipc.peer_slot(b"test-peer", argument["peer_pid"])
    buffers, descriptors, crcs = [], [], []
    for i in range(argument.get("count", 1)):
        buffer = allocate_buffer(argument["nbytes"], "cpu")
        with from_output_buffer(buffer) as out:
            fill_pattern(out.array, argument["seed"] + i)
        descriptors.append(descriptor.pack(ipc.export_buffer(buffer, peer=peer)).hex())
        crcs.append(checksum(buffer.to_numpy()))
        buffers.append(buffer)
    _report({"descriptors": descriptors, "crcs": crcs, "crc": crcs[0], "fds": fd_count()})
    if argument.get("exit"):
        return  # a clean exit with the descriptors still queued at the peer
    _hold()


def _cmd_shrink(argument: dict[str, Any]) -> None:
    """Fetch a session's arena as a peer does, try to shrink, grow and re-seal it, and report
    each attempt's errno (0 where it worked)."""
    import errno
    import fcntl

    from warp_buffer import handoff

    fd, geometry = handoff.fetch_arena(argument["owner_pid"], argument["session"])
    outcomes = {}
    attempts = {"shrink_to_0": lambda: os.ftruncate(fd, 0),
                "shrink_by_a_page": lambda: os.ftruncate(fd, geometry.file_size - 4096),
                "grow": lambda: os.ftruncate(fd, geometry.file_size + 4096),
                "seal_writes": lambda: fcntl.fcntl(fd, fcntl.F_ADD_SEALS, fcntl.F_SEAL_WRITE)}
    for name, attempt in attempts.items():
        try:
            attempt()
            outcomes[name] = 0
        except OSError as exc:
            outcomes[name] = exc.errno
    outcomes["size_after"] = os.fstat(fd).st_size
    os.close(fd)
    _report({"outcomes": outcomes, "eperm": errno.EPERM, "size": geometry.file_size})


def _cmd_flood(argument: dict[str, Any]) -> None:
    import warp_buffer
    from warp_buffer import allocate_buffer, descriptor, from_output_buffer, ipc

    peer = ipc.peer_slot(b"flood-peer", argument["peer_pid"])
    published = 0
    fds_before = fd_count()
    with open(argument["path"], "ab", buffering=0) as out_file:
        count = argument["count"]
        while True:
            for _ in range(count):
                buffer = allocate_buffer(argument["nbytes"], "cpu")
                with from_output_buffer(buffer) as out:
                    frame_fill(out.array.numpy(), published)
                out_file.write(descriptor.pack(ipc.export_buffer(buffer, peer=peer)))
                published += 1
                del buffer, out  # back to the pool: only the peer's accounting pins it
            _report({"published": published, "fds_before": fds_before, "fds": fd_count(),
                     "pool": warp_buffer.pool_stats()["cpu"]})
            line = sys.stdin.readline().split()
            if not line or line[0] != "more":
                return
            count = int(line[1])


def _cmd_holdall(argument: dict[str, Any]) -> None:
    from warp_buffer import descriptor, ipc

    fds_before = fd_count()
    sys.stdin.readline()  # the parent says when the descriptors are all there
    raw = pathlib.Path(argument["path"]).read_bytes()
    size = descriptor.LAYOUT.size
    held = [ipc.import_buffer(descriptor.unpack(raw[i:i + size]))
            for i in range(0, len(raw), size)]

    def intact() -> int:
        return sum(frame_ok(impl.host, i) for i, impl in enumerate(held))

    maps = sum(1 for line in open("/proc/self/maps") if "memfd:warp_buffer" in line)
    _report({"held": len(held), "intact": intact(), "fds_before": fds_before, "fds": fd_count(),
             "maps": maps})
    while sys.stdin.readline().strip() == "check":
        _report({"held": len(held), "intact": intact(), "fds": fd_count()})


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    wp.config.log_level = wp.LOG_WARNING  # keep stdout for the protocol
    command, argument = argv[0], json.loads(argv[1])
    commands = {"import": _cmd_import, "publish": _cmd_publish, "flood": _cmd_flood,
                "holdall": _cmd_holdall, "shrink": _cmd_shrink}
    commands[command](argument)


if __name__ == "__main__":
    main()
