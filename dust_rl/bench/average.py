"""The paper's comparison over a suite: ``dust-rl bench average`` pools single-task studies.

The paper compares its variants on a suite's average success (RoboCasa, 24 tasks), and so does the goal here
(DUST against action_only on the Franka suite average). ``dust-rl bench suite --task all`` trains one
multi-task policy per cell; the single-task studies (``dust-rl bench suite --task T --out runs/bench/T_100``, one
folder per task, each resumable on its own) give the same average from policies each task can learn in the
quickstart's minutes. This command reads their ``results.json`` and writes one table: a row per task, a column
per variant, and the suite average with its 95% interval. A study can also be given as its ``results.json`` alone
(copied out of its folder, e.g. into ``docs/results/``), so an average outlives the machine its cells ran on.

Only like with like: every study must share the env, the demonstration count, the evaluation seeds and the
training settings (up to those that do not change what is trained: threads, device, logging), and each task
appears once; the settings are compared, not the recipe's name, so a study from before its name was recorded
compares as what it ran. A variant's average pools the training seeds that every study trained it with, so each
task weighs the same (seeds only some studies have are named and left out). Beside the pooled interval stand each
training seed's suite average with the t-interval over them, and every arm's paired comparison with its reference
over the same (task, evaluation seed, training seed) episodes (:func:`dust_rl.bench.suite.pairs`; studies written
before the episodes' outcomes were recorded give none).
"""

from __future__ import annotations

import json
import pathlib
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from matplotlib.figure import Figure

from dust_rl.bench.suite import AS_TRAINED, ArmName, arm_lines, comparison_table, interval, outcomes, pairs
from dust_rl.errors import ConfigError
from dust_rl.evaluate.records import paired, t_interval, wilson_interval
from dust_rl.evaluate.report import percent, save_png
from dust_rl.storage.atomic_files import write_json_atomic, write_text_atomic
from dust_rl.storage.paths import SAFE_NAME
from dust_rl.train.imitation import RESUMABLE_FIELDS
from dust_rl.train.settings import RETIRED_FIELDS, grouped_json

# Training settings that may differ between studies: they change how a run is carried out, not what it trains.
NOT_THE_RECIPE = (*RESUMABLE_FIELDS, "seed", "logging.log_every", "logging.checkpoint_every", "runtime.nproc")
SHARED = ("env", "main_demos", "eval_seeds")  # what every study must have in common besides the recipe
READ = (*SHARED, "task", "train", "rows")  # the entries of results.json this command reads
ROW_KEYS = ("variant", "sampler", "demos", "seeds")  # and of each of its rows
REWRITE = "run `dust-rl bench suite` again into its folder to rewrite it"


@dataclass
class AverageConfig:
    """Pool single-task variant comparisons (`dust-rl bench suite` folders) into a suite average."""

    studies: tuple[pathlib.Path, ...]
    """Folders of `dust-rl bench suite` runs, one task each, or their `results.json` files."""
    out: pathlib.Path = pathlib.Path("runs/bench/suite_average")
    """Folder of `average.md`, `average.json` and `average.png`."""
    reference: ArmName | None = None
    """The arm every other arm is compared with, episode by episode; None: dust against action_only and every
    other arm against dust."""

    def __post_init__(self) -> None:
        if len(self.studies) < 2:
            raise ConfigError(f"--studies needs at least two study folders, got {len(self.studies)}")


def load_study(study: pathlib.Path) -> dict:
    """A study's ``results.json``, given its folder or the file itself.

    Raises:
        ConfigError: the folder holds no finished study, the file given does not exist, or it is not a study's
            results (unreadable, or without the entries this command reads).
    """
    if study.suffix == ".json" and not study.is_file():
        raise ConfigError(f"{study}: no such results file (give a study folder or its results.json)")
    path = study if study.is_file() else study / "results.json"
    if not path.is_file():
        raise ConfigError(f"{study} holds no results.json: run (or finish) `dust-rl bench suite --out {study}`")
    try:
        study = json.loads(path.read_text())
    except (ValueError, RecursionError) as err:  # RecursionError: nested past Python's stack
        raise ConfigError(f"{path}: not a readable results file ({err}); {REWRITE}") from err
    missing = [key for key in READ if key not in study] if isinstance(study, dict) else list(READ)
    if missing:
        raise ConfigError(f"{path}: not a results file (no {', '.join(missing)}); {REWRITE}")
    if problem := study_problem(study):
        raise ConfigError(f"{path}: {problem}; the file was edited: {REWRITE}")
    return study


