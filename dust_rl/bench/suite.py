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
once its ``policy.pt`` exists), ``eval/<cell>/<sampler>/`` (skipped once
its ``report.json`` exists) and ``data/heldout_<n>/`` with ``diagnose/heldout_<n>/<cell>/`` (the diagnosis's
episodes and reports), so rerunning the command after an interruption
redoes nothing that finished (a cell on disk from other ``--train.*`` settings or
other evaluation seeds is refused, not reused); two suites run side by side on one data
folder take turns (the second waits while the first collects), and two with one ``out`` share its cells: each
works on the cells the other does not hold (``claims/<cell>/``, a lock; a cell whose training folder another run
holds alike) and ends with those, found done once the other lets go of them, so the same command started twice runs
the study on two cores. The budget (episodes to collect, training steps, evaluation episodes, diagnosed policies)
is printed before anything runs. Output:
``results.json``, ``results.md`` (the paper's form: success with 95%
intervals, episodes pooled over training seeds) and ``results.png`` (bars); ``--finished-only`` writes the same
tables as ``interim.*`` from the cells finished so far, running nothing.

Every cell trains from one named recipe (``--recipe``, :data:`dust_rl.train.recipes.RECIPES`; ``plain`` feeds
no privileged state), recorded in ``results.json``. Beside the paper's five variants the comparison has two
control arms (:data:`ARMS`): ``dust_no_wm``, DUST's network without the world model's loss (does the world model,
or the second stream's capacity, make the difference?), and ``action_only_wide``, action_only widened to at least
DUST's parameters. A seed-level interval (the training seed is the unit a claim generalises over) stands beside
the pooled Wilson interval, and every arm is compared with its reference on the same episodes (same task,
evaluation seed and training seed: the discordant pairs and their exact McNemar p). ``--val-episodes`` also
evaluates every cell on validation seeds, reported apart from the held-out ones, to choose settings on validation
and report them on held-out seeds; ``--arm-steps ARM=N`` trains one arm for its own step count (each arm until its
validation success stops rising, e.g. read off ``dust-rl train --logging.eval-every``'s curve).
``--diagnose-episodes`` runs the oracle-future test of :mod:`dust_rl.diagnose.world_model` on every policy at the
largest demo count, on expert episodes of the held-out seeds: can its actions read a future, and what would a
better world model buy them (:mod:`dust_rl.bench.suite_diagnosis`; one table of ``results.md``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import pathlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import tyro
from matplotlib.figure import Figure

from dust_rl.agents import VARIANTS, PolicyConfig, SamplerConfig
from dust_rl.agents.config import MAX_STEPS, DustConfig, Variant
from dust_rl.agents.encoders.backbone import resolve_image_encoder
from dust_rl.bench.suite_diagnosis import (
    diagnose_policy,
    diagnosis_folder,
    diagnosis_rows,
    diagnosis_table,
    finished_diagnosis,
)
from dust_rl.data import DemoDataset, collect_demos
from dust_rl.data.features import dataset_policy_kwargs, env_state_width
from dust_rl.data.seeding import HELDOUT_SEED, VALIDATION_SEED
from dust_rl.envs.factory import DEFAULT_ENV_ID, env_tasks
from dust_rl.errors import ConfigError, check_at_least
from dust_rl.evaluate.closed_loop import EvalConfig, eval_runtime, evaluate
from dust_rl.evaluate.records import Episode, paired, t_interval, wilson_interval
from dust_rl.evaluate.report import percent, save_png
from dust_rl.storage.atomic_files import write_json_atomic, write_text_atomic
from dust_rl.storage.config_json import config_json
from dust_rl.storage.lock import FolderBusyError, folder_lock
from dust_rl.train.imitation import TrainConfig, check_train_folder, train
from dust_rl.train.recipes import RECIPES, RecipeName
from dust_rl.train.settings import ModelFlags, NestedTrainSettings, TrainRuntime, TrainSettings, as_class

AS_TRAINED = "as trained"  # the sampler name of an evaluation without resampling
WITH_VIDEO = "dust + action-free video"  # the variant label of DUST trained with --video-dataset
VISION_AS_NOISE = "vision as noise N_A=4"  # DUST's actions sampled with its world-model stream left as noise
CELL_REPORT = ("seeds", "env_kwargs", "trainable_parameters", "overall", "tasks")  # a study reads these of a cell
DEFAULT_RECIPE = "vision-readout"  # the quickstart's: a comparison means little where every variant fails


@dataclass(frozen=True)
class Arm:
    """One arm of the comparison: a network variant trained with the study's recipe, with some of the recipe's
    policy settings changed."""

    variant: Variant
    description: str
    policy: tuple[tuple[str, object], ...] = ()
    """Policy settings (fields of :class:`~dust_rl.agents.PolicyConfig`) laid over the recipe's."""
    widen_to: Variant | None = None
    """Widen ``d_model`` (in steps of ``n_heads``) until the trunk holds at least as many parameters as this
    variant's at the recipe's width."""


# Every arm of the study, by the name `--variants` takes: the paper's five variants, then two controls.
ARMS: dict[str, Arm] = {
    "dust": Arm("dust", "two MMDiT streams, decoupled noise (the paper's DUST)"),
    "mmdit_shared": Arm("mmdit_shared", "two MMDiT streams, one shared noise level"),
    "decoupled": Arm("decoupled", "one DiT stream holding both modalities, decoupled noise"),
    "joint": Arm("joint", "one DiT stream holding both modalities, one shared noise level"),
    "action_only": Arm("action_only", "the actions alone, no vision stream"),
    "dust_no_wm": Arm("dust", "DUST's network with the world model's loss off (lambda_wm = 0)",
                      policy=(("lambda_wm", 0.0),)),
    "action_only_wide": Arm("action_only", "action_only with its trunk widened to at least DUST's parameters",
                            widen_to="dust"),
}
ArmName = Literal[tuple(ARMS)]  # type: ignore[valid-type]
# The default comparisons: DUST against action_only, every other arm against DUST.
MAIN_ARM, BASELINE_ARM = "dust", "action_only"


@dataclass(frozen=True)
class Split:
    """A range of evaluation seeds: held-out (to report) or validation (to choose settings on)."""

    folder: str
    """Folder of its evaluations under the study's ``out``."""
    first: int
    episodes: int

    @property
    def seeds(self) -> list[int]:
        """The first and last seed."""
        return [self.first, self.first + self.episodes - 1]


@dataclass(frozen=True)
class ArmPolicy(PolicyConfig):
    """The policy settings every arm trains with; the arm sets the variant (`--variants`)."""

    variant: tyro.conf.Suppress[Variant] = "dust"


@dataclass(kw_only=True)
class CellTraining(NestedTrainSettings):
    """`dust-rl train`'s settings as every cell trains with them: each cell's seed is one of `--seeds`, its variant
    its arm's, its runtime the study's `--runtime.*`."""

    policy: ModelFlags[ArmPolicy] = field(default_factory=ArmPolicy)
    seed: tyro.conf.Suppress[int] = 0

    @classmethod
    def of(cls, settings: TrainSettings) -> CellTraining:
        """A recipe's settings as every cell trains with them."""
        return as_class(cls, dataclasses.replace(settings, policy=as_class(ArmPolicy, settings.policy)))


@dataclass
class SuiteConfig:
    """Train the paper's five variants (and two control arms) on the same data and seeds, evaluate them on the
    same held-out seeds."""

    out: pathlib.Path = pathlib.Path("runs/bench/suite")
    """Folder of every cell (data, train, eval) and of results.json / .md / .png; rerun to resume."""
    env: str = DEFAULT_ENV_ID
    """Gymnasium env id."""
    task: str = "pick_place"
    """Task name, comma-separated names, or `all` (one language-conditioned policy per cell)."""
    demos: tuple[int, ...] = (50, 100, 200)
    """Demonstrations per task; the largest trains every variant, the others give the data-scaling row."""
    variants: tuple[ArmName, ...] = VARIANTS
    """Arms to compare: the paper's five variants and the controls dust_no_wm (DUST without its world-model
    loss) and action_only_wide (action_only widened to at least DUST's parameters); dust and action_only also
    give the data-scaling row. None, with `video_dataset`: only the action-free row (its baseline DUST cells
    trained elsewhere)."""
    seeds: tuple[int, ...] = (0, 1)
    """Training seeds; each cell's episodes are pooled over them."""
    recipe: RecipeName = DEFAULT_RECIPE
    """The named recipe every cell trains from (`dust-rl train --help` lists them; `plain`: no privileged state;
    `--train.*` flags override it); default: the quickstart's, which solves press_button in minutes."""
    train: CellTraining = field(default_factory=lambda: CellTraining.of(RECIPES[DEFAULT_RECIPE].settings()))
    """The settings every cell trains with (`--train.optim.steps`, `--train.model.d-model` ...; defaults from
    `recipe`; its variant and seed are the cell's, its runtime the study's `--runtime.*`)."""
    arm_steps: tuple[str, ...] = ()
    """Optimiser steps of single arms, `ARM=N` each (e.g. `dust=4000 action_only=3000`: each arm trained until its
    validation success stopped rising); the arms not named train `--train.optim.steps`."""
    reference: ArmName | None = None
    """The arm every other arm is compared with, episode by episode; None: dust against action_only and every
    other arm against dust."""
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
    val_episodes: int = 0
    """Validation episodes per task and cell (as trained), reported apart from the held-out ones: choose settings
    on these; 0: none."""
    val_seed: int = VALIDATION_SEED
    """First validation seed (its episodes must not reach the held-out seeds)."""
    diagnose_episodes: int = 20
    """Expert episodes per task, collected from the first held-out seed on, on which every policy at the largest
    demo count gets the oracle-future test (`dust-rl diagnose world-model`); 0: none."""
    image_size: int = 128
    """Camera resolution of the collected data."""
    max_steps: int | None = None
    """Evaluation time limit per episode; default: the task's."""
    workers: int = 1
    """Env processes for collection and evaluation."""
    runtime: TrainRuntime = field(default_factory=TrainRuntime)
    """Where and how every cell trains (`--runtime.threads` ...); evaluations run one thread per worker at fp32
    (`dust_rl.evaluate.closed_loop.eval_runtime`)."""
    finished_only: bool = False
    """Write `interim.json` / `.md` / `.png` from the cells finished so far (policy, evaluations and diagnosis on
    disk), naming the others, and run nothing: a study that takes days can be read as it goes."""

    @property
    def tables_stem(self) -> str:
        """The name (without suffix) of the tables this run writes: ``interim`` with ``finished_only``."""
        return "interim" if self.finished_only else "results"

    def __post_init__(self) -> None:
        check_at_least(self, 1, "eval_episodes", "image_size", "max_steps", "workers")
        check_at_least(self, 0, "eval_seed", "val_episodes", "val_seed", "diagnose_episodes")
        if not self.demos or min(self.demos) < 1 or not self.seeds:
            raise ConfigError("demos and seeds must each list at least one value (demos >= 1)")
        if not self.variants and self.video_dataset is None:
            raise ConfigError("variants is empty and there is no --video-dataset: the study would train nothing")
        if unknown := [v for v in self.variants if v not in ARMS]:
            raise ConfigError(f"unknown variants {unknown}: --variants takes {', '.join(ARMS)}")
        if self.reference is not None and self.reference not in self.variants:
            raise ConfigError(f"--reference {self.reference} is not one of --variants {' '.join(self.variants)}")
        if any(v % 4 or not 4 <= v <= MAX_STEPS for v in self.vision_steps):  # N_o steps, sync and async
            raise ConfigError(f"vision_steps must be multiples of N_A = 4 in [4, {MAX_STEPS}], got {self.vision_steps}")
        for arm in self.steps_by_arm:
            if arm not in self.variants:
                raise ConfigError(f"--arm-steps names {arm}, which is not one of --variants {' '.join(self.variants)}")
        # the held-out seeds of the evaluations and of the diagnosis's expert episodes
        held_out = [self.eval_seed, self.eval_seed + max(self.eval_episodes, self.diagnose_episodes) - 1]
        validation = self.validation.seeds if self.validation else None
        if validation and validation[0] <= held_out[1] and held_out[0] <= validation[1]:
            raise ConfigError(f"validation seeds {validation[0]}..{validation[1]} reach the held-out seeds "
                              f"{held_out[0]}..{held_out[1]}; give another --val-seed")

    @property
    def steps_by_arm(self) -> dict[str, int]:
        """``arm_steps`` read: optimiser steps by arm name.

        Raises:
            ConfigError: an entry that is not ``ARM=N`` with N >= 1.
        """
        steps = {}
        for entry in self.arm_steps:
            arm, _, count = entry.partition("=")
            if not count.isdigit() or int(count) < 1:
                raise ConfigError(f"--arm-steps takes ARM=N with N >= 1 optimiser steps (e.g. dust=4000), "
                                  f"got {entry!r}")
            steps[arm] = int(count)
        return steps

    def steps_of(self, arm: str) -> int:
        """The optimiser steps arm ``arm``'s cells train for."""
        return self.steps_by_arm.get(arm, self.train.optim.steps)

    @property
    def heldout(self) -> Split:
        """The seeds every cell is reported on."""
        return Split("eval", self.eval_seed, self.eval_episodes)

    @property
    def validation(self) -> Split | None:
        """The seeds every cell is validated on (None: no validation)."""
        return Split("validation", self.val_seed, self.val_episodes) if self.val_episodes else None


@dataclass(frozen=True)
class Cell:
    """One trained policy of the study."""

    variant: str  # the arm's name (ARMS)
    seed: int
    demos: int
    video: bool = False  # trained with the action-free episodes too

    @property
    def name(self) -> str:
        return f"{self.variant}{'_video' if self.video else ''}_seed{self.seed}_demos{self.demos}"

    @property
    def label(self) -> str:
        """The arm as the tables name it."""
        return WITH_VIDEO if self.video else self.variant


def samplers(config: SuiteConfig, variant: str) -> dict[str, SamplerConfig | None]:
    """What each policy of arm ``variant`` is evaluated with, by name: as trained, and for DUST the test-time
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
    """Every (cell, sampler) evaluation of the study on held-out seeds, training seed by training seed (every arm of
    seed 0 first), so a study stopped part-way already pairs its arms on the seeds it has run."""
    main = max(config.demos)
    cells = [Cell(v, s, main) for s in config.seeds for v in config.variants]
    scaling = [v for v in (MAIN_ARM, BASELINE_ARM) if v in config.variants]
    cells += [Cell(v, s, n) for n in sorted(config.demos) if n != main for s in config.seeds for v in scaling]
    if config.video_dataset is not None:
        cells += [Cell("dust", s, main, video=True) for s in config.seeds]
    return [(cell, name) for cell in cells for name in samplers(config, cell.variant)
            if name == AS_TRAINED or (cell.demos == main and not cell.video)]


def run_suite(config: SuiteConfig, command: str | None = None) -> dict:
    """Run (or resume) every cell, then write the tables and the plot; returns the results."""
    tasks = env_tasks(config.env, config.task)
    jobs = plan(config)
    cells = list(dict.fromkeys(cell for cell, _ in jobs))
    validation = [(cell, AS_TRAINED) for cell in cells] if config.validation else []
    steps = sum(config.steps_of(cell.variant) for cell in cells)
    diagnosed = [cell for cell in cells if cell.demos == max(config.demos)] if config.diagnose_episodes else []
    splits = [(config.heldout, jobs), *([(config.validation, validation)] if validation else [])]
    if config.finished_only:
        done = [cell for cell in cells if cell_finished(config, cell, splits, cell in diagnosed)]
        if not done:
            raise ConfigError(f"{config.out}: no cell of this study has finished yet (its policy, evaluations and "
                              "diagnosis on disk); run the study without --finished-only")
        unfinished = [cell.name for cell in cells if cell not in done]
        splits = [(split, [job for job in split_jobs if job[0] in done]) for split, split_jobs in splits]
        cells, diagnosed = done, [cell for cell in diagnosed if cell in done]
        return write_results(config, cells, splits, diagnosed, command, unfinished)
    evaluations = (len(jobs) * config.eval_episodes + len(validation) * config.val_episodes) * len(tasks)
    print(f"budget: collect {max(config.demos)} demonstrations x {len(tasks)} tasks; train {len(cells)} policies "
          f"({steps} steps in all); evaluate {len(jobs)} x "
          f"{config.eval_episodes} episodes x {len(tasks)} tasks"
          + (f" and validate {len(validation)} x {config.val_episodes} episodes x {len(tasks)} tasks"
             if validation else "") + f" ({evaluations} episodes)"
          + (f"; diagnose {len(diagnosed)} policies on {config.diagnose_episodes} expert episodes x {len(tasks)} "
             "tasks" if diagnosed else ""))
    env_kwargs = {"image_size": config.image_size}
    for demos in sorted(config.demos):  # the first n seeds of every task: each smaller set is a prefix of the next
        collect_demos(config.out / "data" / str(demos), config.env, tasks, demos, env_kwargs=env_kwargs,
                      workers=config.workers, progress=config.runtime.progress, wait_for_writer=True)
    if diagnosed:
        collect_demos(diagnosis_folder(config.out, "data", config.diagnose_episodes), config.env, tasks,
                      config.diagnose_episodes, env_kwargs=env_kwargs, workers=config.workers,
                      start_seed=config.eval_seed, progress=config.runtime.progress, wait_for_writer=True)
    policies = arm_policies(config, [cell.variant for cell in cells])
    # A cell another suite on this folder works on, or whose training folder another run holds, comes last, once
    # that process lets go of it: then found done, or resumed. (A run started in its folder between the check and
    # training's own lock is refused by that lock.)
    busy = cells
    for wait in (False, True):
        busy, pending = [], busy
        for cell in pending:
            with contextlib.ExitStack() as held:
                try:
                    held.enter_context(folder_lock(claim_folder(config.out, cell), wait=wait))
                    if (trained := config.out / "train" / cell.name).is_dir():
                        with folder_lock(trained, wait=wait):
                            pass
                except FolderBusyError:
                    print(f"{cell.name}: another process works on it; back to it last", flush=True)
                    busy.append(cell)
                    continue
                train_cell(config, cell, policies[cell.variant])
                run_cell(config, cell, splits, cell in diagnosed, command)
    return write_results(config, cells, splits, diagnosed, command)


def run_cell(config: SuiteConfig, cell: Cell, splits: Sequence[tuple[Split, list[tuple[Cell, str]]]],
             diagnosed: bool, command: str | None) -> tuple[dict | None, dict[tuple[str, str], dict]]:
    """Diagnose the cell's trained policy (if ``diagnosed``) and run its evaluations on every split, each unless
    already on disk; returns the diagnosis and the reports by (split folder, sampler name)."""
    policy = config.out / "train" / cell.name / "policy.pt"
    diagnosis = diagnose_cell(config, cell, policy, command) if diagnosed else None
    return diagnosis, {(split.folder, name): evaluate_cell(config, cell, name, policy, split, command)
                       for split, name in cell_evaluations(splits, cell)}


def cell_evaluations(splits: Sequence[tuple[Split, list[tuple[Cell, str]]]], cell: Cell) -> list[tuple[Split, str]]:
    """The (split, sampler name) evaluations the study asks of ``cell``."""
    return [(split, name) for split, split_jobs in splits for job_cell, name in split_jobs if job_cell == cell]


def cell_finished(config: SuiteConfig, cell: Cell, splits: Sequence[tuple[Split, list[tuple[Cell, str]]]],
                  diagnosed: bool) -> bool:
    """Whether the cell's policy, its every evaluation and (if ``diagnosed``) its complete diagnosis are on disk."""
    return ((config.out / "train" / cell.name / "policy.pt").is_file()
            and all((report_folder(config, split, cell, name) / "report.json").is_file()
                    for split, name in cell_evaluations(splits, cell))
            and (not diagnosed or finished_diagnosis(diagnosis_folder(config.out, "diagnose", config.diagnose_episodes)
                                                     / cell.name) is not None))


def write_results(config: SuiteConfig, cells: Sequence[Cell], splits: Sequence[tuple[Split, list[tuple[Cell, str]]]],
                  diagnosed: Sequence[Cell], command: str | None, unfinished: Sequence[str] = ()) -> dict:
    """Read every cell back (all on disk; its training checked against the study's settings), write
    ``<tables_stem>.json`` / ``.md`` / ``.png``; returns the results (with the ``unfinished`` cells' names, if any)."""
    policies = arm_policies(config, [cell.variant for cell in cells])
    reports: dict[str, dict] = {split.folder: {} for split, _ in splits}
    diagnoses: dict[Cell, dict] = {}
    for cell in cells:
        train_cell(config, cell, policies[cell.variant])
        diagnosis, cell_reports = run_cell(config, cell, splits, cell in diagnosed, command)
        if diagnosis is not None:
            diagnoses[cell] = diagnosis
        for (folder, name), report in cell_reports.items():
            reports[folder][cell, name] = report
    results = summarise(config, policies, [(split, split_jobs, reports[split.folder]) for split, split_jobs in splits],
                        diagnoses)
    if unfinished:
        results["unfinished"] = list(unfinished)
    stem = config.tables_stem
    write_json_atomic(config.out / f"{stem}.json", results, indent=2)
    write_text_atomic(config.out / f"{stem}.md", markdown(results, command))
    plot(results, config.out / f"{stem}.png")
    return results


def claim_folder(out: pathlib.Path, cell: Cell) -> pathlib.Path:
    """The folder whose lock a suite holds while it trains, diagnoses and evaluates ``cell``: two suites run with
    one ``out`` share the cells instead of both running each."""
    folder = out / "claims" / cell.name
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def arm_policies(config: SuiteConfig, arms: Sequence[str]) -> dict[str, PolicyConfig]:
    """The policy settings of each arm: the recipe's with the arm's changes (a widened trunk sized on the
    largest demonstration set, whose sizes every set shares)."""
    names = list(dict.fromkeys(arms))
    sizes = (policy_sizes(config.out / "data" / str(max(config.demos)), config.train.policy)
             if any(ARMS[name].widen_to for name in names) else {})
    return {name: arm_policy(name, config.train.policy, sizes) for name in names}


def arm_policy(name: str, policy: PolicyConfig, sizes: Mapping[str, int]) -> PolicyConfig:
    """Arm ``name``'s policy settings: ``policy`` with the arm's variant and changes; a widened arm's ``d_model``
    the smallest multiple of ``n_heads`` up from the recipe's whose trunk holds at least as many parameters as the
    arm it widens to (``sizes``: the data's, :func:`policy_sizes`)."""
    arm = ARMS[name]
    ours = dataclasses.replace(as_class(PolicyConfig, policy), variant=arm.variant, **dict(arm.policy))
    if arm.widen_to is None:
        return ours
    target = trunk_parameters(dataclasses.replace(policy, variant=arm.widen_to), sizes)
    while trunk_parameters(ours, sizes) < target:
        ours = dataclasses.replace(ours, d_model=ours.d_model + ours.n_heads)
    return ours


def policy_sizes(dataset: pathlib.Path, policy: PolicyConfig) -> dict[str, int]:
    """The sizes besides the policy settings that decide a trunk's parameter count, as training builds the
    policy for ``dataset`` (:func:`dust_rl.train.imitation.train`): the data's action and state, the image
    encoder's token, the object state a read-out estimates."""
    data = DemoDataset(dataset)
    kwargs = dataset_policy_kwargs(data)
    return {"action_dim": kwargs["action_dim"], "state_dim": kwargs["state_dim"],
            "vision_dim": resolve_image_encoder(policy.image_encoder).dim,
            "aux_state_dim": env_state_width(data) if policy.lambda_aux else 0}


def trunk_parameters(policy: PolicyConfig, sizes: Mapping[str, int]) -> int:
    """Parameters of ``policy``'s trunk with the data's ``sizes`` (condition tokens at ``d_model``, as training
    builds them), counted without building it (:attr:`~dust_rl.agents.config.DustConfig.n_parameters`).

    Raises:
        ConfigError: the trunk is over the size cap.
    """
    try:
        return DustConfig(**policy.model_settings(), **sizes, cond_dim=policy.d_model).n_parameters
    except ValueError as err:
        raise ConfigError(f"{policy.variant} at d_model {policy.d_model}: {err}") from err


def train_cell(config: SuiteConfig, cell: Cell, policy: PolicyConfig) -> pathlib.Path:
    """The cell's policy file, trained (or resumed) with ``policy`` (its arm's) unless it is already there.

    Raises:
        ConfigError: the cell on disk was trained with other settings (``--train.*``) than the study asks for.
    """
    out = config.out / "train" / cell.name
    recipe = config.train
    settings = recipe.under(
        config.runtime, seed=cell.seed, policy=policy,
        optim=dataclasses.replace(recipe.optim, steps=config.steps_of(cell.variant)),
        data=dataclasses.replace(recipe.data, video_dataset=config.video_dataset if cell.video
                                 else recipe.data.video_dataset))
    train_config = TrainConfig.from_settings(settings, dataset=config.out / "data" / str(cell.demos), out=out,
                                             resume=(out / "config.json").is_file(), recipe=config.recipe)
    if (out / "policy.pt").is_file():
        # a finished cell is reused only for the same study
        check_train_folder(train_config)
    else:
        train(train_config)
    return out / "policy.pt"


def evaluate_cell(config: SuiteConfig, cell: Cell, name: str, policy: pathlib.Path, split: Split,
                  command: str | None) -> dict:
    """The cell's evaluation report with sampler ``name`` on ``split``'s seeds, run unless already on disk.

    Raises:
        ConfigError: the report on disk is of other episodes (seeds, count or step limit) than the study asks for.
    """
    out = report_folder(config, split, cell, name)
    if not (out / "report.json").is_file():
        evaluate(EvalConfig(policy=policy, out=out, episodes=split.episodes, seed=split.first,
                            workers=config.workers, videos=0, max_steps=config.max_steps,
                            sampling=samplers(config, cell.variant)[name], runtime=eval_runtime(config.runtime)),
                 command)
    report = read_cell_report(out / "report.json")
    seeds, max_steps = split.seeds, config.max_steps
    if report["seeds"] != seeds or report["env_kwargs"].get("max_episode_steps") != max_steps:
        raise ConfigError(f"{out} holds an evaluation of seeds {report['seeds']} (step limit "
                          f"{report['env_kwargs'].get('max_episode_steps')}), the study asks for seeds {seeds} (step "
                          f"limit {max_steps}); use another --out")
    return report


def read_cell_report(path: pathlib.Path) -> dict:
    """A cell's evaluation report on disk, checked to hold the entries the study reads from it.

    Raises:
        ConfigError: unreadable, or not an evaluation report (the message says to delete it: the cell is then
            evaluated again).
    """
    again = "delete it and run the same command again to evaluate the cell again"
    try:
        report = json.loads(path.read_text())
    except (ValueError, RecursionError) as err:  # RecursionError: nested past Python's stack
        raise ConfigError(f"{path}: not a readable evaluation report ({err}); {again}") from err
    missing = [key for key in CELL_REPORT if key not in report] if isinstance(report, dict) else list(CELL_REPORT)
    if missing or not all(isinstance(report[key], dict) for key in ("env_kwargs", "overall")):
        raise ConfigError(f"{path}: not an evaluation report (no {', '.join(missing) or 'env_kwargs or overall object'}"
                          f"); {again}")
    return report


def report_folder(config: SuiteConfig, split: Split, cell: Cell, name: str) -> pathlib.Path:
    """Where the cell's evaluation with sampler ``name`` on ``split``'s seeds writes its report."""
    return config.out / split.folder / cell.name / name.replace(" ", "_").replace("=", "")


def diagnose_cell(config: SuiteConfig, cell: Cell, policy: pathlib.Path, command: str | None) -> dict:
    """The world-model diagnosis of the cell's policy on the study's held-out expert episodes, run unless a complete
    one is on disk (:mod:`dust_rl.bench.suite_diagnosis`)."""
    return diagnose_policy(diagnosis_folder(config.out, "diagnose", config.diagnose_episodes) / cell.name, policy,
                           diagnosis_folder(config.out, "data", config.diagnose_episodes),
                           config.runtime, command)


def summarise(config: SuiteConfig, policies: Mapping[str, PolicyConfig],
              splits: Sequence[tuple[Split, list[tuple[Cell, str]], dict]], diagnoses: Mapping[Cell, dict]) -> dict:
    """The study's results: its settings, the arms, per split of seeds the rows and the paired comparisons
    (validation apart, under ``validation``), and the world-model diagnosis of each policy."""
    (heldout, jobs, reports), *validation = splits
    arms = {name: {"variant": policy.variant, "description": ARMS[name].description, "steps": config.steps_of(name),
                   "policy": {f.name: getattr(policy, f.name) for f in dataclasses.fields(policy)
                              if f.name != "variant" and getattr(policy, f.name) != getattr(config.train.policy,
                                                                                                f.name)}}
            for name, policy in policies.items()}

    def split_results(split: Split, jobs: list[tuple[Cell, str]], reports: dict) -> dict:
        rows = rows_of(jobs, reports, split.seeds)
        return {"rows": rows, "comparisons": compare(rows, config.reference)}

    return {"env": config.env, "task": config.task, "recipe": config.recipe, "main_demos": max(config.demos),
            "eval_seeds": heldout.seeds, "train": config_json(config.train.under(config.runtime)),
            "video_dataset": None if config.video_dataset is None else str(config.video_dataset), "arms": arms,
            **split_results(heldout, jobs, reports),
            "validation": {"seeds": validation[0][0].seeds, **split_results(*validation[0])} if validation else None,
            "diagnosis": {"episodes": config.diagnose_episodes, "first_seed": config.eval_seed, "rows": diagnosis_rows(
                {(cell.label, cell.seed): report for cell, report in diagnoses.items()})} if diagnoses else None}


def rows_of(jobs: list[tuple[Cell, str]], reports: dict, eval_seeds: list[int]) -> list[dict]:
    """One row per (arm, demos, sampler): successes pooled over the training seeds with their 95% Wilson
    interval, each training seed's success with the t-interval over them, and every episode's outcome (by task
    and training seed, a string of 1 and 0 in the order of ``eval_seeds``) for paired comparisons."""
    rows: dict[tuple, dict] = {}
    for cell, name in jobs:
        report = reports[cell, name]
        key = (cell.label, cell.demos, name)
        row = rows.setdefault(key, {"variant": cell.label, "demos": cell.demos, "sampler": name, "successes": 0,
                                    "episodes": 0, "seeds": [], "per_seed": [], "per_seed_successes": [],
                                    "trainable_parameters": report["trainable_parameters"], "outcomes": {}})
        overall = report["overall"]
        row["successes"] += overall["successes"]
        row["episodes"] += overall["episodes"]
        row["seeds"].append(cell.seed)
        row["per_seed"].append(overall["success_rate"])
        row["per_seed_successes"].append(overall["successes"])
        for task in report["tasks"]:
            success = {e.seed: e.success for e in map(Episode.from_json, task["per_episode"])}
            row["outcomes"].setdefault(task["task"], {})[str(cell.seed)] = "".join(
                "1" if success[seed] else "0" for seed in range(eval_seeds[0], eval_seeds[1] + 1))
    for row in rows.values():
        row["success_rate"] = row["successes"] / row["episodes"]
        row["ci95_low"], row["ci95_high"] = wilson_interval(row["successes"], row["episodes"])
        row["seed_ci95"] = t_interval(row["per_seed"])
    return list(rows.values())


def pairs(arms: Sequence[str], reference: str | None = None) -> list[tuple[str, str]]:
    """(arm, reference) pairs to compare among ``arms``: each against ``reference``; None: dust against
    action_only and every other arm against dust."""
    if reference is not None:
        return [(arm, reference) for arm in arms if arm != reference and reference in arms]
    first = [(MAIN_ARM, BASELINE_ARM)] if MAIN_ARM in arms and BASELINE_ARM in arms else []
    return first + [(arm, MAIN_ARM) for arm in arms if MAIN_ARM in arms and arm not in (MAIN_ARM, BASELINE_ARM)]


def outcomes(row: dict, seeds: Sequence[int] | None = None) -> dict[tuple[str, int, int], bool]:
    """A row's episodes by (task, training seed, evaluation seed's place), of ``seeds`` only if given."""
    return {(task, int(seed), i): flag == "1" for task, by_seed in row["outcomes"].items()
            for seed, flags in by_seed.items() if seeds is None or int(seed) in seeds for i, flag in enumerate(flags)}


def compare(rows: list[dict], reference: str | None) -> list[dict]:
    """The paired comparisons of the as-trained rows at each demonstration count (:func:`pairs`)."""
    found = []
    for demos in sorted({r["demos"] for r in rows}, reverse=True):
        by_arm = {r["variant"]: r for r in rows if r["demos"] == demos and r["sampler"] == AS_TRAINED}
        found += [{"variant": arm, "reference": ref, "demos": demos,
                   **paired(outcomes(by_arm[arm]), outcomes(by_arm[ref]))}
                  for arm, ref in pairs(list(by_arm), reference)]
    return found


def interval(bounds: Sequence[float] | None) -> str:
    """A 95% interval in percent ("-" where there is none)."""
    return "-" if bounds is None else f"{100 * bounds[0]:.0f}-{100 * bounds[1]:.0f}%"


def comparison_table(comparisons: list[dict], title: str = "Paired comparisons") -> list[str]:
    """Markdown lines of the paired comparisons (none: no lines)."""
    if not comparisons:
        return []
    lines = [f"## {title}", "",
             "Each episode of an arm against its reference's on the same task, evaluation seed and training seed: "
             "won, the arm succeeds where the reference fails; lost, the reverse; the exact McNemar p of that split. "
             "The success difference per training seed, and the t-interval of its mean over the training seeds "
             "(the seed, not the episode, is what a claim about training generalises over).",
             "", "| arm | reference | demos | paired episodes | won | lost | McNemar p | difference per training "
             "seed | seed 95% CI (t) |", "|---|---|---|---|---|---|---|---|---|"]
    lines += [f"| {c['variant']} | {c['reference']} | {c['demos']} | {c['episodes']} | {c['gained']} | {c['lost']} "
              f"| {c['p_value']:.3g} | {seed_differences(c['seed_differences'])} "
              f"| {points_interval(c['difference_ci95'])} |" for c in comparisons]
    return [*lines, ""]


def seed_differences(differences: Mapping[str, float]) -> str:
    """Each training seed's success difference, in points."""
    return " / ".join(f"{seed}: {100 * d:+.0f}" for seed, d in differences.items())


def points_interval(bounds: Sequence[float] | None) -> str:
    """An interval of a success difference, in points ("-" where there is none)."""
    return "-" if bounds is None else f"{100 * bounds[0]:+.0f} to {100 * bounds[1]:+.0f} points"


def markdown(results: dict, command: str | None) -> str:
    """The results in the paper's form: the comparison (and per task, for several), test-time scaling, data scaling,
    the paired comparisons, the oracle-future test, then the validation seeds' apart."""
    main = results["main_demos"]

    def table(title: str, rows: list[dict]) -> list[str]:
        if not rows:  # a study without that part (e.g. --vision-steps with no value, one demo count)
            return []
        lines = [f"## {title}", "", "| variant | demos | sampler | parameters | success | 95% CI | seed 95% CI (t) "
                 "| per training seed |", "|---|---|---|---|---|---|---|---|"]
        for r in rows:
            episodes = r["episodes"] // len(r["seeds"])
            per_seed = " / ".join(f"{s}: {percent(rate)} ({k}/{episodes})" for s, rate, k in
                                  zip(r["seeds"], r["per_seed"], r["per_seed_successes"]))
            lines.append(f"| {r['variant']} | {r['demos']} | {r['sampler']} | {r['trainable_parameters'] / 1e6:.2f}M "
                         f"| {percent(r['success_rate'])} ({r['successes']}/{r['episodes']}) | "
                         f"{interval([r['ci95_low'], r['ci95_high']])} | {interval(r['seed_ci95'])} | {per_seed} |")
        return [*lines, ""]

    rows = results["rows"]
    lines = [f"# Variant comparison: {results['task']} ({results['env']})", "",
             f"Held-out seeds {results['eval_seeds'][0]}..{results['eval_seeds'][1]} per task; every cell trained "
             f"from recipe {results['recipe']} with the same settings (but those listed below); episodes pooled over "
             "training seeds (95% CI: Wilson, over the pooled episodes), beside the t-interval over the training "
             "seeds' success.", ""]
    if unfinished := results.get("unfinished"):
        lines += [f"Interim: {len(unfinished)} cells not finished yet ({', '.join(unfinished)}); their arms' rows "
                  "hold the finished training seeds only, and each comparison pairs the seeds both arms have.", ""]
    lines += arm_lines(results["arms"], {r["variant"]: r["trainable_parameters"] for r in rows},
                       results["train"]["optim"]["steps"])
    lines += table("Variants", [r for r in rows if r["demos"] == main and r["sampler"] == AS_TRAINED])
    lines += per_task_table([r for r in rows if r["demos"] == main and r["sampler"] == AS_TRAINED])
    lines += table("DUST's samplers: test-time scaling, the synchronous control, the vision stream as noise",
                   [r for r in rows if r["demos"] == main and r["sampler"] != AS_TRAINED])
    scaling = [r for r in rows if r["sampler"] == AS_TRAINED and r["variant"] in (MAIN_ARM, BASELINE_ARM)]
    if len({r["demos"] for r in scaling}) > 1:  # one demo count: the Variants table already holds these rows
        lines += table("Data scaling", sorted(scaling, key=lambda r: (r["variant"], r["demos"])))
    lines += comparison_table(results["comparisons"])
    lines += diagnosis_table(results.get("diagnosis"))  # results from before the diagnosis hold none
    validation = results["validation"]
    if validation:
        seeds = validation["seeds"]
        lines += ["# Validation", "", f"Validation seeds {seeds[0]}..{seeds[1]} per task, apart from the held-out "
                  "ones: choose settings on these, report the held-out tables above.", ""]
        lines += table("Variants on validation seeds", validation["rows"])
        lines += comparison_table(validation["comparisons"], "Paired comparisons on validation seeds")
    if command:
        lines += ["Reproduce:", "", f"    {command}", ""]
    return "\n".join(lines)


def per_task_table(rows: list[dict]) -> list[str]:
    """Markdown lines of each row's success per task, pooled over training seeds (one task: no lines)."""
    tasks = sorted({task for r in rows for task in r.get("outcomes", {})})
    if len(tasks) < 2:
        return []
    lines = ["## Per task", "", "Success per task, as trained, episodes pooled over training seeds.", "",
             "| variant | " + " | ".join(tasks) + " |", "|---|" + "---|" * len(tasks)]
    for r in rows:
        cells = []
        for task in tasks:
            flags = "".join(r.get("outcomes", {}).get(task, {}).values())
            cells.append(f"{percent(flags.count('1') / len(flags))} ({flags.count('1')}/{len(flags)})" if flags
                         else "-")
        lines.append(f"| {r['variant']} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def arm_lines(arms: Mapping[str, dict], parameters: Mapping[str, int], steps: int | None) -> list[str]:
    """One line per arm of ``arms`` (a results file's) that changes the recipe's policy settings or its ``steps``:
    what it changes and, for a widened one, its trainable ``parameters`` against those of the arm it widens to."""
    lines = []
    for name, arm in arms.items():
        own_steps = arm.get("steps", steps)  # results from before --arm-steps record none
        if not arm["policy"] and own_steps == steps:
            continue
        changes = ", ".join([f"{k} {v}" for k, v in arm["policy"].items()]
                            + ([f"{own_steps} steps"] if own_steps != steps else []))
        widen_to = ARMS[name].widen_to if name in ARMS else None
        size = (f"; {parameters[name] / 1e6:.2f}M trainable parameters against {widen_to}'s "
                f"{parameters[widen_to] / 1e6:.2f}M" if widen_to in parameters and name in parameters else "")
        lines.append(f"- {name} ({arm['variant']}, {changes}): {arm['description']}{size}")
    return [*lines, ""] if lines else []


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
    stem = config.tables_stem
    print(f"{len(results['rows'])} rows: {config.out / f'{stem}.md'}, {config.out / f'{stem}.png'}")
    return results
