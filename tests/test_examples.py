"""The example pipelines of ``examples/`` run as a user runs them, one process per stage.

Each stage is started with its own domain and namespace, stopped by SIGTERM (which the examples
take as Ctrl-C) or its ``--duration``, and prints a ``<stage> summary {json}`` line. Every stage
checks the content it got against the test pattern of its stamp, so the asserts are delivery
counts (some, not all: a loaded machine drops keep-last frames) and zero wrong ones.
"""

from __future__ import annotations

import ast
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator

import pytest

from tests._pubsub_helpers import ROOT, Child, child_env

pytestmark = pytest.mark.multiprocess

EXAMPLES = ROOT / "examples"
#: Seconds a stage may take to start (imports, a cold Warp kernel compile) or to finish.
START_S, FINISH_S = 120.0, 60.0


class Stage(Child):
    """One example process, reaped by ``close``; reads its ``<stage> <word> ...`` lines."""

    def __init__(self, script: str, argv: list[str], env: dict[str, str]) -> None:
        self.stage = script.removesuffix(".py")
        self._start(script, argv, env, stderr=subprocess.PIPE)

    def expect(self, word: str, timeout: float) -> str:
        """The next line ``<stage> <word> ...``."""
        return self._expect(f"{self.stage} {word}", timeout)

    def finish(self, stop: bool = True) -> dict:
        """Stop it (SIGTERM, which the examples take as Ctrl-C) unless it ends by itself; its
        summary, once it exited cleanly."""
        if stop and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        line = self.expect("summary", FINISH_S)
        self.proc.wait(timeout=FINISH_S)
        assert self.proc.stderr is not None
        err = self.proc.stderr.read()
        assert self.proc.returncode == 0, (self.name, self.proc.returncode, err[-3000:])
        assert "Traceback" not in err, err[-3000:]
        return json.loads(line.split(" ", 2)[2])


class Pipeline:
    """Starts stages of one test (own domain and namespace); kills what is left at the end."""

    def __init__(self, domain: int, topic: str) -> None:
        self.common = ["--domain", str(domain), "--namespace", topic]
        self.stages: list[Stage] = []

    def start(self, script: str, *args: str, **env: str) -> Stage:
        environment = child_env()
        # Three processes on a CI machine of two cores: torch's thread pools in each would
        # fight over the cores (100x slower tensor ops here); one thread a stage.
        environment["OMP_NUM_THREADS"] = "1"
        environment.update(env)
        stage = Stage(script, [sys.executable, str(EXAMPLES / script), *self.common, *args],
                      environment)
        self.stages.append(stage)
        return stage

    def kill_all(self) -> None:
        for stage in self.stages:
            stage.close()


@pytest.fixture
def pipeline(domain: int, topic: str) -> Iterator[Pipeline]:
    started = Pipeline(domain, topic)
    try:
        yield started
    finally:
        started.kill_all()


def test_camera_infer_viewer(pipeline: Pipeline) -> None:
    infer = pipeline.start("infer.py")
    viewer = pipeline.start("viewer.py")
    infer.expect("ready", START_S)
    viewer.expect("ready", START_S)
    camera = pipeline.start("camera.py", "--duration", "3", "--subscribers", "2",
                            "--device", "cpu")
    published = camera.finish(stop=False)["published"]
    time.sleep(1.0)  # the last frames on their way
    inferred = infer.finish()
    viewed = viewer.finish()
    assert published >= 10
    assert 3 <= inferred["frames"] <= published and inferred["wrong"] == 0
    assert inferred["storage"] == {"warp": inferred["frames"]}  # zero-copy on this host
    assert 3 <= viewed["features"] <= inferred["frames"] and viewed["wrong_features"] == 0
    assert viewed["frames_checked"] >= 1 and viewed["wrong_frames"] == 0
    assert viewed["camera_to_viewer_p50_ms"] > 0  # the capture stamp reached the features


def test_point_cloud_pipeline(pipeline: Pipeline) -> None:
    ranges = pipeline.start("ranges.py")
    ranges.expect("ready", START_S)
    lidar = pipeline.start("lidar.py", "--duration", "2", "--device", "cpu")
    published = lidar.finish(stop=False)["published"]
    time.sleep(1.0)
    result = ranges.finish()
    assert published >= 5
    assert 3 <= result["scans"] <= published and result["wrong"] == 0
    assert abs(result["nearest_m"] - 4.0) < 1e-3  # the innermost ring


