"""The README's code runs: every python block executes in a fresh interpreter, with each value a line's comment states
(``obs["language_instruction"]  # "..."``: a comment that is one string literal) asserted, and every ``dust-rl``
command its bash blocks use exists (``--help`` exits 0); the commands themselves are not run (they train for minutes).

A block that must not run is marked on the line before its fence with ``<!-- no-test: why -->``.
"""

from __future__ import annotations

import os
import pathlib
import re
import subprocess
import sys
from typing import NamedTuple

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
SKIP_MARKER = re.compile(r"<!--\s*no-test:\s*(\S.*?)\s*-->")
FENCE = re.compile(r"^```(\w*)\s*$")
SNIPPET_TIMEOUT = 120  # seconds per python block: imports and a gym/torchrl env are most of it
# A python line that states its expression's value in its comment, a string literal and nothing else.
STATED = re.compile(r'^(?P<code>\S.*?)\s+#\s*(?P<value>"[^"]*")\s*$')
# A dust-rl command in a shell line: one or two words (``dust-rl bench suite``) before the options.
COMMAND = re.compile(r"(?:^|[\s/;&|(])dust-rl\s+([a-z][\w-]*)(?:\s+([a-z][\w-]*))?")


class Block(NamedTuple):
    language: str
    code: str
    line: int  # of the opening fence, 1-based
    skip: str | None  # the reason a ``no-test`` marker gives, or None


def code_blocks(path: pathlib.Path, language: str) -> list[Block]:
    """The fenced ``language`` blocks of a markdown file, in order, with any ``no-test`` marker before each."""
    blocks, lines = [], path.read_text().splitlines()
    at = 0
    while at < len(lines):
        fence = FENCE.match(lines[at])
        if not fence:
            at += 1
            continue
        end = next(i for i in range(at + 1, len(lines)) if lines[i].startswith("```"))
        marker = SKIP_MARKER.search(lines[at - 1]) if at else None
        if fence.group(1) == language:
            blocks.append(Block(language, "\n".join(lines[at + 1:end]) + "\n", at + 1, marker and marker.group(1)))
        at = end + 1
    return blocks


def shell_commands(code: str) -> list[str]:
    """The lines of a shell block with their ``\\`` continuations joined, comments dropped."""
    joined = re.sub(r"\\\n\s*", " ", code)
    return [line.split(" #")[0].strip() for line in joined.splitlines() if line.strip() and
            not line.lstrip().startswith("#")]


def with_stated_values(code: str) -> str:
    """``code`` with each line that states its value in its comment (:data:`STATED`) asserting it."""
    lines = []
    for line in code.splitlines():
        stated = STATED.match(line)
        lines.append(f"assert ({stated['code']}) == {stated['value']}, {stated['code']}" if stated else line)
    return "\n".join(lines) + "\n"


PYTHON_BLOCKS = code_blocks(README, "python")


@pytest.mark.parametrize("block", PYTHON_BLOCKS, ids=[f"README.md:{b.line}" for b in PYTHON_BLOCKS])
def test_readme_python_block_runs(block, tmp_path):
    if block.skip:
        pytest.skip(block.skip)
    done = subprocess.run([sys.executable, "-c", with_stated_values(block.code)], cwd=tmp_path, capture_output=True,
                          text=True, timeout=SNIPPET_TIMEOUT, env=os.environ | {"OMP_NUM_THREADS": "1"})
    assert done.returncode == 0, f"README.md:{block.line} failed:\n{done.stderr[-3000:]}"


def test_readme_uses_only_dust_rl_commands_that_exist():
    from dust_rl.cli import commands

    table = commands()
    used = set()
    for block in code_blocks(README, "bash"):
        for line in shell_commands(block.code):
            for first, second in COMMAND.findall(line):
                used.add(f"{first} {second}" if f"{first} {second}" in table else first)
    assert used, "no dust-rl command found in the README's bash blocks"
    unknown = sorted(used - set(table))
    assert not unknown, f"the README uses dust-rl commands that do not exist: {unknown}"
    # Each one parses its --help (all in one interpreter: imports once).
    script = ("import sys\nfrom dust_rl.cli import main\nfor name in sys.argv[1:]:\n"
              "    try:\n        main([*name.split(), '--help'])\n    except SystemExit as exit:\n"
              "        assert exit.code in (0, None), (name, exit.code)\n")
    done = subprocess.run([sys.executable, "-c", script, *sorted(used)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-3000:]


def test_readme_commands_give_runtime_settings_as_the_runtime_group():
    """The runtime flags of earlier versions (`--threads 1`, `--no-progress`, a nested training's
    `--train.runtime.threads`) fail today; the README's dust-rl commands spell them `--runtime.*`."""
    from dust_rl.cli import renamed_flag

    stale = [(block.line, arg) for block in code_blocks(README, "bash") for line in shell_commands(block.code)
             if COMMAND.search(line) for arg in line.split()
             if renamed_flag(arg.partition("=")[0]) is not None]
    assert stale == []
    assert any("--runtime.threads" in block.code for block in code_blocks(README, "bash"))  # the check sees them
