"""Test-only modules: a fake buffer backend (plugins for the registry tests) and message helpers."""
