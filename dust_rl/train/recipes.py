"""Named training recipes: measured settings of :class:`~dust_rl.train.settings.TrainSettings`, each with its result.

``dust-rl train --recipe NAME`` and ``dust-rl quickstart --recipe NAME`` start from one; any flag given beside it
overrides that setting, as ``--preset`` (a policy size, laid over the recipe's policy) does. Without ``--recipe``,
``dust-rl train`` picks by the dataset (:func:`default_recipe`): ``vision-readout`` where it records the simulator's
object state (``observation.environment_state``, what the read-out is fitted on), ``plain`` where it does not, and
with ``--resume`` the recipe the run started with (``defaults`` for a run that predates recipes). Which recipe ran
is recorded in the run's ``config.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
from collections.abc import Callable
from dataclasses import dataclass, fields, replace
from typing import Literal

from dust_rl.agents.config import POLICY_PRESETS, PolicyConfig
from dust_rl.data import DatasetError, DemoDataset
from dust_rl.data.features import env_state_width
from dust_rl.errors import ConfigError
from dust_rl.train.settings import DEFAULT_OUT, DataSettings, OptimSettings, ReadoutSettings, TrainSettings


@dataclass(frozen=True)
class Recipe:
    """A measured way to train: its settings, one line on what it is, and where its result is written up."""

    settings: Callable[[], TrainSettings]
    description: str
    result: str


def vision_readout() -> TrainSettings:
    """The quickstart's training: a task that needs vision (press_button: three coloured buttons, the
    instruction names one) solved in minutes. Frozen EfficientNet-Lite0 tokens at stride 8 (16x16 per camera,
    pooled to 8x8 for the trunk), text fused into them, a token read-out of the objects' state fitted first on
    8,000 rendered frames and fed to the trunk, three quarters of each batch from an episode's first 4 rows
    (docs/franka_results.md, "The token read-out"). 2,000 steps: 96% / 84% on 50 validation / held-out seeds and
    14.3 minutes in all on 2 idle cores, where 3,000 steps gave 90% / 86% in 18.0 minutes (README). lr 3e-4, higher
    than the paper's 1e-4: a small model trained for minutes."""
    return replace(plain(), policy=replace(plain().policy, readout="tokens", readout_grid=(16, 16), lambda_aux=1.0,
                                           aux_state_input=True),
                   readout=ReadoutSettings(aux_frames=8000, warmup_steps=4000, demos=False))


def pick_place_readout() -> TrainSettings:
    """The command behind pick_place 90% from 200 demonstrations (README row 3; ``STEPS=20000 bash scripts/recipe.sh
    pick_place 200 pp200_tokro_g16_h4_f32k_w16k_20k ...``): :func:`vision_readout` with the action-only trunk, a
    four-head read-out fitted on 32,000 rendered frames for 16,000 steps, and 20,000 policy steps checkpointed every
    2,000."""
    settings = vision_readout()
    return replace(settings, policy=replace(settings.policy, variant="action_only", readout_heads=4),
                   optim=replace(settings.optim, steps=20000),
                   readout=replace(settings.readout, aux_frames=32000, warmup_steps=16000),
                   logging=replace(settings.logging, checkpoint_every=2000))


def plain() -> TrainSettings:
    """The best recipe that needs no privileged state (docs/results/2026-11-28-world-model-diagnosis.md): frozen
    EfficientNet-Lite0 tokens at stride 8 pooled to 8x8, text fused into them, three quarters of each batch from an
    episode's first 4 rows, 2,000 steps at lr 3e-4; no read-out."""
    return TrainSettings(policy=PolicyConfig(image_encoder="efficientnet-lite0-s8", cond_grid=(8, 8), text_fusion=True),
                         optim=OptimSettings(steps=2000, lr=3e-4), data=DataSettings(start_rows=4, start_fraction=0.75))


RECIPES: dict[str, Recipe] = {
    "vision-readout": Recipe(vision_readout, "plain + a token read-out of the object state fitted first on 8,000 "
                             "rendered frames (needs observation.environment_state); the quickstart's",
                             "README row 10, docs/quickstart.md"),
    "pick-place-readout": Recipe(pick_place_readout, "vision-readout with the action-only trunk, four read-out heads, "
                                 "32,000 frames, 20,000 steps", "README row 3 (pick_place 90%), "
                                 "docs/results/2026-11-22-franka-closed-loop.md"),
    "plain": Recipe(plain, "Lite0 stride-8 tokens, text fusion, first rows, 2,000 steps at lr 3e-4; no privileged "
                    "state", "docs/results/2026-11-28-world-model-diagnosis.md"),
    "defaults": Recipe(TrainSettings, "every setting at its own default: the committed conv-ae encoder, 3,000 steps "
                       "at lr 1e-4 (runs from before recipes resume with it)", "README row 1 (with --optim.lr 3e-4)"),
}
RecipeName = Literal[tuple(RECIPES)]  # type: ignore[valid-type]
LEGACY_RECIPE = "defaults"  # what a run folder that records no recipe was trained from


