"""System calls one thread makes while something runs, counted with ``strace`` (attached to that
thread only), leaving out those on the file descriptors of the benchmark's own plumbing.

Used by ``benchmarks.lane_stages --syscalls N``: the per-message path of both sides runs on one
thread each (the publisher's loop, the subscriber's ``spin``), so their system calls per message
are what the path costs in kernel entries.
"""

from __future__ import annotations

import collections
import os
import re
import shutil
import signal
import subprocess
import tempfile
import time

__all__ = ["SyscallTrace", "available"]

#: ``name(first argument...`` of a traced call (strace's default line format): the argument when
#: it is a number (an fd), and the fds of a poll set
_CALL = re.compile(r"^(?:\[pid\s+\d+\]\s+)?([a-z0-9_]+)\((-?\d+(?=[,)]))?")
_POLLED = re.compile(r"\{fd=(\d+)")


def available() -> bool:
    """Whether ``strace`` is on PATH."""
    return shutil.which("strace") is not None


class SyscallTrace:
    """``strace`` attached to thread ``tid`` from :meth:`start` to :meth:`stop`; calls whose
    first argument is one of ``exclude_fds`` are not counted."""

    def __init__(self, tid: int, exclude_fds: set[int] = frozenset()) -> None:
        self.tid = tid
        self.exclude_fds = set(exclude_fds)
        self._file = tempfile.NamedTemporaryFile(prefix="lane_strace_", suffix=".txt",
                                                 delete=False)
        self._file.close()
        self._proc: subprocess.Popen | None = None

    def start(self, timeout: float = 10.0) -> None:
        """Attach, and return once the thread is traced."""
        self._proc = subprocess.Popen(["strace", "-qq", "-e", "signal=none", "-o",
                                       self._file.name, "-p", str(self.tid)],
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + timeout
        while not self._traced():
            if self._proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"strace could not attach to thread {self.tid}")
            time.sleep(0.01)

    def _traced(self) -> bool:
        try:
            with open(f"/proc/{self.tid}/status", encoding="ascii") as status:
                for line in status:
                    if line.startswith("TracerPid:"):
                        return int(line.split()[1]) != 0
        except OSError:
            return False
        return False

    def stop(self) -> collections.Counter[str]:
        """Detach; the calls made meanwhile, by name."""
        proc = self._proc
        if proc is not None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        counts: collections.Counter[str] = collections.Counter()
        try:
            with open(self._file.name, encoding="utf-8", errors="replace") as trace:
                for line in trace:
                    match = _CALL.match(line)
                    if match is None or "resumed>" in line:
                        continue
                    name, first = match.groups()
                    if first is not None and int(first) in self.exclude_fds:
                        continue
                    polled = {int(fd) for fd in _POLLED.findall(line)}
                    if polled and polled <= self.exclude_fds:
                        continue  # a poll of the plumbing alone
                    counts[name] += 1
        finally:
            os.unlink(self._file.name)
        return counts