def study_problem(study: dict) -> str | None:
    """What in ``study`` this command cannot read, in words (None: nothing): a task that is not a task's name (it is
    written into the table and the plot as it is), evaluation seeds that are not a range, rows that are not results
    rows, or a row's per-seed successes that are not one count in [0, episodes per seed] per training seed (rates
    in [0, 1] in a study from before the counts were recorded)."""
    task, seeds, rows = study["task"], study["eval_seeds"], study["rows"]
    if not (isinstance(task, str) and SAFE_NAME.fullmatch(task)):
        return f"task {task!r:.80} is not a task name (letters, digits, '_', '.', '-')"
    if not (isinstance(seeds, list) and len(seeds) == 2 and all(_is_int(s) for s in seeds) and 0 <= seeds[0]
            <= seeds[1]):
        return f"eval_seeds must be [first, last] seeds, got {seeds!r:.80}"
    if not (isinstance(rows, list) and all(isinstance(r, dict) and all(k in r for k in ROW_KEYS) for r in rows)):
        return f"rows must be a list of results rows (each with {', '.join(ROW_KEYS)}), got {rows!r:.80}"
    episodes = seeds[1] - seeds[0] + 1
    for row in rows:
        name = f"row {row['variant']!r:.40} ({row['sampler']!r:.40}, {row['demos']!r:.20} demos)"
        if not _per_seed(row["seeds"], row["seeds"], _is_int):
            return f"{name}: seeds must be a list of training seeds, got {row['seeds']!r:.80}"
        counted = "per_seed_successes" if row.get("per_seed_successes") else "per_seed"
        each, valid = ((f"count in [0, {episodes}]", lambda k: _is_int(k) and 0 <= k <= episodes)
                       if counted == "per_seed_successes" else ("rate in [0, 1]", _is_rate))
        if not _per_seed(row.get(counted), row["seeds"], valid):
            return (f"{name}: {counted} must be one {each} per training seed {row['seeds']}, got "
                    f"{row.get(counted)!r:.80}")
    return None


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_rate(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and 0 <= value <= 1  # NaN is not


def _per_seed(values: object, seeds: list, valid: Callable[[object], bool]) -> bool:
    """Whether ``values`` is a list of one valid value per training seed."""
    return isinstance(values, list) and len(values) == len(seeds) and all(map(valid, values))


def recipe(study: dict) -> dict:
    """The study's training settings that decide what a cell learns, nested groups flattened (``policy.d_model``,
    ``optim.lr``; a study from before the groups has its settings moved into them); a retired setting at the value
    every run now has is left out (a study from before it was retired compares with one from after)."""
    flat = {}
    for key, value in grouped_json(study["train"]).items():
        if isinstance(value, dict):
            flat.update({f"{key}.{k}": v for k, v in value.items()})
        else:
            flat[key] = value
    return {k: v for k, v in flat.items()
            if k not in NOT_THE_RECIPE and (k not in RETIRED_FIELDS or RETIRED_FIELDS[k] != v)}


def arm_steps(study: dict) -> dict[str, int]:
    """The optimiser steps of each of the study's arms (``bench suite --arm-steps``; a study from before records
    none: the recipe's)."""
    steps = recipe(study).get("optim.steps")
    return {name: arm.get("steps", steps) for name, arm in study.get("arms", {}).items()}


def check_comparable(studies: list[tuple[pathlib.Path, dict]]) -> None:
    """Refuse studies that differ in anything but their task.

    Raises:
        ConfigError: naming the first setting that differs, or a task studied twice.
    """
    (first_path, first), *others = studies
    for path, study in others:
        for key in SHARED:
            if study[key] != first[key]:
                raise ConfigError(f"{path} has {key} {study[key]}, {first_path} {first[key]}: average only studies "
                                  "of the same env, demonstration count and evaluation seeds")
        theirs, ours = recipe(study), recipe(first)
        if theirs != ours:
            differs = sorted(k for k in ours.keys() | theirs.keys() if ours.get(k) != theirs.get(k))
            raise ConfigError(f"{path} and {first_path} were trained with other settings ({', '.join(differs)}): "
                              "average only studies of one recipe")
        theirs, ours = arm_steps(study), arm_steps(first)
        if differs := sorted(name for name in ours.keys() & theirs.keys() if ours[name] != theirs[name]):
            raise ConfigError(f"{path} and {first_path} trained {', '.join(differs)} for other step counts "
                              f"({', '.join(f'{theirs[n]} against {ours[n]}' for n in differs)}): average only "
                              "studies of one recipe")
    tasks = [study["task"] for _, study in studies]
    if len(set(tasks)) < len(tasks):
        raise ConfigError(f"a task appears in more than one study ({tasks}): give one folder per task")


def per_seed_successes(row: dict, episodes_per_seed: int) -> dict[int, int]:
    """Successes of each training seed of a results row (recorded; from the rates in studies that predate that)."""
    counts = row.get("per_seed_successes") or [round(rate * episodes_per_seed) for rate in row["per_seed"]]
    return dict(zip(row["seeds"], counts))


def average(config: AverageConfig) -> dict:
    """Per-task success of every variant (as trained) and the suite average over the shared training seeds."""
    studies = [(folder, load_study(folder)) for folder in config.studies]
    check_comparable(studies)
    first = studies[0][1]
    low, high = first["eval_seeds"]
    n = high - low + 1
    rows = {study["task"]: {r["variant"]: per_seed_successes(r, n) for r in study["rows"]
                            if r["sampler"] == AS_TRAINED and r["demos"] == study["main_demos"]}
            for _, study in studies}
    variants = [v for v in dict.fromkeys(v for by_variant in rows.values() for v in by_variant)
                if all(v in by_variant for by_variant in rows.values())]
    if not variants:
        raise ConfigError("no variant was evaluated in every study: nothing to average")
    if config.reference is not None and config.reference not in variants:
        raise ConfigError(f"--reference {config.reference} was not evaluated in every study (those: "
                          f"{', '.join(variants)})")
    columns = {}
    for variant in variants:
        seeds = sorted(set.intersection(*(set(by_variant[variant]) for by_variant in rows.values())))
        if not seeds:
            raise ConfigError(f"{variant}: no training seed is shared by every study")
        left_out = {task: sorted(set(by_variant[variant]) - set(seeds)) for task, by_variant in rows.items()}
        per_task = {task: sum(by_variant[variant][s] for s in seeds) for task, by_variant in rows.items()}
        per_seed = {seed: sum(by_variant[variant][seed] for by_variant in rows.values()) for seed in seeds}
        episodes, seed_episodes = n * len(seeds), n * len(rows)
        successes = sum(per_task.values())
        total = episodes * len(per_task)
        columns[variant] = {
            "seeds": seeds, "left_out_seeds": {t: s for t, s in left_out.items() if s},
            "episodes_per_task": episodes,
            "per_task": {task: {"successes": k, "success_rate": k / episodes} for task, k in per_task.items()},
            "successes": successes, "episodes": total, "success_rate": successes / total,
            "ci95": list(wilson_interval(successes, total)),
            "per_seed": {str(seed): {"successes": k, "episodes": seed_episodes, "success_rate": k / seed_episodes}
                         for seed, k in per_seed.items()},
            "seed_ci95": t_interval([k / seed_episodes for k in per_seed.values()]),
            "trainable_parameters": next(r["trainable_parameters"] for r in first["rows"] if r["variant"] == variant),
        }
    without = [str(path) for path, study in studies if any("outcomes" not in r for r in study["rows"])]
    arms = next((study["arms"] for _, study in studies if "arms" in study), {})
    return {"env": first["env"], "demos": first["main_demos"], "eval_seeds": first["eval_seeds"],
            "recipes": sorted({study["recipe"] for _, study in studies if "recipe" in study}),
            "tasks": sorted(rows), "studies": [str(p) for p in config.studies],
            "arms": {name: arm for name, arm in arms.items() if name in columns},
            "steps": recipe(first).get("optim.steps"), "variants": columns,
            "comparisons": [] if without else compare(studies, columns, config.reference),
            "without_outcomes": without}


def compare(studies: list[tuple[pathlib.Path, dict]], columns: dict[str, dict], reference: str | None) -> list[dict]:
    """Each arm against its reference (:func:`~dust_rl.bench.suite.pairs`), episode by episode over every task,
    evaluation seed and the training seeds both columns pool."""
    found = []
    for arm, ref in pairs(list(columns), reference):
        seeds = set(columns[arm]["seeds"]) & set(columns[ref]["seeds"])
        episodes: dict[str, dict] = {arm: {}, ref: {}}
        for _, study in studies:
            for row in study["rows"]:
                if row["sampler"] == AS_TRAINED and row["demos"] == study["main_demos"] and row["variant"] in episodes:
                    episodes[row["variant"]].update(outcomes(row, seeds))
        found.append({"variant": arm, "reference": ref, "demos": studies[0][1]["main_demos"],
                      **paired(episodes[arm], episodes[ref])})
    return found


def markdown(result: dict, command: str | None) -> str:
    """A row per task, a column per variant, the suite average last."""
    variants = result["variants"]
    names = list(variants)
    recipes = " / ".join(result["recipes"]) or "not recorded"
    lines = [f"# Suite average: {len(result['tasks'])} tasks of {result['env']}, {result['demos']} demonstrations "
             "per task", "",
             f"Held-out seeds {result['eval_seeds'][0]}..{result['eval_seeds'][1]}; per variant, the training seeds "
             f"every study has (episodes pooled over them; 95% CI: Wilson); recipe {recipes}, the same training "
             "settings in every study.", "",
             *arm_lines(result["arms"], {v: c["trainable_parameters"] for v, c in variants.items()},
                        result.get("steps")),
             "| task | " + " | ".join(f"{v} ({variants[v]['trainable_parameters'] / 1e6:.2f}M, seeds "
                                      f"{', '.join(map(str, variants[v]['seeds']))})" for v in names) + " |",
             "|---|" + "---|" * len(names)]
    for task in result["tasks"]:
        cells = []
        for v in names:
            t = variants[v]["per_task"][task]
            cells.append(f"{100 * t['success_rate']:.0f}% ({t['successes']}/{variants[v]['episodes_per_task']})")
        lines.append(f"| {task} | " + " | ".join(cells) + " |")
    lines.append("| **suite average** | " + " | ".join(
        f"**{100 * variants[v]['success_rate']:.0f}%** ({variants[v]['successes']}/{variants[v]['episodes']}; "
        f"CI {100 * variants[v]['ci95'][0]:.0f}-{100 * variants[v]['ci95'][1]:.0f}%)" for v in names) + " |")
    lines.append("| per training seed | " + " | ".join(" / ".join(
        f"{s}: {percent(t['success_rate'])} ({t['successes']}/{t['episodes']})"
        for s, t in variants[v]["per_seed"].items()) for v in names) + " |")
    lines.append("| seed 95% CI (t) | " + " | ".join(interval(variants[v]["seed_ci95"]) for v in names) + " |")
    lines.append("")
    lines += comparison_table(result["comparisons"])
    if result["without_outcomes"]:
        lines.append(f"No paired comparisons: {', '.join(result['without_outcomes'])} predate the record of each "
                     "episode's outcome; run `dust-rl bench suite` again into those folders (every cell is reused) "
                     "to rewrite their results.json.")
    for v in names:
        for task, seeds in variants[v]["left_out_seeds"].items():
            lines.append(f"- {v}, {task}: left out training seeds {', '.join(map(str, seeds))} (not in every study)")
    if command:
        lines += ["", "Reproduce:", "", f"    {command}"]
    return "\n".join(lines) + "\n"


def plot(result: dict, out_png: pathlib.Path) -> pathlib.Path:
    """Grouped bars: each task and the suite average, a bar per variant (the average with its 95% interval)."""
    variants = result["variants"]
    groups = [*result["tasks"], "suite average"]
    width = 0.8 / len(variants)
    fig = Figure(figsize=(max(6.0, 0.9 * len(groups)), 4.0), layout="constrained")
    ax = fig.add_subplot()
    x = np.arange(len(groups))
    for i, (name, column) in enumerate(variants.items()):
        rates = [100 * column["per_task"][t]["success_rate"] for t in result["tasks"]]
        rates.append(100 * column["success_rate"])
        bars = ax.bar(x + (i - (len(variants) - 1) / 2) * width, rates, width, label=name)
        low, high = (100 * c for c in column["ci95"])
        ax.errorbar(bars[-1].get_x() + width / 2, rates[-1], yerr=[[rates[-1] - low], [high - rates[-1]]],
                    color="black", capsize=3)
    ax.set_xticks(x, groups, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("success (%)")
    ax.set_ylim(0, 100)
    ax.legend(fontsize=8)
    ax.set_title(f"{result['env']}, {result['demos']} demonstrations per task, held-out seeds")
    save_png(fig, out_png)
    return out_png


def average_command(config: AverageConfig, command: str | None = None) -> dict:
    """``dust-rl bench average``: write the table and the plot, print where they are."""
    result = average(config)
    config.out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(config.out / "average.json", result, indent=2)
    write_text_atomic(config.out / "average.md", markdown(result, command))
    plot(result, config.out / "average.png")
    print((config.out / "average.md").read_text())
    return result
