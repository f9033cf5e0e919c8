"""``warp-buffer demo`` end to end: three processes, the warp and the CPU path, exit code 0."""

from __future__ import annotations

import argparse
import os
import pathlib
import subprocess
import sys
import time

import pytest

from warp_buffer_cli import demo

ROOT = pathlib.Path(__file__).resolve().parent.parent
pytestmark = pytest.mark.multiprocess


def test_demo_passes_on_the_cpu_device():
    """Run as a user does (``warp-buffer demo``): exit 0, and stdout is its report alone."""
    done = subprocess.run(
        [sys.executable, "-m", "warp_buffer_cli.main", "demo", "--frames", "12", "--height",
         "32", "--width", "48", "--rate", "100", "--timeout", "40", "--device", "cpu",
         "--domain", str(230 + os.getpid() % 20)],
        cwd=ROOT, env={k: v for k, v in os.environ.items() if k != "WARP_BUFFER_VERBOSE"},
        capture_output=True, text=True, timeout=150)
    out = done.stdout
    assert done.returncode == 0, out + done.stderr[-3000:]
    assert "warp subscriber: path warp" in out and "cpu subscriber: path cpu" in out
    assert "received 12/12" in out and "p99" in out
    report = ("warp-buffer demo:", "publisher:", "warp subscriber:", "latency", "check",
              "cpu subscriber:", "latency", "check", "demo:")
    assert [line.split()[0] for line in out.splitlines()] == [p.split()[0] for p in report]
    for noise in ("Warp 1.", "CUDA driver", "Module "):  # Warp's banner, native warning, logs
        assert noise not in out + done.stderr


def test_the_demo_passes_without_torch_an_optional_extra(tmp_path):
    """``pip install warp-buffer`` has no torch: the warp subscriber views the frames through
    Warp instead, and says so (the demo ran, then failed with ModuleNotFoundError)."""
    fake = tmp_path / "torch"  # ahead of site-packages on the path: `import torch` fails
    fake.mkdir()
    (fake / "__init__.py").write_text("raise ImportError('torch is not installed (a test)')\n")
    env = {k: v for k, v in os.environ.items() if k != "WARP_BUFFER_VERBOSE"}
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), str(ROOT)])
    done = subprocess.run(
        [sys.executable, "-m", "warp_buffer_cli.main", "demo", "--frames", "8", "--height",
         "16", "--width", "24", "--rate", "100", "--timeout", "40", "--device", "cpu",
         "--domain", str(210 + os.getpid() % 20)],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=150)
    out = done.stdout
    assert done.returncode == 0, out + done.stderr[-3000:]
    assert "torch is not installed" in out and "frames viewed through Warp" in out
    assert "warp subscriber: path warp" in out and out.count("received 8/8, bad 0") == 2


def test_subscribers_already_on_the_topic_do_not_make_the_demo_start_early(topic):
    """Two other subscriptions of the demo's topic (a recorder, ``topic echo``) were matched
    before the demo's own: counting two, the publisher started before its subscribers listened
    and they missed the first frames ("received 492/500, lost 0", demo: FAILED)."""
    from buffer_pubsub import Node

    domain = 250 + os.getpid() % 20
    with Node("demo_onlooker", domain_id=domain) as onlooker:
        for _ in range(2):
            onlooker.create_subscription(demo.TENSOR, topic, lambda msg: None, depth=50)
        done = subprocess.run(
            [sys.executable, "-m", "warp_buffer_cli.main", "demo", "--frames", "30", "--height",
             "16", "--width", "16", "--rate", "100", "--timeout", "40", "--device", "cpu",
             "--domain", str(domain), "--topic", topic],
            cwd=ROOT, capture_output=True, text=True, timeout=150)
    assert done.returncode == 0, done.stdout + done.stderr[-3000:]
    assert done.stdout.count("received 30/30") == 2, done.stdout


