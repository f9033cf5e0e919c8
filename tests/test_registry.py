"""Backend registry (plugin discovery through entry points), EndpointInfo and backend options."""

from __future__ import annotations

import os
import pathlib
import sys

import pytest
from plugins.fake_backend import FakeBackend, PluginBackend

from rosidl_buffer import (
    BackendLoadError,
    BufferBackend,
    EndpointInfo,
    EndpointType,
    RosidlBufferError,
    UnknownBackendError,
    local_host_id,
    parse_acceptable_backends,
    registry,
)

TESTS_DIR = pathlib.Path(__file__).resolve().parent

# Entry points of the test distribution: name -> object reference.
GOOD_PLUGIN = PluginBackend.NAME  # not "fake": other tests' plugins may use that name
BROKEN_PLUGINS = {
    "broken_import": "plugins.broken_import:Backend",
    "missing_module": "plugins.no_such_module:Backend",
    "missing_attribute": "plugins.fake_backend:NoSuchBackend",
    "raising_constructor": "plugins.fake_backend:RaisingBackend",
    "not_a_backend": "plugins.fake_backend:not_a_backend",
    "mismatched_name": "plugins.fake_backend:FakeBackend",  # reports "fake"
}
TEST_PLUGINS = {GOOD_PLUGIN: "plugins.fake_backend:PluginBackend", **BROKEN_PLUGINS,
                "cpu": "plugins.fake_backend:FakeBackend"}  # "cpu" is built in: ignored


@pytest.fixture
def test_plugins(tmp_path, monkeypatch):
    """Install a throw-away distribution announcing the test plugins, for one test."""
    dist_info = tmp_path / "fake_plugin-0.0.dist-info"
    dist_info.mkdir()
    (dist_info / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: fake-plugin\nVersion: 0.0\n", encoding="utf-8")
    lines = [f"{name} = {target}" for name, target in TEST_PLUGINS.items()]
    (dist_info / "entry_points.txt").write_text(
        f"[{registry.ENTRY_POINT_GROUP}]\n" + "\n".join(lines) + "\n", encoding="utf-8")
    monkeypatch.syspath_prepend(str(TESTS_DIR))  # where the `plugins` package lives
    monkeypatch.syspath_prepend(str(tmp_path))
    registry.refresh()
    yield
    registry.refresh()  # monkeypatch restores sys.path next; the cache is already forgotten


@pytest.fixture
def no_test_plugins():
    registry.refresh()
    yield
    registry.refresh()


# ------------------------------------------------------------------------------- listing
def test_cpu_is_always_listed_first(no_test_plugins):
    names = registry.get_backend_names()
    assert names[0] == "cpu" and names.count("cpu") == 1
    assert GOOD_PLUGIN not in names


def test_test_plugins_are_discovered(test_plugins):
    names = registry.get_backend_names()
    assert names[0] == "cpu" and names.count("cpu") == 1
    assert set(TEST_PLUGINS) <= set(names)


def test_refresh_forgets_removed_plugins(test_plugins, monkeypatch, tmp_path):
    assert GOOD_PLUGIN in registry.get_backend_names()
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p != str(tmp_path)])
    assert GOOD_PLUGIN in registry.get_backend_names()  # cached until refresh
    registry.refresh()
    assert GOOD_PLUGIN not in registry.get_backend_names()


# ------------------------------------------------------------------------------- loading
def test_good_plugin_instantiates(test_plugins):
    backend = registry.create_backend_instance(GOOD_PLUGIN)
    assert isinstance(backend, PluginBackend) and isinstance(backend, BufferBackend)
    assert backend.get_backend_type() == GOOD_PLUGIN
    assert backend.get_backend_metadata() == "fake-metadata-v1"
    assert registry.create_backend_instance(GOOD_PLUGIN) is not backend  # a new instance


@pytest.mark.parametrize("name", ["cpu", "no_such_backend"])
def test_unknown_backend(test_plugins, name):
    with pytest.raises(UnknownBackendError, match=name) as excinfo:
        registry.create_backend_instance(name)
    assert isinstance(excinfo.value, RosidlBufferError)


@pytest.mark.parametrize("name", sorted(BROKEN_PLUGINS))
def test_broken_plugin_gives_load_error(test_plugins, name):
    with pytest.raises(BackendLoadError, match=name) as excinfo:
        registry.create_backend_instance(name)
    assert isinstance(excinfo.value, RosidlBufferError)
    # A broken plugin does not spoil the good one.
    assert registry.create_backend_instance(GOOD_PLUGIN).get_backend_type() == GOOD_PLUGIN


