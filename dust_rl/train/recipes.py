"""Named training recipes: measured settings of :class:`~dust_rl.train.settings.TrainSettings`, each with its result.

``dust-rl train --recipe NAME`` and ``dust-rl quickstart --recipe NAME`` start from one; any flag given beside it
overrides that setting, as ``--preset`` (a policy size, laid over the recipe's policy) does. Without ``--recipe``,
``dust-rl train`` picks by the dataset (:func:`default_recipe`): ``vision-readout`` where it records the simulator's
object state (``observation.environment_state``, what the read-out is fitted on), ``plain`` where it does not. Which
recipe ran is recorded in the run's ``config.json``, and ``--resume`` starts from the settings recorded there (the
run's recipe with its flags; ``defaults`` for a run that predates recipes), so a flag is needed only to change one
a run may change between sittings (:data:`~dust_rl.train.imitation.RESUMABLE_FIELDS`).

A recipe's read-out is fitted for its own step count: ``vision-readout`` renders 8,000 aux frames and fits 4,000
warm-up steps before its 2,000 policy steps. ``dust-rl train --optim.steps N`` with fewer steps than the recipe's
scales both down with N (:func:`scaled_to_steps`), so a short trial run does not spend minutes on a full run's
read-out; at the recipe's step count and above they are the recipe's.
"""

from __future__ import annotations

import argparse
import os
import pathlib
from collections.abc import Callable
from dataclasses import dataclass, fields, replace
from typing import Literal, NamedTuple

