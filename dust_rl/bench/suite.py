"""The paper's comparison on our suites: ``dust-rl bench suite``.

DUST's claim is that a world-model stream kept apart from the actions (two
MMDiT streams, decoupled noise) makes a better action policy than an
action-only diffusion head. This command trains every variant of the
comparison (``dust``, ``mmdit_shared``, ``decoupled``, ``joint``,
``action_only``) on the same demonstrations with the same recipe and
training seeds, and evaluates each on the same held-out seeds; then DUST's
test-time scaling (N_A = 4, N_o = q * 4, async) against the synchronous
control (both step counts raised together), DUST acting with its vision
stream left as noise (whether the actions use the predicted future at all),
a data-scaling row (DUST and action_only on the first n demonstrations
per task, n from ``--demos``) and, with ``--video-dataset``, DUST trained
with action-free episodes beside the demonstrations (the paper pretrains
its world model on action-free video; :mod:`dust_rl.train.action_free`).

Every cell is a job cached on disk under ``out``: ``data/<n>/`` (collection,
resumed), ``train/<variant>_seed<s>_demos<n>/`` (training, resumed; skipped
once its ``policy.pt`` exists) and ``eval/<cell>/<sampler>/`` (skipped once
its ``report.json`` exists), so rerunning the command after an interruption
redoes nothing that finished (a cell on disk from other ``--train.*`` settings or
other evaluation seeds is refused, not reused); two suites run side by side on one data
folder take turns (the second waits while the first collects). The budget (episodes to collect, training
steps, evaluation episodes) is printed before anything runs. Output:
``results.json``, ``results.md`` (the paper's form: success with 95%
intervals, episodes pooled over training seeds) and ``results.png`` (bars).
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
from dataclasses import dataclass, field

from matplotlib.figure import Figure

from dust_rl.agents import VARIANTS, SamplerConfig
from dust_rl.agents.config import MAX_STEPS, Variant
from dust_rl.data import collect_demos
from dust_rl.data.seeding import HELDOUT_SEED
from dust_rl.envs.factory import DEFAULT_ENV_ID, env_tasks
from dust_rl.errors import ConfigError, check_at_least
from dust_rl.evaluate.closed_loop import EvalConfig, evaluate, wilson_interval
from dust_rl.evaluate.report import save_png
from dust_rl.storage.atomic_files import write_json_atomic, write_text_atomic
from dust_rl.storage.config_json import config_json
from dust_rl.storage.run_folder import check_run_folder
from dust_rl.train.imitation import RESUMABLE_FIELDS, TrainConfig, TrainSettings, train
from dust_rl.train.recipes import vision_readout
from dust_rl.train.settings import grouped_json

AS_TRAINED = "as trained"  # the sampler name of an evaluation without resampling
WITH_VIDEO = "dust + action-free video"  # the variant label of DUST trained with --video-dataset
VISION_AS_NOISE = "vision as noise N_A=4"  # DUST's actions sampled with its world-model stream left as noise


@dataclass
class SuiteConfig:
    """Train the paper's five variants on the same data and seeds, evaluate them on the same held-out seeds."""

    out: pathlib.Path = pathlib.Path("runs/bench/suite")
    """Folder of every cell (data, train, eval) and of results.json / .md / .png; rerun to resume."""
    env: str = DEFAULT_ENV_ID
    """Gymnasium env id."""
    task: str = "pick_place"
    """Task name, comma-separated names, or `all` (one language-conditioned policy per cell)."""
    demos: tuple[int, ...] = (50, 100, 200)
    """Demonstrations per task; the largest trains every variant, the others give the data-scaling row."""
    variants: tuple[Variant, ...] = VARIANTS
    """Variants to compare (the first two of the data-scaling row: dust and action_only, when listed); none, with
    `video_dataset`: only the action-free row (its baseline DUST cells trained elsewhere)."""
    seeds: tuple[int, ...] = (0, 1)
    """Training seeds; each cell's episodes are pooled over them."""
    train: TrainSettings = field(default_factory=vision_readout)
    """The recipe every cell trains with (`--train.optim.steps`, `--train.policy.d-model` ...; its variant and
    seed are the cell's); default: the quickstart's, which solves press_button in minutes (a comparison means
    little where every variant fails)."""
    video_dataset: pathlib.Path | None = None
    """Episodes of the same robot and cameras (of the same tasks with a read-out, as in the default recipe) that
    DUST also trains on with their actions dropped, one more row at the largest demo count (e.g. more layouts than
    the demonstrations: `dust-rl collect --seed N`); None: no such row."""
    vision_steps: tuple[int, ...] = (4, 8, 16, 32)
    """N_o of DUST's test-time scaling (async, N_A = 4) and of the synchronous control (N_A = N_o)."""
    eval_episodes: int = 20
    """Evaluation episodes per task and cell."""
    eval_seed: int = HELDOUT_SEED
    """First held-out seed (training data: seeds from 0)."""
    image_size: int = 128
    """Camera resolution of the collected data."""
    max_steps: int | None = None
    """Evaluation time limit per episode; default: the task's."""
    workers: int = 1
    """Env processes for collection and evaluation."""
    progress: bool = True
    """Show progress bars."""

    def __post_init__(self) -> None:
        check_at_least(self, 1, "eval_episodes", "image_size", "max_steps", "workers")
        check_at_least(self, 0, "eval_seed")
        if not self.demos or min(self.demos) < 1 or not self.seeds:
            raise ConfigError("demos and seeds must each list at least one value (demos >= 1)")
        if not self.variants and self.video_dataset is None:
            raise ConfigError("variants is empty and there is no --video-dataset: the study would train nothing")
        if any(v % 4 or not 4 <= v <= MAX_STEPS for v in self.vision_steps):  # N_o steps, sync and async
            raise ConfigError(f"vision_steps must be multiples of N_A = 4 in [4, {MAX_STEPS}], got {self.vision_steps}")