def recipe_help() -> str:
    """The recipes, one line each, for ``--help``."""
    return "A named recipe to start from (flags given beside it override it). Default: vision-readout where the " \
        "dataset records observation.environment_state, else plain; with --resume, the run's own. " + \
        "; ".join(f"{name}: {recipe.description} [{recipe.result}]" for name, recipe in RECIPES.items())


def default_recipe(dataset: pathlib.Path, out: pathlib.Path, resume: bool) -> tuple[str, str | None]:
    """The recipe ``dust-rl train`` starts from when given none, and one line saying why and how to choose another
    (None for a dataset that does not open: training then says what is wrong with it).

    Raises:
        ConfigError: the run to resume records a recipe this version does not have.
    """
    stored = _stored_config(out) if resume else None
    if stored is not None:
        name = stored.get("recipe", LEGACY_RECIPE)
        if name not in RECIPES:
            raise ConfigError(f"{out} was trained with recipe {name!r}, which this version does not have; start a "
                              f"new run with another --out and one of --recipe {sorted(RECIPES)}")
        return name, f"recipe {name}: the one {out} started with"
    try:
        with_state = env_state_width(DemoDataset(dataset)) > 0
    except DatasetError:
        return "plain", None
    if with_state:
        return "vision-readout", (f"recipe vision-readout: {dataset} records observation.environment_state, which "
                                  "its read-out is fitted on; --recipe plain trains without it")
    return "plain", (f"recipe plain: {dataset} records no observation.environment_state for a read-out; --recipe "
                     "NAME picks another (dust-rl train --help lists them)")


def starting_settings(command: str, args: list[str]) -> tuple[list[str], str | None, TrainSettings | None]:
    """What ``dust-rl train`` / ``quickstart`` starts from: ``args`` without ``--recipe NAME`` and ``--preset NAME``,
    the recipe's name and its settings with the preset's policy size laid over them (None, None: the command's own
    defaults, as for ``--help`` without ``--recipe``).

    Raises:
        ConfigError: an unknown recipe or preset, a flag without its name, ``--preset`` on quickstart.
    """
    args, recipe = _pop_option(args, "--recipe", RECIPES)
    args, preset = _pop_option(args, "--preset", POLICY_PRESETS)
    if preset is not None and command != "train":
        raise ConfigError(f"--preset applies to dust-rl train, not dust-rl {command}")
    if recipe is None and command == "train" and not {"-h", "--help"} & set(args):
        where = _where(args)
        if where.dataset is not None:
            recipe, why = default_recipe(where.dataset, where.out, where.resume)
            if why is not None and not int(os.environ.get("RANK", "0")):  # torchrun's other ranks stay quiet
                print(why)
    if recipe is None and preset is None:
        return args, None, None
    settings = RECIPES[recipe or LEGACY_RECIPE].settings()
    if preset is not None:
        size = {f.name: getattr(POLICY_PRESETS[preset], f.name) for f in fields(PolicyConfig)
                if getattr(POLICY_PRESETS[preset], f.name) != getattr(PolicyConfig(), f.name)}
        settings = replace(settings, policy=replace(settings.policy, **size))
    return args, recipe or LEGACY_RECIPE, settings


def _pop_option(args: list[str], flag: str, choices: dict) -> tuple[list[str], str | None]:
    """``args`` without any ``flag NAME`` (or ``flag=NAME``), and the name given last (None: none given)."""
    kept, given, rest = [], None, iter(args)
    for arg in rest:
        if arg != flag and not arg.startswith(f"{flag}="):
            kept.append(arg)
            continue
        given = arg.partition("=")[2] if arg != flag else next(rest, "nothing")
        if given not in choices:
            raise ConfigError(f"{flag} takes one of {sorted(choices)}, got {given}")
    return kept, given


def _where(args: list[str]) -> argparse.Namespace:
    """``--dataset``, ``--out`` and ``--resume`` as ``args`` give them (the rest left to the command's parser)."""
    parser = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    parser.add_argument("--dataset", type=pathlib.Path)
    parser.add_argument("--out", type=pathlib.Path, default=DEFAULT_OUT)
    parser.add_argument("--resume", action=argparse.BooleanOptionalAction, default=False)
    return parser.parse_known_args(args)[0]


def _stored_config(out: pathlib.Path) -> dict | None:
    """The config a run folder's ``config.json`` records (None: none readable; resuming reports that itself)."""
    try:
        stored = json.loads((out / "config.json").read_text())["config"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return stored if isinstance(stored, dict) else None