def test_load_backends_separates_errors(test_plugins):
    names = ["cpu", GOOD_PLUGIN, *BROKEN_PLUGINS, "no_such_backend"]
    loaded, errors = registry.load_backends(names)
    assert list(loaded) == [GOOD_PLUGIN] and isinstance(loaded[GOOD_PLUGIN], PluginBackend)
    assert set(errors) == {*BROKEN_PLUGINS, "no_such_backend"}
    assert all(isinstance(error, BackendLoadError) for error in errors.values())


# ------------------------------------------------------------------------------- discovery hook
def endpoint(supported_backends=None, **overrides) -> EndpointInfo:
    fields = dict(
        gid=bytes(range(16)), node_name="talker", node_namespace="/", topic_name="/image",
        topic_type="sensor_msgs/msg/Image", endpoint_type=EndpointType.SUBSCRIPTION,
        host_id=local_host_id(), process_id=os.getpid(), user_id=os.getuid(),
        supported_backends=supported_backends or {},
    )
    fields.update(overrides)
    return EndpointInfo(**fields)


@pytest.mark.parametrize(
    ("advertised", "accepted"),
    [({"fake": "fake-metadata-v1"}, True), ({"fake": "", "warp": "x"}, True),
     ({}, False), ({"warp": "x"}, False)],
)
def test_default_discovery_accepts_only_peers_advertising_the_backend(advertised, accepted):
    ok, groups = FakeBackend().on_discovering_endpoint(endpoint(advertised), [], advertised)
    assert ok is accepted and groups == []


# ------------------------------------------------------------------------------- EndpointInfo
@pytest.mark.parametrize("gid", [b"", bytes(15), bytes(17), "0123456789abcdef", None],
                         ids=["empty", "15", "17", "str", "none"])
def test_gid_must_be_16_bytes(gid):
    with pytest.raises(ValueError, match="16 bytes"):
        endpoint(gid=gid)


def test_endpoint_info_normalises_and_freezes():
    advertised = {"fake": "m"}
    info = endpoint(advertised, gid=bytearray(range(16)), endpoint_type=EndpointType.PUBLISHER)
    assert type(info.gid) is bytes and info.is_publisher
    advertised["warp"] = "added later"
    assert dict(info.supported_backends) == {"fake": "m"}  # a private, read-only copy
    with pytest.raises(TypeError):
        info.supported_backends["warp"] = "x"  # type: ignore[index]
    with pytest.raises(AttributeError):
        info.topic_name = "/other"  # type: ignore[misc]


def test_endpoint_identity_ignores_advertised_backends():
    assert endpoint({"fake": "a"}) == endpoint({"fake": "b"})
    assert hash(endpoint({"fake": "a"})) == hash(endpoint())
    assert endpoint() != endpoint(gid=bytes(16))


@pytest.mark.parametrize(
    ("overrides", "same"),
    [({}, True), ({"process_id": os.getpid() + 1}, False), ({"host_id": "elsewhere"}, False)],
)
def test_is_same_process(overrides, same):
    assert endpoint(**overrides).is_same_process() is same


# ------------------------------------------------------------------------------- options
AVAILABLE = ["cpu", "fake", "warp"]


@pytest.mark.parametrize(
    ("option", "expected"),
    [("", ["cpu"]), (None, ["cpu"]), ("cpu", ["cpu"]), (" any ", AVAILABLE),
     ("fake", ["fake", "cpu"]), ("warp, fake", ["warp", "fake", "cpu"]),
     ("cpu,fake,fake", ["cpu", "fake"]),
     # rmw_zenoh_cpp 0.12.0 rmw_subscription_data.cpp: "any" anywhere in the list is use_all
     ("cpu, any", AVAILABLE), ("fake,any,nope", AVAILABLE), (["any"], AVAILABLE)],
)
def test_parse_acceptable_backends(option, expected):
    assert parse_acceptable_backends(option, AVAILABLE) == expected


def test_any_always_includes_cpu():
    assert parse_acceptable_backends("any", ["fake"]) == ["fake", "cpu"]


def test_unknown_acceptable_backend_is_an_error():
    with pytest.raises(ValueError, match="nope"):
        parse_acceptable_backends("fake,nope", AVAILABLE)