def test_demo_fails_when_a_check_fails(monkeypatch, capsys):
    """The verdict is not hard-coded: a subscriber that sees wrong content makes it fail."""
    parser = argparse.ArgumentParser()
    demo.add_arguments(parser)
    args = parser.parse_args(["--frames", "4", "--height", "8", "--width", "8",
                              "--timeout", "20", "--domain", str(210 + os.getpid() % 20)])
    monkeypatch.setenv("WARP_BUFFER_DEMO_CORRUPT", "1")
    assert demo.run(args) == 1
    assert "FAILED" in capsys.readouterr().out


def test_latency_is_stamped_at_callback_entry_and_the_check_is_timed_apart():
    """The demo stamped latency after checking every element of the frame: a slow check read
    as a slow transport ("zero-copy is slower than copying")."""
    from types import SimpleNamespace

    stats = demo._new_stats()
    msg = SimpleNamespace(data=SimpleNamespace(get_backend_type=lambda: "warp"))
    info = SimpleNamespace(route="lane", source_timestamp_ns=time.time_ns())

    def slow_check(_msg) -> bool:
        time.sleep(0.3)
        return True

    demo.record_frame(stats, msg, info, slow_check)
    assert stats["check_ms"][0] >= 300
    assert stats["latency_ms"][0] < stats["check_ms"][0] / 2  # the check is not in it
    assert (stats["received"], stats["bad"], stats["backends"], stats["routes"]) == (
        1, 0, ["warp"], ["lane"])
    demo.record_frame(stats, msg, info, lambda _msg: 1 / 0)  # a failing check is a bad frame
    assert stats["bad"] == 1 and "ZeroDivisionError" in stats["errors"][0]


def _parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    demo.add_arguments(parser)
    return parser.parse_args(argv)


def test_demo_fails_fast_with_the_typed_error_on_a_missing_device(capsys):
    import warp_buffer

    if "cuda:7" in {str(d.alias) for d in warp_buffer.init_warp().get_devices()}:
        pytest.skip("this machine has a cuda:7")
    started = time.monotonic()
    assert demo.run(_parse(["--device", "cuda:7", "--domain", "3"])) == 1
    assert time.monotonic() - started < 5
    err = capsys.readouterr().err
    assert "DeviceUnavailableError" in err and "cuda:7" in err


def test_demo_fails_fast_with_the_typed_error_on_a_bad_transport_config(monkeypatch, capsys):
    monkeypatch.setenv("ZENOH_SESSION_CONFIG_URI", "/nonexistent/zenoh.json5")
    started = time.monotonic()
    assert demo.run(_parse(["--device", "cpu", "--domain", "3"])) == 1
    assert time.monotonic() - started < 5  # before any child starts
    err = capsys.readouterr().err
    assert "TransportConfigError" in err and "ZENOH_SESSION_CONFIG_URI" in err


def test_demo_defaults_to_warps_preferred_device():
    import warp_buffer

    args = _parse([])
    assert args.device is None
    assert demo._check_setup(args) is None
    assert args.device == str(warp_buffer.init_warp().get_preferred_device().alias)


@pytest.mark.parametrize("argv", [["--frames", "0"], ["--frames", "x"], ["--width", "-3"],
                                  ["--rate", "-1"], ["--timeout", "0"], ["--domain", "-1"],
                                  ["--timeout", "inf"], ["--timeout", "1e300"],
                                  ["--rate", "1e-300"], ["--domain", "99999999999999999999"]])
def test_demo_rejects_bad_arguments_with_a_usage_error(argv, capsys):
    with pytest.raises(SystemExit) as exit_info:
        _parse(argv)
    assert exit_info.value.code == 2
    assert "error: argument " + argv[0] in capsys.readouterr().err


def test_demo_help_shows_the_defaults():
    parser = argparse.ArgumentParser()
    demo.add_arguments(parser)
    text = parser.format_help()
    assert "frames to publish (default: 50)" in text
    assert "(default: None)" not in text and "preferred device" in text