from dust_rl.agents.config import POLICY_PRESETS, PolicyConfig
from dust_rl.data import DatasetError, DemoDataset
from dust_rl.data.features import env_state_width
from dust_rl.errors import ConfigError
from dust_rl.storage.config_json import config_from_json
from dust_rl.storage.run_folder import saved_run_config
from dust_rl.train.settings import (
    DEFAULT_OUT,
    RETIRED_RUN_SETTINGS,
    DataSettings,
    OptimSettings,
    ReadoutSettings,
    TrainSettings,
    grouped_json,
)


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
    14.3 minutes in all on 2 idle cores (2026-11-25), where 3,000 steps gave 90% / 86% in 18.0 minutes; 98% held-out
    in 17.8 minutes on a 2-core AVX-512 CPU (2026-12-01), 96% in 16.5 minutes on a 2-core CPU's AVX2 paths with
    placed read-out frames (2026-12-02, docs/quickstart.md). lr 3e-4, higher than the paper's 1e-4:
    a small model trained for minutes."""
    return replace(plain(), policy=replace(plain().policy, readout="tokens", readout_grid=(16, 16), lambda_aux=1.0,
                                           aux_state_input=True),
                   readout=ReadoutSettings(aux_frames=8000, warmup_steps=4000, demos=False))


def action_only() -> TrainSettings:
    """The recipe behind pick_place 92% from 2,000 demonstrations (docs/franka_results.md, "The recipe at 50 episodes
    per seed set"; ``bash scripts/recipe.sh pick_place 2000``): :func:`plain` with the action-only trunk, 20,000
    steps checkpointed every 2,000."""
    settings = plain()
    return replace(settings, policy=replace(settings.policy, variant="action_only"),
                   optim=replace(settings.optim, steps=20000), logging=replace(settings.logging, checkpoint_every=2000))


def pick_place_readout() -> TrainSettings:
    """The command behind pick_place 90% from 200 demonstrations (README row 3; ``bash scripts/recipe.sh pick_place
    200 RUN --recipe pick-place-readout``): :func:`action_only` with :func:`vision_readout`'s token read-out, four
    heads, fitted on 32,000 rendered frames for 16,000 steps."""
    settings, readout = action_only(), vision_readout()
    return replace(settings, policy=replace(readout.policy, variant="action_only", readout_heads=4),
                   readout=replace(readout.readout, aux_frames=32000, warmup_steps=16000))


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
    "pick-place-readout": Recipe(pick_place_readout, "action-only with vision-readout's read-out, four heads, "
                                 "32,000 frames, 16,000 warm-up steps", "README rows 2-9 (pick_place 90%), "
                                 "docs/results/2026-11-22-franka-closed-loop.md"),
    "action-only": Recipe(action_only, "plain with the action-only trunk, 20,000 steps; no privileged state",
                          "docs/franka_results.md (pick_place 92% from 2,000 demonstrations)"),
    "plain": Recipe(plain, "Lite0 stride-8 tokens, text fusion, first rows, 2,000 steps at lr 3e-4; no privileged "
                    "state", "docs/results/2026-11-28-world-model-diagnosis.md"),
    "defaults": Recipe(TrainSettings, "every setting at its own default: the committed conv-ae encoder, 3,000 steps "
                       "at lr 1e-4 (runs from before recipes resume with it)", "README row 1 (with --optim.lr 3e-4)"),
}
RecipeName = Literal[tuple(RECIPES)]  # type: ignore[valid-type]
LEGACY_RECIPE = "defaults"  # what a run folder that records no recipe was trained from


def recipe_help() -> str:
    """The recipes, one line each, for ``--help``."""
    return "A named recipe to start from (flags given beside it override it; with fewer --optim.steps than its own, " \
        "its read-out's aux frames and warm-up steps scale down with them). Default: vision-readout where the " \
        "dataset records observation.environment_state, else plain; with --resume, the run's own settings. " + \
        "; ".join(f"{name}: {recipe.description} [{recipe.result}]" for name, recipe in RECIPES.items())


def default_recipe(dataset: pathlib.Path) -> tuple[str, str | None]:
    """The recipe ``dust-rl train`` starts a new run from when given none, and one line saying why and how to choose
    another (None for a dataset that does not open: training then says what is wrong with it)."""
    try:
        with_state = env_state_width(DemoDataset(dataset)) > 0
    except DatasetError:
        return "plain", None
    if with_state:
        return "vision-readout", (f"recipe vision-readout: {dataset} records observation.environment_state, which "
                                  "its read-out is fitted on; --recipe plain trains without it")
    return "plain", (f"recipe plain: {dataset} records no observation.environment_state for a read-out; --recipe "
                     "NAME picks another (dust-rl train --help lists them)")


def scaled_to_steps(settings: TrainSettings, steps: int) -> TrainSettings:
    """``settings`` (a recipe's) for a run of ``steps`` optimiser steps: below the recipe's own count, its read-out's
    aux frames and warm-up steps in proportion to them (rounded down, at least one of each it has), so a trial run
    of 20 steps does not render 8,000 frames and fit 4,000 warm-up steps first; at or above it, unchanged."""
    own = settings.optim.steps
    if steps >= own:
        return settings

    def scaled(count: int) -> int:
        return max(1, count * steps // own) if count else 0

    return replace(settings, optim=replace(settings.optim, steps=steps),
                   readout=replace(settings.readout, aux_frames=scaled(settings.readout.aux_frames),
                                   warmup_steps=scaled(settings.readout.warmup_steps)))


class Start(NamedTuple):
    """What ``dust-rl train`` / ``quickstart`` / ``bench suite`` start from (:func:`starting_settings`)."""

    args: list[str]
    """The command line without ``--recipe NAME`` and ``--preset NAME``."""
    recipe: str | None
    """The recipe's name (None where ``settings`` is)."""
    settings: TrainSettings | None
    """The settings to parse the command line over (None: the command's own defaults, as for ``--help``)."""
    run: dict[str, pathlib.Path]
    """On ``--resume``, the resumed run's own ``dataset`` and ``cache_dir`` (what it trains on beside the settings)."""


def starting_settings(command: str, args: list[str]) -> Start:
    """What ``dust-rl train`` / ``quickstart`` starts from: the recipe (``--recipe``, else one chosen by the data
    (:func:`default_recipe`), scaled to the ``--optim.steps`` given (:func:`scaled_to_steps`); with ``--resume``
    the run's own saved settings) with the preset's policy size laid over it.

    Raises:
        ConfigError: an unknown recipe or preset, a flag without its name, ``--preset`` on quickstart, a run to
            resume that records a recipe this version does not have or another than ``--recipe`` names.
        FileNotFoundError: ``--resume`` without a run to resume.
    """
    args, recipe = _pop_option(args, "--recipe", RECIPES)
    args, preset = _pop_option(args, "--preset", POLICY_PRESETS)
    if preset is not None and command != "train":
        raise ConfigError(f"--preset applies to dust-rl train, not dust-rl {command}")
    where = _where(args) if command == "train" and not {"-h", "--help"} & set(args) else None
    settings, run, why = None, {}, None
    if where is not None and where.resume:
        recipe, settings, run = _resumed(where.out, recipe)
        why = f"recipe {recipe}: the one {where.out} started with, resumed with the settings it saved"
    elif recipe is None and where is not None and where.dataset is not None:
        recipe, why = default_recipe(where.dataset)
    if why is not None and not int(os.environ.get("RANK", "0")):  # torchrun's other ranks stay quiet
        print(why)
    if recipe is None and preset is None:
        return Start(args, None, None, run)
    if settings is None:
        settings = RECIPES[recipe or LEGACY_RECIPE].settings()
        if where is not None and where.steps is not None:
            settings = scaled_to_steps(settings, where.steps)
    if preset is not None:
        size = {f.name: getattr(POLICY_PRESETS[preset], f.name) for f in fields(PolicyConfig)
                if getattr(POLICY_PRESETS[preset], f.name) != getattr(PolicyConfig(), f.name)}
        settings = replace(settings, policy=replace(settings.policy, **size))
    return Start(args, recipe or LEGACY_RECIPE, settings, run)


def _resumed(out: pathlib.Path, given: str | None) -> tuple[str, TrainSettings, dict[str, pathlib.Path]]:
    """The recipe, settings and dataset (and cache folder) the run in ``out`` saved, which ``--resume`` starts from.

    Raises:
        ConfigError: a recipe this version does not have, or another than ``given`` (``--recipe``).
        FileNotFoundError: no run in ``out``.
    """
    stored = saved_run_config(out, RETIRED_RUN_SETTINGS, grouped_json)
    name = stored.get("recipe", LEGACY_RECIPE)
    if name not in RECIPES:
        raise ConfigError(f"{out} was trained with recipe {name!r}, which this version does not have; start a "
                          f"new run with another --out and one of --recipe {sorted(RECIPES)}")
    if given not in (None, name):
        raise ConfigError(f"--recipe {given}: {out} was started with recipe {name}, whose saved settings --resume "
                          "restores; drop --recipe, or start a new run with another --out")
    run = {key: pathlib.Path(stored[key]) for key in ("dataset", "cache_dir") if stored.get(key) is not None}
    return name, config_from_json(TrainSettings, stored), run


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
    """``--dataset``, ``--out``, ``--resume`` and ``--optim.steps`` as ``args`` give them (the rest, and a step count
    that is not a number, left to the command's parser)."""
    parser = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    parser.add_argument("--dataset", type=pathlib.Path)
    parser.add_argument("--out", type=pathlib.Path, default=DEFAULT_OUT)
    parser.add_argument("--resume", action=argparse.BooleanOptionalAction, default=False)
    parser.add_argument("--optim.steps", dest="steps")
    where = parser.parse_known_args(args)[0]
    where.steps = int(where.steps) if where.steps is not None and where.steps.isdigit() else None
    return where
