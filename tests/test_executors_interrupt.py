"""Ctrl-C while a callback runs: the program ends cleanly, whichever executor runs the callback.

A child relay node gets SIGINT while its callback sleeps before publishing (see
``tests/_executor_children.py``). Closing the node raced the callback: ``close()`` undeclared the
publisher while the callback still held it, and its publish printed a ``NodeClosedError``
traceback on stderr. Now ``close()`` waits for the running callback (within its budget) first,
and a publish that still loses that race is no error the user sees.
"""

from __future__ import annotations

import signal
import subprocess
import sys

import pytest

from tests._pubsub_helpers import ROOT, child_env

pytestmark = pytest.mark.multiprocess


def _interrupted_during_a_callback(mode: str, domain: int, topic: str) -> tuple[int, str, str]:
    proc = subprocess.Popen([sys.executable, "-m", "tests._executor_children", mode, str(domain),
                             topic], cwd=ROOT, env=child_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        lines = []
        for line in proc.stdout:
            lines.append(line)
            if line.startswith("IN_CALLBACK"):
                proc.send_signal(signal.SIGINT)
                break
        out, err = proc.communicate(timeout=30)
        return proc.returncode, "".join(lines) + out, err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


@pytest.mark.parametrize("mode", ["thread", "manual", "single", "multi"])
def test_ctrl_c_during_a_publishing_callback_ends_without_a_traceback(mode, domain, topic):
    code, out, err = _interrupted_during_a_callback(mode, domain, topic)
    assert "IN_CALLBACK" in out and "INTERRUPTED" in out, (out, err)
    assert "Traceback" not in err and "NodeClosedError" not in err, err
    assert code == 0, (code, err)
    if mode in ("thread", "multi"):
        # The callback ran on a thread of the library: closing the node waited for it, so its
        # publish went out before the publisher was undeclared.
        assert "CALLBACK_DONE" in out, (out, err)