# Starts a program with SIGINT ignored, as a shell's background job (``&``, nohup) does.
_IGNORING_SIGINT = ("import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_IGN); "
                    "os.execv(sys.executable, [sys.executable, *sys.argv[1:]])")


def test_a_stage_started_in_the_background_stops_on_ctrl_c(pipeline: Pipeline) -> None:
    """A stage started with ``&`` from a script inherits SIGINT ignored: ``kill -INT`` left it
    running (the CLI's commands took it)."""
    stage = Stage("ranges.py", [sys.executable, "-c", _IGNORING_SIGINT,
                                str(EXAMPLES / "ranges.py"), *pipeline.common], child_env())
    pipeline.stages.append(stage)  # (killed at the end if it is still running)
    stage.expect("ready", START_S)
    stage.proc.send_signal(signal.SIGINT)
    assert stage.finish(stop=False)["scans"] == 0


@pytest.fixture
def router_endpoint() -> Iterator[str]:
    """A ``warp-buffer router`` on a Unix socket of this test."""
    workdir = tempfile.mkdtemp(prefix="wbex_", dir="/tmp")  # short: a socket path lives here
    endpoint = f"unixsock-stream/{workdir}/router.sock"
    router = subprocess.Popen([sys.executable, "-m", "warp_buffer_cli.main", "router", "--listen",
                               endpoint], cwd=ROOT, env=child_env(), stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)
    try:
        assert router.stdout is not None
        line = router.stdout.readline()
        assert line.startswith("warp-buffer router"), line + (router.stderr.read() or "")
        yield endpoint
    finally:
        if router.poll() is None:
            router.terminate()
        try:
            router.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            router.kill()
            router.communicate()
        for name in os.listdir(workdir):
            os.unlink(os.path.join(workdir, name))
        os.rmdir(workdir)


def test_two_hosts_through_the_router(pipeline: Pipeline, router_endpoint: str) -> None:
    """The camera on host A; inference and viewer on host B, every node a client of one router.
    Two hosts on one machine: the warp backend's host id differs per process
    (WARP_BUFFER_TEST_HOST_ID), so frames cross as bytes, and the same code reads them."""
    host_a = {"WARP_BUFFER_TEST_HOST_ID": "example-host-a"}
    host_b = {"WARP_BUFFER_TEST_HOST_ID": "example-host-b"}
    router = ["--router", router_endpoint]
    infer = pipeline.start("infer.py", *router, **host_b)
    viewer = pipeline.start("viewer.py", *router, **host_b)
    infer.expect("ready", START_S)
    viewer.expect("ready", START_S)
    camera = pipeline.start("camera.py", *router, "--duration", "3", "--rate", "10",
                            "--subscribers", "2", "--device", "cpu", **host_a)
    published = camera.finish(stop=False)["published"]
    time.sleep(1.0)
    inferred = infer.finish()
    viewed = viewer.finish()
    assert published >= 5
    assert 3 <= inferred["frames"] <= published and inferred["wrong"] == 0
    assert inferred["storage"] == {"cpu": inferred["frames"]}  # bytes from the other host
    assert 3 <= viewed["features"] and viewed["wrong_features"] == 0
    assert viewed["frames_checked"] >= 1 and viewed["wrong_frames"] == 0


def test_examples_use_only_the_public_api() -> None:
    """What users copy must not reach into private modules or attributes of the library."""
    for path in sorted(EXAMPLES.glob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module and node.module != "__future__":
                names = [*node.module.split("."), *(alias.name for alias in node.names)]
                assert not any(name.startswith("_") for name in names), (path.name, node.module)
            elif isinstance(node, ast.Attribute) and node.attr.startswith("_") \
                    and not node.attr.startswith("__"):
                raise AssertionError(f"{path.name}:{node.lineno} uses private {node.attr}")


def test_every_example_says_how_to_run_it() -> None:
    for path in sorted(EXAMPLES.glob("*.py")):
        doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8")))
        assert doc, path.name
        if path.stem not in ("pipeline_common", "pipeline_kernels"):
            assert f"python examples/{path.name}" in doc, path.name
