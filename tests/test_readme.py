"""Every snippet in README.md works as written.

- Each ```python block runs in a fresh interpreter (as a file, since Warp reads kernel source),
  from an empty directory that it must leave empty, on a private domain, and must exit 0. A block whose first line is a comment
  starting with ``# illustrative`` is shown to the reader only (it needs a second host); the set
  of such blocks is kept small and checked here.
- Each ```bash block's commands must exist: ``warp-buffer`` subcommands and every option the
  README passes them (checked against their ``--help``), and the other programs on PATH or in the
  repository.
- Every ``WARP_BUFFER_*`` switch the README documents exists in the code.
"""

from __future__ import annotations

import os
import pathlib
import re
import shlex
import shutil
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
README = (ROOT / "README.md").read_text(encoding="utf-8")
BLOCK = re.compile(r"^```(\w+)[^\n]*\n(.*?)^```", re.S | re.M)
ILLUSTRATIVE = "# illustrative"
MAX_ILLUSTRATIVE = 2


def _blocks(language: str) -> list[str]:
    return [body for lang, body in BLOCK.findall(README) if lang == language]


def _runnable_python() -> list[str]:
    return [b for b in _blocks("python") if not b.lstrip().startswith(ILLUSTRATIVE)]


def test_readme_has_runnable_snippets_and_few_illustrative_ones() -> None:
    assert len(_runnable_python()) >= 4
    illustrative = [b for b in _blocks("python") if b.lstrip().startswith(ILLUSTRATIVE)]
    assert len(illustrative) <= MAX_ILLUSTRATIVE
    for block in illustrative:  # even these must at least be valid Python
        compile(block, "<README illustrative block>", "exec")


@pytest.mark.multiprocess
@pytest.mark.parametrize("index", range(len(_runnable_python())))
def test_python_snippet_runs(index: int, tmp_path: pathlib.Path) -> None:
    code = _runnable_python()[index]
    env = {k: v for k, v in os.environ.items()
           if k not in ("WARP_BUFFER_ZENOH_ROUTER", "ZENOH_SESSION_CONFIG_URI",
                        "WARP_BUFFER_VERBOSE")}
    env["ROS_DOMAIN_ID"] = str(120 + (os.getpid() + index) % 60)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH", "")) if p)
    script = tmp_path / f"readme_block_{index}.py"  # a file: Warp reads a kernel's source
    script.write_text(code, encoding="utf-8")
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    done = subprocess.run([sys.executable, str(script)], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=180)
    assert done.returncode == 0, f"README python block {index} failed:\n{code}\n{done.stderr}"
    assert not list(cwd.iterdir()), "a snippet left files in the current directory"


def _commands() -> list[list[str]]:
    """Every command line of the bash blocks, as argv (environment assignments dropped)."""
    commands = []
    for block in _blocks("bash"):
        for line in block.splitlines():
            line = line.split(" #")[0].strip()
            if not line or line.startswith("#"):
                continue
            for part in re.split(r"&&|\|\|", line):
                argv = [w for w in shlex.split(part) if not re.match(r"^[A-Z_][A-Z0-9_]*=", w)]
                if argv:
                    commands.append(argv)
    return commands


def _help(subcommand: str) -> str:
    done = subprocess.run([sys.executable, "-m", "warp_buffer_cli.main", subcommand, "--help"],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_shell_commands_exist() -> None:
    from warp_buffer_cli.main import _COMMANDS

    commands = _commands()
    assert commands, "no shell commands found in the README"
    helps: dict[str, str] = {}
    for argv in commands:
        program = argv[0]
        if program.endswith("warp-buffer"):
            words = [w for w in argv[1:] if w not in ("-v", "--verbose")]
            assert words and words[0] in _COMMANDS, argv
            text = helps.get(words[0]) or helps.setdefault(words[0], _help(words[0]))
            for option in (w.split("=")[0] for w in words[1:] if w.startswith("--")):
                assert option in text, f"{argv}: {option} is not an option of {words[0]}"
        elif program.startswith(".venv/"):
            assert program.split("/")[-1] in ("python", "pip", "warp-buffer"), argv
            if program.endswith("python") and argv[1:3] == ["-m", "pytest"]:
                continue
            if program.endswith("python") and len(argv) > 1:
                assert (ROOT / argv[1]).exists() or argv[1] == "your_node.py", argv
        else:
            assert shutil.which(program) is not None, f"{program} is not installed"


def test_documented_switches_exist_in_the_code() -> None:
    documented = set(re.findall(r"\bWARP_BUFFER_[A-Z0-9_]+", README))
    assert documented
    sources = "\n".join(p.read_text(encoding="utf-8") for package in
                        ("rosidl_buffer", "warp_buffer", "warp_buffer_backend",
                         "tensor_conversions", "buffer_pubsub", "warp_buffer_cli")
                        for p in (ROOT / package).rglob("*.py"))
    missing = sorted(name for name in documented if name not in sources)
    assert not missing, f"README documents switches the code does not read: {missing}"
