"""``dust-rl`` command line.

``dust-rl train --recipe NAME ...`` (and ``quickstart``, ``bench suite``) starts from a named, measured recipe
(:data:`dust_rl.train.recipes.RECIPES`; ``dust-rl train`` without it picks one by the dataset), ``--preset NAME``
from a named policy size (:data:`dust_rl.agents.config.POLICY_PRESETS`, laid over the recipe's policy); flags
given beside them (anywhere) still override them.

Bad input ends in one line, ``dust-rl: error: <what is wrong and what to do>`` (exit code 1):
a :class:`~dust_rl.errors.UserError` (bad settings, unusable datasets, a busy dataset folder, a
diverged training run), a corrupt or unfitting checkpoint, or a file system error. Argument syntax
errors, and settings a nested config group refuses (``--model.n-heads 3``), are reported by the
parser, naming the group (exit code 2). Any other exception is a bug and keeps its traceback.
"""

from __future__ import annotations

import os
import shlex
import sys
from collections.abc import Callable
from typing import TYPE_CHECKING, Annotated, Union

import tyro

from dust_rl.errors import CheckpointError, ConfigError, UserError

if TYPE_CHECKING:
    from dust_rl.evaluate.closed_loop import EvalConfig

GROUPS = (tyro.conf.OmitSubcommandPrefixes,)  # "dust-rl dataset info", not "dust-rl dataset action:info"
# Spellings of earlier versions (a whole flag, or a group's prefix ending in "."), today's, and why: refused with
# today's spelling rather than tyro's list of every flag.
_RUNTIME = ("every command's runtime settings are one group (--runtime.threads, --runtime.device, "
            "--runtime.no-progress ...)")
_MODEL = "the policy a command builds is the group --model.*, and --policy PATH a policy file"
RENAMED_FLAGS: dict[str, tuple[str, str]] = {
    **{f"--{name}": (f"--runtime.{name}", _RUNTIME) for name in
       ("threads", "device", "precision", "compile", "no-compile", "progress", "no-progress")},
    "--train.runtime.": ("--runtime.", "the command's training runs under its own --runtime.*"),
    "--policy.": ("--model.", _MODEL), "--train.policy.": ("--train.model.", _MODEL)}
DESCRIPTION = ("DUST (dual-stream diffusion) for torchrl and gymnasium: collect demonstrations, train, evaluate, "
               "fine-tune with RL. `dust-rl COMMAND --help` lists a command's arguments; `dust-rl --version` prints "
               "the version.")


def commands() -> dict[str, tuple[type, Callable[[object, str], object]]]:
    """Every command: name (one or two words) -> (its dataclass of arguments, its runner(config, command line))."""
    from dust_rl.bench.average import AverageConfig, average_command
    from dust_rl.bench.gpu_check import GpuCheckConfig, gpu_check_command
    from dust_rl.bench.steer_speed import SteerSpeedConfig, steer_speed_command
    from dust_rl.bench.suite import SuiteConfig, suite_command
    from dust_rl.bench.train_speed import TrainSpeedConfig, train_speed_command
    from dust_rl.data import commands as data
    from dust_rl.diagnose.cameras import CameraAblation, diagnose_cameras_command
    from dust_rl.diagnose.world_model import WorldModelDiagnosis, diagnose_world_model_command
    from dust_rl.evaluate.closed_loop import EvalConfig
    from dust_rl.quickstart import QuickstartConfig, quickstart
    from dust_rl.rl.finetune import FinetuneCommand, finetune_command
    from dust_rl.train import encoder_commands as encoders
    from dust_rl.train.imitation import TrainConfig, train_command

    return {
        "quickstart": (QuickstartConfig, quickstart),
        "demo": (data.DemoCommand, data.run_demo),
        "expert-table": (data.ExpertTableCommand, data.run_expert_table),
        "collect": (data.CollectCommand, data.run_collect),
        "dataset": (data.DatasetCommand, data.run_dataset),
        "pretrain-encoder": (encoders.PretrainEncoderCommand, encoders.run_pretrain_encoder),
        "encoder": (encoders.EncoderCommand, encoders.run_encoder),
        "train": (TrainConfig, train_command),
        "eval": (EvalConfig, eval_command),
        "finetune": (FinetuneCommand, finetune_command),
        "bench suite": (SuiteConfig, suite_command),
        "bench average": (AverageConfig, average_command),
        "bench gpu": (GpuCheckConfig, gpu_check_command),
        "bench steer-speed": (SteerSpeedConfig, steer_speed_command),
        "bench train-speed": (TrainSpeedConfig, train_speed_command),
        "diagnose world-model": (WorldModelDiagnosis, diagnose_world_model_command),
        "diagnose cameras": (CameraAblation, diagnose_cameras_command),
    }