@pytest.mark.parametrize("started", [1, 3], ids=["while-spawning", "all-started"])
def test_sigterm_ends_the_demo_and_reaps_its_children(started):
    """SIGTERM as soon as ``started`` children exist: also while the demo is still inside
    ``Popen`` for the next one (a signal raised there once orphaned a child)."""
    import signal

    proc = subprocess.Popen(
        [sys.executable, "-m", "warp_buffer_cli.main", "demo", "--frames", "3000", "--height",
         "32", "--width", "48", "--timeout", "30", "--device", "cpu",
         "--domain", str(210 + os.getpid() % 20)],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    children: list[str] = []
    try:
        deadline = time.monotonic() + 60
        while len(children) < started and time.monotonic() < deadline:
            time.sleep(0.01)
            children = _demo_children(proc)
        assert len(children) >= started
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=60) == 128 + signal.SIGTERM
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.communicate()
    assert not [pid for pid in children if pathlib.Path(f"/proc/{pid}").exists()]


def _demo(*options: str, domain: int | None = None, **popen: object) -> subprocess.Popen:
    argv = [sys.executable, "-m", "warp_buffer_cli.main", "demo", "--height", "32", "--width",
            "48", "--device", "cpu", *options]
    if domain is not None:
        argv += ["--domain", str(domain)]
    return subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, **popen)


def _demo_children(proc: subprocess.Popen) -> list[str]:
    """The pids of the demo's own children (its set-up may run others, `uname` for one,
    before its signal handler is installed)."""
    return subprocess.run(["pgrep", "-P", str(proc.pid), "-f", " --topic "],
                          capture_output=True, text=True).stdout.split()


def _children_of(proc: subprocess.Popen, count: int = 3) -> list[str]:
    children: list[str] = []
    deadline = time.monotonic() + 60
    while len(children) < count and time.monotonic() < deadline:
        time.sleep(0.2)
        children = _demo_children(proc)
    assert len(children) == count
    return children


def test_a_slow_rate_passes_and_stays_within_its_timeout():
    """--rate 0.02 slept 50 s after the only frame: the parent killed the publisher before it
    reported, and a demo whose subscribers got every frame FAILED, after 33 s."""
    start = time.monotonic()
    proc = _demo("--frames", "1", "--rate", "0.02", "--timeout", "20",
                 domain=190 + os.getpid() % 20)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, out + err[-2000:]
    assert time.monotonic() - start < 30


@pytest.mark.parametrize("sig", ["SIGKILL", "SIGINT"])
def test_the_children_go_with_the_demo_and_ctrl_c_is_one_line(sig):
    """SIGKILL (or SIGHUP) of the demo left its three children running for their whole run;
    Ctrl-C (SIGINT to the process group, as a terminal sends it) printed a traceback per
    process."""
    import signal

    proc = _demo("--frames", "3000", "--timeout", "30", domain=170 + os.getpid() % 20,
                 start_new_session=True)
    try:
        children = _children_of(proc)
        time.sleep(1.0)
        if sig == "SIGKILL":
            proc.kill()
        else:
            os.killpg(proc.pid, signal.SIGINT)
        code = proc.wait(timeout=60)
        deadline = time.monotonic() + 15
        while (alive := [p for p in children if pathlib.Path(f"/proc/{p}").exists()
                         and "zombie" not in pathlib.Path(f"/proc/{p}/status").read_text()
                         .lower()]) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not alive, f"children still running after {sig}: {alive}"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        _, err = proc.communicate()
    if sig == "SIGINT":
        assert code == 130 and "Traceback" not in err, err[-3000:]
        assert "interrupted" in err


def test_the_default_domain_follows_ros_domain_id_and_the_topic_is_private():
    env = dict(os.environ, ROS_DOMAIN_ID=str(140 + os.getpid() % 10))
    proc = _demo("--frames", "2", "--timeout", "30", env=env)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, out + err[-2000:]
    first = out.splitlines()[0]
    assert f"domain {env['ROS_DOMAIN_ID']}," in first
    assert f"topic {demo.TOPIC}_{proc.pid}" in first  # two demos in one domain never mix
