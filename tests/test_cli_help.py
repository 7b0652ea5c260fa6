"""Every command's ``--help`` reads as plain text: no reStructuredText markup from the docstrings it is built from."""

from __future__ import annotations

import dataclasses
import inspect
import re
import typing

import pytest

from dust_rl.cli import commands, main
from dust_rl.runtime.settings import RuntimeSettings

RST = re.compile(r"``|:(?:mod|func|class|meth|data|attr|obj):`")
# Commands whose help lists nested subcommands: each of those has its own help too.
NESTED = ["dataset info", "encoder check", "finetune steer", "finetune self-imitation", "eval resample"]
RUNTIME_NAMES = {field.name for field in dataclasses.fields(RuntimeSettings)}  # threads, device, precision ...
# A runtime flag outside the --runtime.* group (`--threads`, `--no-progress`; earlier versions' spellings).
FLAT_RUNTIME_FLAG = re.compile(rf"(?<![\w.-])--(?:no-)?(?:{'|'.join(RUNTIME_NAMES)})(?![\w-])")
# Commands that run a policy or train one, each with the one --runtime.* group.
RUNTIME_COMMANDS = ["quickstart", "collect", "pretrain-encoder", "train", "eval", "finetune steer",
                    "finetune residual", "finetune self-imitation", "bench suite", "bench gpu",
                    "bench steer-speed", "bench train-speed", "diagnose world-model", "diagnose cameras"]


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


def reached_dataclasses(hint: object, reached: dict[type, None], within: tuple[str, ...] = ("dust_rl.",),
                        ) -> dict[type, None]:
    """The dataclasses of the modules named ``within*`` (the dust_rl packages, agents and envs among them) that
    ``hint``, a command's config class or a field's type, reaches through nested dataclass fields, unions of
    subcommands, optional and tuple types, in the order first reached."""
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        if hint in reached or not hint.__module__.startswith(within):
            return reached
        reached[hint] = None
        hints = typing.get_type_hints(hint, include_extras=True)
        for field in dataclasses.fields(hint):
            reached_dataclasses(hints[field.name], reached, within)
    for argument in typing.get_args(hint):  # Annotated[T, ...], T | None, tuple[T, ...], A | B
        reached_dataclasses(argument, reached, within)
    return reached


def declared_by(cls: type, name: str) -> type:
    """The class of ``cls``'s MRO whose own annotations declare the field ``name``."""
    return next(owner for owner in cls.__mro__ if name in inspect.get_annotations(owner))


def declared_outside_the_group(classes: typing.Iterable[type]) -> list[str]:
    """Each field of ``classes`` named as a runtime setting that RuntimeSettings does not declare."""
    return [f"{cls.__module__}.{cls.__qualname__}.{field.name} (declared by {declared_by(cls, field.name).__name__})"
            for cls in classes for field in dataclasses.fields(cls)
            if field.name in RUNTIME_NAMES and declared_by(cls, field.name) is not RuntimeSettings]


def test_runtime_settings_are_declared_only_by_the_runtime_group():
    """Every field named threads, device, precision, compile or progress of a command's config, however deeply
    nested, is RuntimeSettings' own: no command keeps a second, flat or redeclared spelling (`--threads` beside
    `--runtime.threads`, a nested group's suppressed copy)."""
    from dust_rl.bench.suite import CellTraining
    from dust_rl.evaluate.closed_loop import EvalConfig, EvalSetup
    from dust_rl.rl.config import RoundTraining, SelfImitationConfig, SteerConfig
    from dust_rl.train.settings import NestedTrainSettings, TrainRuntime

    reached: dict[type, None] = {}
    for config, _ in commands().values():
        reached_dataclasses(config, reached)
    # The walk reaches the nested and subcommand configs (so the check below sees them), not result records.
    assert {EvalConfig, SteerConfig, SelfImitationConfig, RoundTraining, NestedTrainSettings, CellTraining,
            TrainRuntime, RuntimeSettings} <= set(reached)
    assert EvalSetup not in reached
    assert declared_outside_the_group(reached) == []


@dataclasses.dataclass(kw_only=True)
class _RedeclaredRuntime(RuntimeSettings):
    threads: int = 2


@dataclasses.dataclass
class _FlatCommand:
    nested: tuple[_RedeclaredRuntime, ...] | None = None
    progress: bool = True


def test_the_walk_finds_a_runtime_field_declared_outside_the_group():
    """The check above can fail: a flat field and a nested group's redeclared one are both found."""
    reached = reached_dataclasses(_FlatCommand, {}, within=(__name__, "dust_rl."))
    assert list(reached) == [_FlatCommand, _RedeclaredRuntime]
    assert declared_outside_the_group(reached) == [
        f"{__name__}._FlatCommand.progress (declared by _FlatCommand)",
        f"{__name__}._RedeclaredRuntime.threads (declared by _RedeclaredRuntime)"]


@pytest.mark.parametrize("command", [*commands(), *NESTED, "finetune residual"])
def test_help_offers_runtime_settings_only_in_the_runtime_group(capsys, command):
    text = help_text(capsys, command.split())
    assert FLAT_RUNTIME_FLAG.findall(text) == []
    if command in RUNTIME_COMMANDS:
        assert all(f"--runtime.{name}" in text for name in ("threads", "device", "no-progress")), command


@pytest.mark.parametrize("command", ["quickstart", "bench suite"])
def test_a_command_that_trains_offers_one_runtime_group_not_its_trainings(capsys, command):
    """quickstart and bench suite run the training under their own --runtime.*; a suite's cells take their seed
    from --seeds and their variant from --variants, so the nested training settings offer neither."""
    text = help_text(capsys, command.split())
    assert "--runtime.threads" in text and "--train.optim.steps" in text
    assert "--train.runtime." not in text
    suppressed = re.compile(r"--train\.(?:seed|model\.variant)(?![\w-])")
    assert set(suppressed.findall(text)) == (set() if command == "bench suite"
                                             else {"--train.seed", "--train.model.variant"})
