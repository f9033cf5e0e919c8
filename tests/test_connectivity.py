"""Reaching other hosts: ``warp-buffer router``, router/peer warnings, config errors that name the
file (``buffer_pubsub.config`` and ``buffer_pubsub.connectivity``)."""

from __future__ import annotations

import json
import logging
import os
import pathlib
import signal
import subprocess
import sys
import time

import pytest

from buffer_pubsub import Node, TransportConfigError, config, connectivity

ROOT = pathlib.Path(__file__).resolve().parent.parent


@pytest.fixture
def fast_warning(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(connectivity, "WARN_AFTER_S", 0.5)


def test_missing_config_file_is_named(tmp_path: pathlib.Path,
                                      monkeypatch: pytest.MonkeyPatch) -> None:
    missing = tmp_path / "nope.json5"
    with pytest.raises(TransportConfigError, match="nope.json5.*does not exist"):
        Node("n", config=missing)
    monkeypatch.setenv(config.CONFIG_URI_ENV, str(missing))
    with pytest.raises(TransportConfigError, match=f"nope.json5.*{config.CONFIG_URI_ENV}"):
        Node("n")


@pytest.mark.parametrize("text", ['{mode: "peer",, }', '{mode: "blah"}'])
def test_bad_json5_names_the_file_not_a_rust_source(tmp_path: pathlib.Path, text: str) -> None:
    path = tmp_path / "bad.json5"
    path.write_text(text)
    with pytest.raises(TransportConfigError) as info:
        config.make_config(path)
    message = str(info.value)
    assert str(path) in message and ".rs:" not in message


def test_unreachable_router_warns_then_fails_naming_it(
        fast_warning: None, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture) -> None:
    monkeypatch.setenv(config.CONNECT_TIMEOUT_ENV, "1.5")
    caplog.set_level(logging.WARNING, logger="buffer_pubsub")
    started = time.monotonic()
    with pytest.raises(TransportConfigError, match=r"tcp/127\.0\.0\.1:1.*warp-buffer router"):
        Node("n", router="tcp/127.0.0.1:1")
    assert time.monotonic() - started < 5
    assert any("still waiting for Zenoh router tcp/127.0.0.1:1" in r.getMessage()
               for r in caplog.records)


def test_unreachable_peer_of_a_config_file_is_reported(
        fast_warning: None, tmp_path: pathlib.Path, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "peer.json5"
    path.write_text('{mode: "peer", connect: {endpoints: ["tcp/127.0.0.1:1"]}, '
                    'scouting: {multicast: {enabled: false}}}')
    caplog.set_level(logging.WARNING, logger="buffer_pubsub")
    with Node("n", config=path):  # a peer starts anyway and keeps retrying
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and not caplog.records:
            time.sleep(0.05)
    assert any("tcp/127.0.0.1:1" in r.getMessage() and "keeps retrying" in r.getMessage()
               for r in caplog.records)


def test_a_node_closed_before_the_check_is_not_reported(
        fast_warning: None, tmp_path: pathlib.Path, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "peer.json5"
    path.write_text('{mode: "peer", connect: {endpoints: ["tcp/127.0.0.1:1"]}, '
                    'scouting: {multicast: {enabled: false}}}')
    caplog.set_level(logging.WARNING, logger="buffer_pubsub")
    Node("n", config=path).close()
    time.sleep(1.0)  # twice the (patched) delay of the check
    assert not [r for r in caplog.records if "keeps retrying" in r.getMessage()]


def test_router_defaults_follow_rmw_zenoh() -> None:
    router = config.make_router_config()
    assert router.get_json("mode") == '"router"'
    assert router.get_json("listen/endpoints") == '["tcp/[::]:7447"]'
    assert router.get_json("scouting/multicast/enabled") == "false"
    assert router.get_json("scouting/gossip/enabled") == "true"
    assert config.make_config(router="tcp/localhost:7447").get_json("mode") == '"client"'


def _start_router(socket_path: pathlib.Path) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "warp_buffer_cli.main", "router", "--listen",
         f"unixsock-stream/{socket_path}"], cwd=ROOT, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True)


@pytest.mark.multiprocess
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_router_serves_a_node_and_stops_cleanly(tmp_path: pathlib.Path, signum: int) -> None:
    socket_path = tmp_path / "router.sock"
    router = _start_router(socket_path)
    try:
        assert router.stdout is not None
        line = router.stdout.readline()
        assert line.startswith("warp-buffer router ") and str(socket_path) in line, line
        zid = line.split()[2]
        with Node("router_user", router=f"unixsock-stream/{socket_path}") as node:
            assert zid in {str(z) for z in node.session.info.routers_zid()}
        router.send_signal(signum)
        assert router.wait(timeout=10) == 0
        assert router.stdout.read() == ""  # one line on stdout, nothing else
    finally:
        if router.poll() is None:
            router.kill()
        router.wait()
        for stream in (router.stdout, router.stderr):
            if stream is not None:
                stream.close()


def test_router_rejects_a_bad_endpoint() -> None:
    done = subprocess.run([sys.executable, "-m", "warp_buffer_cli.main", "router", "--listen",
                           "bogus"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "bogus" in done.stderr and done.stdout == ""


def test_connect_timeout_env_is_validated(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(config.CONNECT_TIMEOUT_ENV, "soon")
    with pytest.raises(TransportConfigError, match=config.CONNECT_TIMEOUT_ENV):
        config.make_config(router="tcp/localhost:7447")
    monkeypatch.setenv(config.CONNECT_TIMEOUT_ENV, "2.5")
    assert config.connect_timeout_s() == 2.5
    del os.environ[config.CONNECT_TIMEOUT_ENV]
    assert config.connect_timeout_s() == config.DEFAULT_CONNECT_TIMEOUT_S


def _zenoh_segments(pid: int | str) -> set[str]:
    """The Zenoh shared-memory segments (``/dev/shm/*.zenoh``) process ``pid`` maps."""
    with open(f"/proc/{pid}/maps", encoding="utf-8") as maps:
        return {line.split()[-1] for line in maps if line.rstrip().endswith(".zenoh")}


@pytest.mark.multiprocess
def test_a_router_and_its_clients_map_no_named_shared_memory(tmp_path: pathlib.Path) -> None:
    # Zenoh's SHM transport names its segments in /dev/shm: a killed router or client would
    # leave them behind. Same-host zero copy is the backends' job; the transport stays off it.
    socket_path = tmp_path / "router.sock"
    router = _start_router(socket_path)
    try:
        assert router.stdout is not None
        assert router.stdout.readline().startswith("warp-buffer router ")
        with Node("shm_user", router=f"unixsock-stream/{socket_path}") as node:
            assert node.session.info.routers_zid()  # connected
            assert _zenoh_segments("self") == set()
            assert _zenoh_segments(router.pid) == set()
    finally:
        router.kill()
        router.communicate()


def test_a_nodes_data_queue_holds_more_than_one_demo_frame() -> None:
    # Zenoh's default (2 batches of 64 KiB) held less than one 240x320 float32 frame (300 KB):
    # a keep-last frame was dropped whenever the reader stalled for one frame period.
    frame = 240 * 320 * 4
    for made in (config.make_config(), config.make_config(router="tcp/localhost:7447")):
        batches = json.loads(made.get_json("transport/link/tx/queue/size"))["data"]
        batch = json.loads(made.get_json("transport/link/tx/batch_size"))
        assert batches * batch >= 1.5 * frame, (batches, batch)


def test_zenoh_config_override_changes_every_configuration_as_rmw_zenohs_does(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(config.OVERRIDE_ENV,
                       'mode="client";connect/endpoints=["tcp/10.0.0.9:7447"];;')
    made = config.make_config()
    assert made.get_json("mode") == '"client"'
    assert made.get_json("connect/endpoints") == '["tcp/10.0.0.9:7447"]'
    router = config.make_router_config(listen=["tcp/127.0.0.1:7500"])
    assert router.get_json("connect/endpoints") == '["tcp/10.0.0.9:7447"]'
    assert router.get_json("listen/endpoints") == '["tcp/127.0.0.1:7500"]'  # the flag wins
    for bad, named in (("multicast", "'multicast' is not key=value"),
                       ("scouting/nope=1", "scouting/nope=1")):
        monkeypatch.setenv(config.OVERRIDE_ENV, bad)
        with pytest.raises(TransportConfigError, match=named):
            config.make_config()


def test_a_lone_node_on_the_default_configuration_warns_of_no_missing_router(
        fast_warning: None, caplog: pytest.LogCaptureFixture) -> None:
    """The default connects to this host's router when one runs (rmw_zenoh's), but needs none:
    a node alone, with no router, logs nothing about it."""
    caplog.set_level(logging.WARNING, logger="buffer_pubsub")
    with Node("lone", domain_id=231):
        time.sleep(connectivity.WARN_AFTER_S + 0.5)
    assert not [r for r in caplog.records if "7447" in r.getMessage()], caplog.records


# ROS_DOMAIN_ID as rcl's rcl_get_default_domain_id reads it: strtoul(text, base 0), so hex and
# octal count; written from rcl/src/rcl/domain_id.c.
@pytest.mark.parametrize(("text", "domain"), [
    ("7", 7), (" 42 ", 42), ("+3", 3), ("0", 0), ("010", 8), ("0x10", 16), ("232", 232),
    (str((1 << 64) - 1), (1 << 64) - 1)])
def test_the_domain_env_is_read_as_rcl_reads_it(monkeypatch: pytest.MonkeyPatch, text: str,
                                                domain: int) -> None:
    monkeypatch.setenv("ROS_DOMAIN_ID", text)
    assert config.resolve_domain_id(None) == domain


@pytest.mark.parametrize(("text", "why"), [
    ("-1", "not an integer"),  # (strtoul makes it 2**64 - 1, which rcl takes: refused here)
    ("abc", "not an integer"), ("1.5", "not an integer"),
    ("\u0663", "not an integer"),  # an Arabic-Indic 3, which int() took
    ("08", "not an integer"), ("0x", "not an integer"),
    (str(1 << 64), "out of range"), ("9" * 30, "out of range")])
def test_a_domain_env_that_names_no_domain_is_refused(monkeypatch: pytest.MonkeyPatch, text: str,
                                             why: str) -> None:
    monkeypatch.setenv("ROS_DOMAIN_ID", text)
    with pytest.raises(TransportConfigError, match=why):
        config.resolve_domain_id(None)
