"""``topic echo`` prints strings as ``ros2 topic echo`` does (PyYAML, YAML 1.1): plain where
PyYAML leaves them plain, quoted where a reader would take them for something else."""

from __future__ import annotations

import io

import pytest

from warp_buffer_cli.topic._fields import yaml_lines

# What PyYAML's ``yaml.dump({"data": value})`` prints (rosidl_runtime_py's message_to_yaml),
# written down from its rules: plain text stays plain; what YAML 1.1 reads as a bool, null,
# number or date, what starts with an indicator, holds ": " or " #", or has outer spaces is
# single-quoted.
PYYAML = {
    "hello 5702": "hello 5702",
    "/camera/image": "/camera/image",
    "it's": "it's",
    "-a": "-a",
    "a,b": "a,b",
    "ünï": "ünï",
    "1e3": "1e3",  # YAML 1.1: a float needs a dot
    "true": "'true'", "Yes": "'Yes'", "off": "'off'", "~": "'~'", "null": "'null'",
    "123": "'123'", "0x1f": "'0x1f'", "1.5": "'1.5'", ".inf": "'.inf'", "1_000": "'1_000'",
    "12:30:45": "'12:30:45'", "2024-01-02": "'2024-01-02'",
    "a: b": "'a: b'", "a #b": "'a #b'", "x:": "'x:'", "#x": "'#x'", "- a": "'- a'",
    "[x]": "'[x]'", "": "''", " lead": "' lead'", "trail ": "'trail '", "'q'": "'''q'''",
}


@pytest.mark.parametrize("value", list(PYYAML))
def test_a_string_is_quoted_exactly_where_pyyaml_quotes_it(value: str) -> None:
    assert list(yaml_lines({"data": value})) == [f"data: {PYYAML[value]}"]


# (1e3 left out: ruamel reads it as a float, where YAML 1.1 and PyYAML keep a string)
@pytest.mark.parametrize("value", [*(v for v in PYYAML if v != "1e3"), "a\nb", "tab\there",
                                   "bell\x07"])
def test_every_string_reads_back_as_itself_in_yaml_1_1(value: str) -> None:
    """An independent reader (ruamel.yaml, in YAML 1.1 mode) gets the same string back."""
    from ruamel.yaml import YAML

    reader = YAML(typ="safe", pure=True)
    reader.version = (1, 1)
    text = "\n".join(yaml_lines({"data": value})) + "\n"
    assert reader.load(io.StringIO(text))["data"] == value, text
