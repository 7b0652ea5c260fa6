"""Every command's ``--help`` reads as plain text: no reStructuredText markup from the docstrings it is built from."""

from __future__ import annotations

import re

import pytest

from dust_rl.cli import commands, main

RST = re.compile(r"``|:(?:mod|func|class|meth|data|attr|obj):`")
# Commands whose help lists nested subcommands: each of those has its own help too.
NESTED = ["dataset info", "encoder check", "finetune steer", "finetune self-imitation", "eval resample"]


def help_text(capsys, args: list[str]) -> str:
    with pytest.raises(SystemExit) as exit_info:
        main([*args, "--help"])
    assert exit_info.value.code == 0
    return capsys.readouterr().out


@pytest.mark.parametrize("command", [*commands(), *NESTED])
def test_help_has_no_rst_markup(capsys, command):
    text = help_text(capsys, command.split())
    assert "usage: dust-rl" in text
    assert RST.findall(text) == []


def test_the_check_sees_markup():
    assert RST.findall("a ``literal`` and :mod:`dust_rl.data`") == ["``", "``", ":mod:`"]