@dataclass(frozen=True)
class Cell:
    """One trained policy of the study."""

    variant: str
    seed: int
    demos: int
    video: bool = False  # trained with the action-free episodes too

    @property
    def name(self) -> str:
        return f"{self.variant}{'_video' if self.video else ''}_seed{self.seed}_demos{self.demos}"

    @property
    def label(self) -> str:
        """The variant as the tables name it."""
        return WITH_VIDEO if self.video else self.variant


def samplers(config: SuiteConfig, variant: str) -> dict[str, SamplerConfig | None]:
    """What each policy of ``variant`` is evaluated with, by name: as trained, and for DUST the test-time
    scaling (async, N_A = 4, N_o = q * 4), the synchronous control (N_A = N_o) and its actions sampled with the
    vision stream left as noise (does acting use the predicted future, or did the world model only shape training?)."""
    runs: dict[str, SamplerConfig | None] = {AS_TRAINED: None}
    if variant == "dust":
        runs[VISION_AS_NOISE] = SamplerConfig("action_only", 4)
        for n_o in config.vision_steps:
            runs[f"async N_A=4 N_o={n_o}"] = SamplerConfig("async", 4, n_o // 4)
            runs[f"sync N_A=N_o={n_o}"] = SamplerConfig("sync", n_o)
    return runs


def plan(config: SuiteConfig) -> list[tuple[Cell, str]]:
    """Every (cell, sampler) evaluation of the study."""
    main = max(config.demos)
    cells = [Cell(v, s, main) for v in config.variants for s in config.seeds]
    scaling = [v for v in ("dust", "action_only") if v in config.variants]
    cells += [Cell(v, s, n) for n in sorted(config.demos) if n != main for v in scaling for s in config.seeds]
    if config.video_dataset is not None:
        cells += [Cell("dust", s, main, video=True) for s in config.seeds]
    return [(cell, name) for cell in cells for name in samplers(config, cell.variant)
            if name == AS_TRAINED or (cell.demos == main and not cell.video)]


def run_suite(config: SuiteConfig, command: str | None = None) -> dict:
    """Run (or resume) every cell, then write the tables and the plot; returns the results."""
    tasks = env_tasks(config.env, config.task)
    jobs = plan(config)
    cells = list(dict.fromkeys(cell for cell, _ in jobs))
    steps = config.train.optim.steps
    print(f"budget: collect {max(config.demos)} demonstrations x {len(tasks)} tasks; train {len(cells)} policies "
          f"x {steps} steps ({len(cells) * steps} steps); evaluate {len(jobs)} x "
          f"{config.eval_episodes} episodes x {len(tasks)} tasks "
          f"({len(jobs) * config.eval_episodes * len(tasks)} episodes)")
    env_kwargs = {"image_size": config.image_size}
    for demos in sorted(config.demos):  # the first n seeds of every task: each smaller set is a prefix of the next
        collect_demos(config.out / "data" / str(demos), config.env, tasks, demos, env_kwargs=env_kwargs,
                      workers=config.workers, progress=config.progress, wait_for_writer=True)
    reports = {}
    for cell, name in jobs:
        policy = train_cell(config, cell)
        reports[cell, name] = evaluate_cell(config, cell, name, policy, command)
    results = summarise(config, jobs, reports)
    write_json_atomic(config.out / "results.json", results, indent=2)
    write_text_atomic(config.out / "results.md", markdown(results, command))
    plot(results, config.out / "results.png")
    return results


def train_cell(config: SuiteConfig, cell: Cell) -> pathlib.Path:
    """The cell's policy file, trained (or resumed) unless it is already there.

    Raises:
        ConfigError: the cell on disk was trained with other settings (``--train.*``) than the study asks for.
    """
    out = config.out / "train" / cell.name
    recipe = config.train
    settings = dataclasses.replace(
        recipe, seed=cell.seed, runtime=dataclasses.replace(recipe.runtime, progress=config.progress),
        policy=dataclasses.replace(recipe.policy, variant=cell.variant),
        data=dataclasses.replace(recipe.data, video_dataset=config.video_dataset if cell.video
                                 else recipe.data.video_dataset))
    train_config = TrainConfig.from_settings(settings, dataset=config.out / "data" / str(cell.demos), out=out,
                                             resume=(out / "config.json").is_file())
    if (out / "policy.pt").is_file():
        # a finished cell is reused only for the same study
        check_run_folder(train_config, RESUMABLE_FIELDS, upgrade=grouped_json)
    else:
        train(train_config)
    return out / "policy.pt"


def evaluate_cell(config: SuiteConfig, cell: Cell, name: str, policy: pathlib.Path, command: str | None) -> dict:
    """The cell's evaluation report with sampler ``name``, run unless already on disk.

    Raises:
        ConfigError: the report on disk is of other episodes (seeds, count or step limit) than the study asks for.
    """
    out = config.out / "eval" / cell.name / name.replace(" ", "_").replace("=", "")
    if not (out / "report.json").is_file():
        evaluate(EvalConfig(policy=policy, out=out, episodes=config.eval_episodes, seed=config.eval_seed,
                            workers=config.workers, videos=0, max_steps=config.max_steps,
                            sampling=samplers(config, cell.variant)[name], progress=config.progress), command)
    report = json.loads((out / "report.json").read_text())
    seeds, max_steps = [config.eval_seed, config.eval_seed + config.eval_episodes - 1], config.max_steps
    if report["seeds"] != seeds or report["env_kwargs"].get("max_episode_steps") != max_steps:
        raise ConfigError(f"{out} holds an evaluation of seeds {report['seeds']} (step limit "
                          f"{report['env_kwargs'].get('max_episode_steps')}), the study asks for seeds {seeds} (step "
                          f"limit {max_steps}); use another --out")
    return report


def summarise(config: SuiteConfig, jobs: list[tuple[Cell, str]], reports: dict) -> dict:
    """One row per (variant, demos, sampler): successes pooled over the training seeds, with a 95% interval."""
    rows: dict[tuple, dict] = {}
    for cell, name in jobs:
        report = reports[cell, name]
        key = (cell.label, cell.demos, name)
        row = rows.setdefault(key, {"variant": cell.label, "demos": cell.demos, "sampler": name, "successes": 0,
                                    "episodes": 0, "seeds": [], "per_seed": [],
                                    "trainable_parameters": report["trainable_parameters"]})
        overall = report["overall"]
        row["successes"] += overall["successes"]
        row["episodes"] += overall["episodes"]
        row["seeds"].append(cell.seed)
        row["per_seed"].append(overall["success_rate"])
    for row in rows.values():
        row["success_rate"] = row["successes"] / row["episodes"]
        row["ci95_low"], row["ci95_high"] = wilson_interval(row["successes"], row["episodes"])
    return {"env": config.env, "task": config.task, "main_demos": max(config.demos),
            "eval_seeds": [config.eval_seed, config.eval_seed + config.eval_episodes - 1],
            "train": config_json(config.train),
            "video_dataset": None if config.video_dataset is None else str(config.video_dataset),
            "rows": list(rows.values())}


def markdown(results: dict, command: str | None) -> str:
    """The results in the paper's form: the comparison, test-time scaling, data scaling."""
    main = results["main_demos"]

    def table(title: str, rows: list[dict]) -> list[str]:
        if not rows:  # a study without that part (e.g. --vision-steps with no value, one demo count)
            return []
        lines = [f"## {title}", "", "| variant | demos | sampler | parameters | success | 95% CI | per seed |",
                 "|---|---|---|---|---|---|---|"]
        for r in rows:
            per_seed = " / ".join(f"{100 * s:.0f}%" for s in r["per_seed"])
            lines.append(f"| {r['variant']} | {r['demos']} | {r['sampler']} | {r['trainable_parameters'] / 1e6:.2f}M "
                         f"| {100 * r['success_rate']:.0f}% ({r['successes']}/{r['episodes']}) | "
                         f"{100 * r['ci95_low']:.0f}-{100 * r['ci95_high']:.0f}% | {per_seed} |")
        return [*lines, ""]

    rows = results["rows"]
    lines = [f"# Variant comparison: {results['task']} ({results['env']})", "",
             f"Held-out seeds {results['eval_seeds'][0]}..{results['eval_seeds'][1]} per task; episodes pooled over "
             "training seeds; every cell trained with the same recipe.", ""]
    lines += table("Variants", [r for r in rows if r["demos"] == main and r["sampler"] == AS_TRAINED])
    lines += table("DUST's samplers: test-time scaling, the synchronous control, the vision stream as noise",
                   [r for r in rows if r["demos"] == main and r["sampler"] != AS_TRAINED])
    scaling = [r for r in rows if r["sampler"] == AS_TRAINED and r["variant"] in ("dust", "action_only")]
    if len({r["demos"] for r in scaling}) > 1:  # one demo count: the Variants table already holds these rows
        lines += table("Data scaling", sorted(scaling, key=lambda r: (r["variant"], r["demos"])))
    if command:
        lines += ["Reproduce:", "", f"    {command}", ""]
    return "\n".join(lines)


def percent_with_errors(rows: list[dict]) -> tuple[list[float], list[list[float]]]:
    """Rows' success in percent and their 95% intervals as matplotlib's ``yerr`` (below, above)."""
    rates = [100 * r["success_rate"] for r in rows]
    errors = [[rate - 100 * r["ci95_low"] for rate, r in zip(rates, rows)],
              [100 * r["ci95_high"] - rate for rate, r in zip(rates, rows)]]
    return rates, errors


def plot(results: dict, out_png: pathlib.Path) -> pathlib.Path:
    """Bars of success (with 95% intervals) for every row."""
    rows = results["rows"]
    fig = Figure(figsize=(max(6.0, 0.45 * len(rows)), 4.0), layout="constrained")
    ax = fig.add_subplot()
    x = range(len(rows))
    rates, errors = percent_with_errors(rows)
    ax.bar(x, rates, yerr=errors, capsize=3)
    ax.set_xticks(list(x), [f"{r['variant']} ({r['demos']})\n{r['sampler']}" for r in rows], rotation=60,
                  ha="right", fontsize=7)
    ax.set_ylabel("success (%)")
    ax.set_ylim(0, 100)
    ax.set_title(f"{results['task']}: variants, samplers, demonstrations")
    save_png(fig, out_png)
    return out_png


def suite_command(config: SuiteConfig, command: str | None = None) -> dict:
    """``dust-rl bench suite``: run the study, print where the tables are."""
    results = run_suite(config, command)
    print(f"{len(results['rows'])} rows: {config.out / 'results.md'}, {config.out / 'results.png'}")
    return results