def eval_command(config: EvalConfig, command: str) -> dict:
    """``dust-rl eval``: a fine-tuned RL agent's ``rl_agent.pt`` through :mod:`dust_rl.rl.fine_tuned_policy`, any
    other policy file through :mod:`dust_rl.evaluate` alone."""
    from dust_rl.evaluate.closed_loop import evaluate_command
    from dust_rl.rl.config import RL_AGENT_KIND
    from dust_rl.rl.fine_tuned_policy import evaluate_agent_command
    from dust_rl.storage.checkpoint_files import checkpoint_kind

    runner = evaluate_agent_command if checkpoint_kind(config.policy) == RL_AGENT_KIND else evaluate_command
    return runner(config, command)


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--version"]:
        from dust_rl import __version__

        print(f"dust-rl {__version__}")
        return
    command_line = shlex.join(["dust-rl", *argv])  # provenance for files a command writes
    table = commands()
    name = " ".join(argv[:2]) if " ".join(argv[:2]) in table else argv[0] if argv else None
    try:
        check_arguments(argv)
        if name in table:  # parsed on its own, so messages name the command ("dust-rl train --help")
            config_class, runner = table[name]
            words = len(name.split())
            args, default = with_preset(name, argv[words:])
            runner(tyro.cli(config_class, args=args, prog=f"dust-rl {name}", config=GROUPS, default=default),
                   command_line)
        else:  # no or an unknown command: tyro lists them all and exits
            choices = Union[tuple(Annotated[cls, tyro.conf.subcommand(name)] for name, (cls, _) in table.items())]  # noqa: UP007
            tyro.cli(choices, args=argv, prog="dust-rl", description=DESCRIPTION, config=GROUPS)
    except (UserError, CheckpointError, OSError) as err:
        # One line: an error re-raised from a worker process carries that process's traceback after its message.
        raise SystemExit(f"dust-rl: error: {str(err).splitlines()[0] if str(err) else type(err).__name__}") from err


def check_arguments(argv: list[str]) -> None:
    """Raise :class:`ConfigError` at a flag spelled as earlier versions did (:data:`RENAMED_FLAGS`: ``--threads``,
    ``--policy.d-model``), at an argument
    that is not UTF-8 text (a path with such a byte: torch's files,
    JSON metadata and tyro need text, and would fail on it deep inside a run) or that is empty: no setting takes
    an empty value, and an empty path is the current folder (``--out "$OUT"`` with ``OUT`` unset would make it a
    dataset or a run)."""
    for previous, arg in zip(["", *argv], argv):
        try:
            arg.encode()
        except UnicodeEncodeError:
            raise ConfigError(f"argument {os.fsencode(arg)!r} is not UTF-8 text; rename the file or folder "
                              "with a UTF-8 name") from None
        flag, equals, value = arg.partition("=")
        if (renamed := renamed_flag(flag)) is not None:
            raise ConfigError(renamed)
        if (equals and flag.startswith("--") and not value) or not arg:
            named = flag if equals else previous if previous.startswith("--") else "an argument"
            raise ConfigError(f"{named} is given an empty value (an unset shell variable?); give it one or drop it")


def renamed_flag(flag: str) -> str | None:
    """What to say of ``flag`` if it is spelled as an earlier version did (:data:`RENAMED_FLAGS`), else None."""
    for old, (today, why) in RENAMED_FLAGS.items():
        if flag == old or (old.endswith(".") and flag.startswith(old)):
            return f"{flag} is spelled {today}{flag.removeprefix(old)}: {why}"
    return None


def with_preset(name: str, args: list[str]) -> tuple[list[str], object | None]:
    """``args`` without ``--recipe NAME`` and ``--preset NAME``, and the default config they give (None: the
    command's own), train, quickstart and bench suite starting from a named recipe (:mod:`dust_rl.train.recipes`;
    ``dust-rl train --resume`` from the run's own saved settings and dataset).

    Raises:
        ConfigError: ``--recipe`` or ``--preset`` where it does not apply, without a name, or with an unknown one.
    """
    if name not in ("train", "quickstart", "bench suite"):
        for flag in ("--recipe", "--preset"):
            if any(arg == flag or arg.startswith(f"{flag}=") for arg in args):
                raise ConfigError(f"{flag} applies to dust-rl train, quickstart and bench suite, not dust-rl {name}")
        return args, None
    from dust_rl.bench.suite import CellTraining, SuiteConfig
    from dust_rl.quickstart import QuickstartConfig
    from dust_rl.train.imitation import TrainConfig
    from dust_rl.train.recipes import starting_settings
    from dust_rl.train.settings import NestedTrainSettings, as_class

    start = starting_settings(name, args)
    if start.settings is None:
        return start.args, None
    if name == "train":
        return start.args, TrainConfig.from_settings(start.settings, **{"dataset": tyro.MISSING, **start.run},
                                                      recipe=start.recipe)
    if name == "quickstart":
        return start.args, QuickstartConfig(recipe=start.recipe, train=as_class(NestedTrainSettings, start.settings))
    return start.args, SuiteConfig(recipe=start.recipe, train=CellTraining.of(start.settings))


if __name__ == "__main__":
    main()
