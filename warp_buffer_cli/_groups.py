"""Subcommand groups (``warp-buffer bag record``, ``warp-buffer topic list``): a group module
(listed in ``warp_buffer_cli.main._COMMANDS``, with no ``run`` of its own) keeps its table of
leaves in ``COMMANDS`` (tests/test_readme.py reads it) and calls :func:`add_subcommands` with it
from its ``add_arguments``. ``warp_buffer_cli/bag`` is one; ``topic`` and ``node`` fit the same
way, each in a module of its own.

A leaf module has ``add_arguments(parser)`` and ``run(args) -> int`` and must be cheap to import
(heavy imports inside ``run``): a group registers all its leaves so that ``--help`` lists them.
"""

from __future__ import annotations

import argparse
import importlib
import re
from collections.abc import Mapping

# Sphinx roles (:class:`~.errors.BagDamagedError`) and literals (``ros2 bag play``) of a
# module docstring, which a leaf's --help shows as plain text: the name and the words.
_ROLE = re.compile(r":[a-z]+:`~?\.?(?:[\w.]*\.)?([^`.]+)`")
_LITERAL = re.compile(r"``([^`]+)``")


def plain_text(docstring: str | None) -> str | None:
    """``docstring`` without its reStructuredText markup, for a terminal."""
    if docstring is None:
        return None
    return _LITERAL.sub(r"\1", _ROLE.sub(r"\1", docstring))


def add_subcommands(parser: argparse.ArgumentParser,
                    commands: Mapping[str, tuple[str, str]]) -> None:
    """Register ``commands`` (name -> (module, one-line help)) as required subcommands of
    ``parser``; the chosen leaf's ``run`` and its full name (for one-line errors) land in the
    parsed arguments as ``run`` and ``command_name``."""
    leaves = parser.add_subparsers(dest="subcommand", required=True,
                                   metavar="{" + ",".join(commands) + "}")
    for name, (module_name, help_text) in commands.items():
        module = importlib.import_module(module_name)
        leaf = leaves.add_parser(name, help=help_text, description=plain_text(module.__doc__),
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
        module.add_arguments(leaf)
        leaf.set_defaults(run=module.run, command_name=leaf.prog)
