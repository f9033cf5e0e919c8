"""The WARP_BUFFER_* switches are read one way (warp_buffer._env)."""

from __future__ import annotations

import pytest

from warp_buffer._env import env_flag, env_float


@pytest.mark.parametrize("value,default,expected", [
    ("1", False, True), ("TRUE", False, True), (" yes ", False, True), ("on", False, True),
    ("0", True, False), ("False", True, False), ("no", True, False), ("OFF ", True, False),
    ("", True, True), ("", False, False), ("maybe", True, True), ("maybe", False, False),
])
def test_env_flag(monkeypatch, value, default, expected):
    monkeypatch.setenv("WARP_BUFFER_TEST_SWITCH", value)
    assert env_flag("WARP_BUFFER_TEST_SWITCH", default) is expected


def test_env_flag_unset_is_the_default(monkeypatch):
    monkeypatch.delenv("WARP_BUFFER_TEST_SWITCH", raising=False)
    assert env_flag("WARP_BUFFER_TEST_SWITCH", True) is True
    assert env_flag("WARP_BUFFER_TEST_SWITCH", False) is False


@pytest.mark.parametrize("value,expected", [("2.5", 2.5), ("x", 7.0), ("", 7.0), ("nan", 7.0),
                                            ("inf", 7.0), ("-inf", 7.0)])
def test_env_float(monkeypatch, value, expected):
    monkeypatch.setenv("WARP_BUFFER_TEST_NUMBER", value)
    assert env_float("WARP_BUFFER_TEST_NUMBER", 7.0) == expected


def test_the_switches_use_it(monkeypatch):
    from warp_buffer import loan, pool

    monkeypatch.setenv("WARP_BUFFER_LOAN_PROTECT", "Off")
    monkeypatch.setenv("WARP_BUFFER_DISABLE_IPC", "Yes")
    assert not loan.protection_enabled() and pool.ipc_disabled()
