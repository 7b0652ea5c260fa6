"""``dust-rl bench suite`` on a tiny budget: every cell runs once, the tables come out, a rerun redoes nothing."""

from __future__ import annotations

import dataclasses
import json
import threading
import time

import pytest
import tyro
from test_train import TINY_POLICY

from dust_rl.agents import PolicyConfig, load_policy, save_image_encoder
from dust_rl.bench.suite import (
    AS_TRAINED,
    VISION_AS_NOISE,
    WITH_VIDEO,
    Cell,
    CellTraining,
    SuiteConfig,
    arm_policies,
    arm_policy,
    claim_folder,
    compare,
    markdown,
    pairs,
    plan,
    rows_of,
    run_suite,
    train_cell,
    trunk_parameters,
)
from dust_rl.cli import with_preset
from dust_rl.data.seeding import HELDOUT_SEED, VALIDATION_SEED
from dust_rl.diagnose.world_model import WorldModelDiagnosis, diagnose
from dust_rl.errors import ConfigError
from dust_rl.evaluate.records import t_bounds, t_critical, t_interval
from dust_rl.runtime.settings import RuntimeSettings
from dust_rl.storage.lock import folder_lock
from dust_rl.train.imitation import TrainSettings
from dust_rl.train.recipes import RECIPES, plain, vision_readout
from dust_rl.train.settings import LoggingSettings, OptimSettings

pytestmark = pytest.mark.usefixtures("one_thread")


def test_suite_runs_every_cell_once_writes_the_tables_and_resumes(tiny_encoder, tmp_path, capsys):
    encoder = save_image_encoder(tiny_encoder, tmp_path / "encoder.pt")
    train = CellTraining.of(TrainSettings(policy=PolicyConfig(**TINY_POLICY, image_encoder=str(encoder)),
                                          optim=OptimSettings(steps=2, batch_size=8),
                                          logging=LoggingSettings(log_every=1, checkpoint_every=2)))
    config = SuiteConfig(out=tmp_path / "suite", task="press_button", demos=(1, 2),
                         variants=("dust", "action_only", "dust_no_wm", "action_only_wide"), seeds=(0,),
                         recipe="plain", train=train, arm_steps=("action_only_wide=3",), vision_steps=(4, 8),
                         eval_episodes=1, val_episodes=1, diagnose_episodes=2,
                         image_size=32, max_steps=6, video_dataset=tmp_path / "suite" / "data" / "1",  # collected
                         runtime=RuntimeSettings(threads=1, progress=False))                          # by the suite
    with pytest.raises(ConfigError, match="no cell of this study has finished yet"):
        run_suite(dataclasses.replace(config, finished_only=True))
    results = run_suite(config, "dust-rl bench suite ...")
    assert ("budget: collect 2 demonstrations x 1 tasks; train 7 policies (15 steps in all); evaluate 12 x 1 "
            "episodes x 1 tasks and validate 7 x 1 episodes x 1 tasks (19 episodes); diagnose 5 policies on 2 expert "
            "episodes x 1 tasks") in capsys.readouterr().out
    rows = {(r["variant"], r["demos"], r["sampler"]): r for r in results["rows"]}
    assert set(rows) == {("dust", 2, AS_TRAINED), ("action_only", 2, AS_TRAINED), ("dust_no_wm", 2, AS_TRAINED),
                         ("action_only_wide", 2, AS_TRAINED),
                         ("dust", 2, "async N_A=4 N_o=4"), ("dust", 2, "sync N_A=N_o=4"),
                         ("dust", 2, "async N_A=4 N_o=8"), ("dust", 2, "sync N_A=N_o=8"),
                         ("dust", 2, VISION_AS_NOISE),
                         ("dust", 1, AS_TRAINED), ("action_only", 1, AS_TRAINED), (WITH_VIDEO, 2, AS_TRAINED)}
    assert all(r["episodes"] == 1 and 0 <= r["ci95_low"] <= r["ci95_high"] <= 1 for r in rows.values())
    assert all(r["per_seed_successes"] == [r["successes"]] and r["seed_ci95"] is None  # one training seed
               and r["outcomes"] == {"press_button": {"0": "1" if r["successes"] else "0"}} for r in rows.values())
    parameters = {v: rows[v, 2, AS_TRAINED]["trainable_parameters"] for v in config.variants}
    assert parameters["dust"] == parameters["dust_no_wm"] > parameters["action_only"]
    assert parameters["action_only_wide"] >= parameters["dust"]
    cell = tmp_path / "suite" / "train"
    no_wm, wide = (load_policy(cell / f"{v}_seed0_demos2" / "policy.pt").config for v in ("dust_no_wm",
                                                                                         "action_only_wide"))
    assert (no_wm.variant, no_wm.lambda_wm, no_wm.d_model) == ("dust", 0.0, TINY_POLICY["d_model"])
    assert wide.variant == "action_only" and wide.d_model > TINY_POLICY["d_model"]
    assert wide.d_model % wide.n_heads == 0
    assert results["arms"]["dust_no_wm"] == {"variant": "dust", "policy": {"lambda_wm": 0.0}, "steps": 2,
                                             "description": "DUST's network with the world model's loss off "
                                             "(lambda_wm = 0)"}
    assert results["arms"]["action_only_wide"]["policy"] == {"d_model": wide.d_model}
    assert results["arms"]["action_only_wide"]["steps"] == 3  # its own step count, the others the recipe's
    stored = json.loads((cell / "action_only_wide_seed0_demos2" / "config.json").read_text())["config"]
    assert stored["optim"]["steps"] == 3
    assert results["arms"]["dust"]["policy"] == {} and results["recipe"] == "plain"
    assert json.loads((cell / "dust_seed0_demos2" / "config.json").read_text())["config"]["recipe"] == "plain"
    sync8 = json.loads((tmp_path / "suite" / "eval" / "dust_seed0_demos2" / "sync_N_AN_o8" / "report.json").read_text())
    assert sync8["sampler"] == {"name": "sync", "n_action_steps": 8, "vision_steps": 8, "noise_scale": 1.0}
    noise = json.loads((tmp_path / "suite" / "eval" / "dust_seed0_demos2" / "vision_as_noise_N_A4" /
                        "report.json").read_text())
    assert noise["sampler"]["name"] == "action_only"
    assert [(c["variant"], c["reference"], c["demos"], c["episodes"]) for c in results["comparisons"]] == [
        ("dust", "action_only", 2, 1), ("dust_no_wm", "dust", 2, 1), ("action_only_wide", "dust", 2, 1),
        (WITH_VIDEO, "dust", 2, 1), ("dust", "action_only", 1, 1)]

    # Validation: every cell as trained on its own seeds, reported apart.
    validation = results["validation"]
    assert validation["seeds"] == [VALIDATION_SEED, VALIDATION_SEED]
    assert {(r["variant"], r["demos"]) for r in validation["rows"]} == {(v, d) for v, d, s in rows if s == AS_TRAINED}
    assert all(r["sampler"] == AS_TRAINED for r in validation["rows"])
    assert len(validation["comparisons"]) == len(results["comparisons"])
    report = json.loads((tmp_path / "suite" / "validation" / "dust_seed0_demos2" / "as_trained" /
                         "report.json").read_text())
    assert report["seeds"] == [VALIDATION_SEED, VALIDATION_SEED]
    markdown = (tmp_path / "suite" / "results.md").read_text()
    assert "## Data scaling" in markdown and "| action_only | 1 | as trained |" in markdown
    assert f"| {WITH_VIDEO} | 2 | as trained |" in markdown and "recipe plain" in markdown
    assert "## Paired comparisons" in markdown and "| dust_no_wm | dust | 2 | 1 |" in markdown
    assert f"- action_only_wide (action_only, d_model {wide.d_model}, 3 steps): action_only with its trunk" in markdown
    assert f"{parameters['action_only_wide'] / 1e6:.2f}M trainable parameters against dust's" in markdown
    assert markdown.index("# Validation") > markdown.index("## Paired comparisons") > 0
    assert "## Paired comparisons on validation seeds" in markdown
    assert f"Validation seeds {VALIDATION_SEED}..{VALIDATION_SEED}" in markdown
    video_policy = tmp_path / "suite" / "train" / "dust_video_seed0_demos2" / "policy.pt"
    assert load_policy(video_policy).info["video_dataset"] == str(config.video_dataset)
    assert (tmp_path / "suite" / "results.png").read_bytes()[:4] == b"\x89PNG"

    # The oracle-future test of every policy at the largest demo count, as `dust-rl diagnose world-model` gives it.
    diagnosis = {row["variant"]: row for row in results["diagnosis"]["rows"]}
    assert set(diagnosis) == {*config.variants, WITH_VIDEO}
    assert results["diagnosis"]["first_seed"] == HELDOUT_SEED and results["diagnosis"]["episodes"] == 2
    assert set(diagnosis["dust"]["action_error"]) == {"own", "true", "present", "noise", "other"}
    assert set(diagnosis["dust"]["paired"]) == {"true - noise", "true - present", "own - true"}
    assert set(diagnosis["action_only"]["action_error"]) == {"own"} and diagnosis["action_only"]["skill"] is None
    alone = diagnose(WorldModelDiagnosis(policy=cell / "dust_seed0_demos2" / "policy.pt",
                                         dataset=tmp_path / "suite" / "data" / "heldout_2", out=tmp_path / "alone",
                                         runtime=RuntimeSettings(threads=1, progress=False)))
    assert diagnosis["dust"]["action_error"] == {name: row["action_error"]["mean"]
                                                 for name, row in alone["oracle_future"]["conditions"].items()}
    assert diagnosis["dust"]["skill"] == alone["vision_stream"]["joint_sample"]["skill"]
    dust = diagnosis["dust"]
    oracle_row = ("| dust | 0 | " + " | ".join(f"{dust['action_error'][name]:.4f}" for name in
                                              ("own", "true", "present", "noise", "other")) + " | "
                  + " | ".join(f"{dust['paired'][name]['mean']:+.4f} ({dust['paired'][name]['p']:.3g})" for name in
                               ("true - noise", "true - present", "own - true")) + f" | {dust['skill']:+.2f} |")
    assert "## The oracle-future test" in markdown and oracle_row in markdown
    assert (f"| action_only | 0 | {diagnosis['action_only']['action_error']['own']:.4f} | - | - | - | - | - | - | - "
            "| - |") in markdown

    # A rerun finds every cell on disk: no training, no evaluation, no diagnosis.
    stamps = {p: p.stat().st_mtime_ns for p in (tmp_path / "suite").rglob("*") if p.name in ("policy.pt",
                                                                                            "report.json")}
    assert len(stamps) == 7 + len(rows) + len(validation["rows"]) + len(diagnosis)
    assert run_suite(config) == results
    assert all(p.stat().st_mtime_ns == stamp for p, stamp in stamps.items())

    # The cells finished so far give the interim tables; nothing runs, and the unfinished cell is named.
    missing = tmp_path / "suite" / "validation" / "dust_no_wm_seed0_demos2" / "as_trained" / "report.json"
    kept = missing.read_bytes()
    missing.unlink()
    interim = run_suite(dataclasses.replace(config, finished_only=True), "dust-rl bench suite ...")
    assert not missing.exists() and interim["unfinished"] == ["dust_no_wm_seed0_demos2"]
    assert interim["rows"] == [r for r in results["rows"] if r["variant"] != "dust_no_wm"]
    assert interim["comparisons"] == [c for c in results["comparisons"] if c["variant"] != "dust_no_wm"]
    assert interim["diagnosis"]["rows"] == [r for r in results["diagnosis"]["rows"] if r["variant"] != "dust_no_wm"]
    interim_md = (tmp_path / "suite" / "interim.md").read_text()
    assert "Interim: 1 cells not finished yet (dust_no_wm_seed0_demos2)" in interim_md
    assert (tmp_path / "suite" / "interim.png").is_file()
    assert all(p.stat().st_mtime_ns == stamp for p, stamp in stamps.items() if p != missing)
    missing.write_bytes(kept)
    stamps[missing] = missing.stat().st_mtime_ns

    # Another number of diagnosis episodes diagnoses anew beside the first (one episode: no other episode's future).
    fewer = run_suite(dataclasses.replace(config, diagnose_episodes=1))["diagnosis"]
    with_vision = [row for row in fewer["rows"] if row["skill"] is not None]
    assert fewer["episodes"] == 1 and len(with_vision) == 3 and all("other" in row["skipped"] for row in with_vision)
    assert "dust, seed 0: other not run (fewer than two episodes" in (tmp_path / "suite" / "results.md").read_text()
    assert all(p.stat().st_mtime_ns == stamp for p, stamp in stamps.items())

    # Cells on disk from other settings are refused, not passed off as this study's.
    longer_train = dataclasses.replace(train, optim=dataclasses.replace(train.optim, steps=3))
    longer = dataclasses.replace(config, train=longer_train)
    with pytest.raises(ConfigError, match="other settings"):
        run_suite(longer)
    with pytest.raises(ConfigError, match="holds an evaluation of seeds"):
        run_suite(dataclasses.replace(config, eval_episodes=2))
    with pytest.raises(ConfigError, match="holds an evaluation of seeds"):
        run_suite(dataclasses.replace(config, val_episodes=2))
    assert all(p.stat().st_mtime_ns == stamp for p, stamp in stamps.items())

    # A diagnosis from before a condition was measured is redone, the others kept.
    stale = tmp_path / "suite" / "diagnose" / "heldout_2" / "dust_seed0_demos2" / "report.json"
    older = json.loads(stale.read_text())
    del older["oracle_future"]["conditions"]["present"]
    stale.write_text(json.dumps(older))
    assert run_suite(config)["diagnosis"] == results["diagnosis"]
    assert "present" in json.loads(stale.read_text())["oracle_future"]["conditions"]
    assert all(p.stat().st_mtime_ns == stamp for p, stamp in stamps.items() if p != stale)


@pytest.mark.parametrize("holder", ["suite", "training run"])
def test_a_cell_another_process_holds_comes_last(holder, tiny_encoder, tmp_path, capfd):
    """Two suites on one folder share its cells: while one holds a cell (or a training run its folder), the other
    runs the rest, then waits for it and finds it done (here the test holds it and, as a suite, trains it)."""
    encoder = save_image_encoder(tiny_encoder, tmp_path / "encoder.pt")
    train = CellTraining.of(TrainSettings(policy=PolicyConfig(**TINY_POLICY, image_encoder=str(encoder)),
                                          optim=OptimSettings(steps=2, batch_size=8),
                                          logging=LoggingSettings(checkpoint_every=2)))
    config = SuiteConfig(out=tmp_path / "suite", task="press_button", demos=(1,), variants=("action_only",),
                         seeds=(0, 1), recipe="plain", train=train, vision_steps=(), eval_episodes=1,
                         diagnose_episodes=0, image_size=32, max_steps=6,
                         runtime=RuntimeSettings(threads=1, progress=False))
    held, other = Cell("action_only", 0, 1), Cell("action_only", 1, 1)
    held_folder = claim_folder(config.out, held) if holder == "suite" else config.out / "train" / held.name
    held_folder.mkdir(parents=True, exist_ok=True)
    outcome: list = []

    def run() -> None:
        try:
            outcome.append(run_suite(config))
        except BaseException as err:  # reported below, not lost in the thread
            outcome.append(err)

    def wait_for(done, what: str) -> None:  # a bound on a hang, not a timing test
        deadline = time.monotonic() + 600
        while not done() and suite.is_alive() and time.monotonic() < deadline:
            time.sleep(0.2)
        assert done(), f"the suite did not get to {what}: {outcome}"

    captured = []
    with folder_lock(held_folder):
        suite = threading.Thread(target=run, daemon=True)
        suite.start()
        wait_for((config.out / "eval" / other.name / "as_trained" / "report.json").is_file, "the other cell")
        assert not (config.out / "train" / held.name / "policy.pt").exists()
        if holder == "suite":  # the other suite's work (a training run would take the folder's lock itself)
            trained = train_cell(config, held, arm_policies(config, ["action_only"])["action_only"])
            stamp = trained.stat().st_mtime_ns
        wait_for(lambda: captured.append(capfd.readouterr()) or "waiting for it to finish" in "".join(
            err for _, err in captured), "wait for the held cell")
    assert f"{held.name}: another process works on it; back to it last" in "".join(out for out, _ in captured)
    suite.join(timeout=600)
    assert not suite.is_alive() and isinstance(outcome[0], dict), outcome
    assert [row["seeds"] for row in outcome[0]["rows"]] == [[0, 1]]
    assert (config.out / "eval" / held.name / "as_trained" / "report.json").is_file()
    if holder == "suite":  # found done, not trained again
        assert trained.stat().st_mtime_ns == stamp


def test_suite_settings_are_checked():
    with pytest.raises(ConfigError, match="multiples of N_A = 4"):
        SuiteConfig(vision_steps=(4, 6))
    with pytest.raises(ConfigError, match="at least one value"):
        SuiteConfig(seeds=())
    with pytest.raises(ConfigError, match="would train nothing"):
        SuiteConfig(variants=())
    with pytest.raises(ConfigError, match="unknown variants"):
        SuiteConfig(variants=("dust", "wide"))
    with pytest.raises(ConfigError, match="--reference joint is not one of --variants dust action_only"):
        SuiteConfig(variants=("dust", "action_only"), reference="joint")
    with pytest.raises(ConfigError, match="--arm-steps takes ARM=N"):
        SuiteConfig(variants=("dust",), arm_steps=("dust=0",))
    with pytest.raises(ConfigError, match="--arm-steps names joint, which is not one of --variants dust"):
        SuiteConfig(variants=("dust",), arm_steps=("joint=100",))
    per_arm = SuiteConfig(variants=("dust", "action_only"), arm_steps=("dust=4000",))
    assert (per_arm.steps_of("dust"), per_arm.steps_of("action_only")) == (4000, per_arm.train.optim.steps)
    with pytest.raises(ConfigError, match="reach the held-out seeds"):
        SuiteConfig(val_seed=HELDOUT_SEED - 5, val_episodes=10)
    assert SuiteConfig(val_seed=HELDOUT_SEED - 5, val_episodes=5).validation.seeds == [HELDOUT_SEED - 5,
                                                                                        HELDOUT_SEED - 1]
    assert SuiteConfig().validation is None  # no validation unless asked for
    with pytest.raises(ConfigError, match="reach the held-out seeds"):  # the diagnosis's episodes are held out too
        SuiteConfig(eval_episodes=20, diagnose_episodes=40, val_seed=HELDOUT_SEED + 30, val_episodes=5)


def test_recipe_gives_the_settings_every_cell_trains_with_and_flags_override_it():
    args, default = with_preset("bench suite", ["--recipe", "plain", "--train.optim.steps", "7", "--variants",
                                                "dust_no_wm", "action_only_wide"])
    config = tyro.cli(SuiteConfig, args=args, default=default)
    assert config.recipe == "plain" and config.train == CellTraining.of(
        dataclasses.replace(plain(), optim=dataclasses.replace(plain().optim, steps=7)))
    assert config.variants == ("dust_no_wm", "action_only_wide")
    args, default = with_preset("bench suite", ["--train.optim.steps", "7"])
    config = tyro.cli(SuiteConfig, args=args, default=default)
    assert (config.recipe, config.train.policy, config.train.readout) == (
        "vision-readout", CellTraining.of(vision_readout()).policy, vision_readout().readout)
    with pytest.raises(ConfigError, match="--preset applies to dust-rl train, not dust-rl bench suite"):
        with_preset("bench suite", ["--preset", "gpu-base"])


def test_a_widened_arm_holds_at_least_the_parameters_of_the_arm_it_widens_to_and_no_more_width():
    sizes = {"action_dim": 7, "state_dim": 17, "vision_dim": 40, "aux_state_dim": 0}
    policy = RECIPES["plain"].settings().policy
    dust = trunk_parameters(arm_policy("dust", policy, sizes), sizes)
    wide = arm_policy("action_only_wide", policy, sizes)
    assert wide.variant == "action_only" and wide.d_model % policy.n_heads == 0
    assert trunk_parameters(wide, sizes) >= dust > trunk_parameters(
        dataclasses.replace(wide, d_model=wide.d_model - policy.n_heads), sizes)
    assert arm_policy("dust_no_wm", policy, sizes) == dataclasses.replace(policy, lambda_wm=0.0)
    assert arm_policy("joint", policy, sizes) == dataclasses.replace(policy, variant="joint")


def test_t_interval_is_students_over_the_training_seeds():
    assert [round(t_critical(df), 3) for df in (1, 2, 4, 9, 29)] == [12.706, 4.303, 2.776, 2.262, 2.045]
    low, high = t_interval([0.5, 0.6, 0.7])  # mean 0.6, sd 0.1: 0.6 -/+ 4.303 * 0.1 / sqrt(3)
    assert low == pytest.approx(0.6 - 0.24841, abs=1e-5) and high == pytest.approx(0.6 + 0.24841, abs=1e-5)
    assert t_interval([0.9, 1.0]) == [pytest.approx(0.95 - 12.706 * 0.05, abs=1e-4), 1.0]  # clipped to [0, 1]
    assert t_interval([0.4]) is None
    assert t_bounds([-0.1, 0.1]) == [pytest.approx(-1.2706, abs=1e-4), pytest.approx(1.2706, abs=1e-4)]  # unclipped


def report(task_outcomes: dict[str, str], first_seed: int = 100) -> dict:
    """An evaluation report (the entries the study reads) of each task's episodes, "1" a success, from
    ``first_seed``, listed in reverse seed order (worker processes finish in any order)."""
    tasks = [{"task": task, "per_episode": [[first_seed + i, flag == "1", 5, ""] for i, flag in enumerate(flags)][::-1]}
             for task, flags in task_outcomes.items()]
    successes = sum(flags.count("1") for flags in task_outcomes.values())
    episodes = sum(len(flags) for flags in task_outcomes.values())
    return {"trainable_parameters": 1000, "tasks": tasks,
            "overall": {"successes": successes, "episodes": episodes, "success_rate": successes / episodes}}


def test_rows_keep_each_episode_and_the_comparisons_pair_them_by_task_evaluation_and_training_seed():
    outcomes = {("dust", 0): {"a": "1101", "b": "0011"}, ("dust", 1): {"a": "1111", "b": "0000"},
                ("action_only", 0): {"a": "0101", "b": "0010"}, ("action_only", 1): {"a": "0111", "b": "1000"},
                ("joint", 0): {"a": "1101", "b": "0011"}, ("joint", 1): {"a": "1111", "b": "0000"}}
    jobs = [(Cell(v, s, 10), AS_TRAINED) for v, s in outcomes]
    rows = rows_of(jobs, {(Cell(v, s, 10), AS_TRAINED): report(o) for (v, s), o in outcomes.items()}, [100, 103])
    dust = rows[0]
    assert dust["outcomes"] == {"a": {"0": "1101", "1": "1111"}, "b": {"0": "0011", "1": "0000"}}
    assert (dust["seeds"], dust["per_seed_successes"], dust["per_seed"]) == ([0, 1], [5, 4], [5 / 8, 4 / 8])
    assert (dust["successes"], dust["episodes"]) == (9, 16) and dust["seed_ci95"] == t_interval([5 / 8, 4 / 8])
    # dust wins a's first and b's last episode of seed 0 and a's first of seed 1, loses b's first of seed 1:
    # 3 won, 1 lost, p = 2 * (1 + 4) / 2**4
    # per training seed, dust 5/8 against 3/8, then 4/8 against 4/8
    ahead = {"seed_differences": {"0": 0.25, "1": 0.0}, "difference_ci95": t_bounds([0.25, 0.0])}
    assert compare(rows, None) == [{"variant": "dust", "reference": "action_only", "demos": 10, "episodes": 16,
                                    "gained": 3, "lost": 1, "p_value": 0.625, **ahead},
                                   {"variant": "joint", "reference": "dust", "demos": 10, "episodes": 16,
                                    "gained": 0, "lost": 0, "p_value": 1.0,
                                    "seed_differences": {"0": 0.0, "1": 0.0}, "difference_ci95": [0.0, 0.0]}]
    assert compare(rows, "action_only")[1] == {"variant": "joint", "reference": "action_only", "demos": 10,
                                               "episodes": 16, "gained": 3, "lost": 1, "p_value": 0.625, **ahead}


def test_pairs_compare_dust_with_action_only_and_every_other_arm_with_dust_or_all_with_the_reference():
    arms = ["dust", "action_only", "joint", "dust_no_wm"]
    assert pairs(arms) == [("dust", "action_only"), ("joint", "dust"), ("dust_no_wm", "dust")]
    assert pairs(arms, "joint") == [("dust", "joint"), ("action_only", "joint"), ("dust_no_wm", "joint")]
    assert pairs(["action_only", "joint"]) == [] and pairs(["dust", "joint"], "action_only") == []


def test_cells_run_seed_by_seed_so_a_stopped_study_pairs_its_arms():
    config = SuiteConfig(variants=("dust", "action_only"), seeds=(0, 1), demos=(200,))
    cells = list(dict.fromkeys(cell for cell, _ in plan(config)))
    assert cells == [Cell("dust", 0, 200), Cell("action_only", 0, 200), Cell("dust", 1, 200),
                     Cell("action_only", 1, 200)]


def test_no_variants_with_a_video_dataset_plans_only_the_action_free_row(tmp_path):
    config = SuiteConfig(variants=(), seeds=(0, 1), demos=(50, 200), video_dataset=tmp_path)
    assert plan(config) == [(Cell("dust", 0, 200, video=True), AS_TRAINED), (Cell("dust", 1, 200, video=True),
                                                                            AS_TRAINED)]


def test_the_tables_leave_out_parts_the_study_did_not_run():
    row = {"variant": "joint", "demos": 200, "sampler": AS_TRAINED, "trainable_parameters": 2e6, "success_rate": 0.8,
           "successes": 80, "episodes": 100, "ci95_low": 0.71, "ci95_high": 0.87, "per_seed": [0.76, 0.84],
           "seeds": [0, 1], "per_seed_successes": [38, 42], "seed_ci95": [0.29, 1.0]}
    text = markdown({"task": "press_button", "env": "DustFranka-v0", "eval_seeds": [10000, 10049], "main_demos": 200,
                     "recipe": "plain", "train": {"optim": {"steps": 2000}},
                     "arms": {"joint": {"variant": "joint", "policy": {}, "description": "."}},
                     "rows": [row, {**row, "variant": "action_only"}], "comparisons": [], "validation": None}, None)
    assert ("| joint | 200 | as trained | 2.00M | 80% (80/100) | 71-87% | 29-100% | 0: 76% (38/50) / 1: 84% (42/50) "
            "|") in text
    assert "## Variants" in text and "## Data scaling" not in text and "## DUST's samplers" not in text
    assert "## Paired comparisons" not in text and "# Validation" not in text and "- joint" not in text
    assert "## The oracle-future test" not in text


def test_a_study_of_several_tasks_shows_each_task_pooled_over_training_seeds():
    row = {"variant": "dust", "demos": 100, "sampler": AS_TRAINED, "trainable_parameters": 2e6, "success_rate": 0.5,
           "successes": 4, "episodes": 8, "ci95_low": 0.2, "ci95_high": 0.8, "per_seed": [0.5, 0.5], "seeds": [0, 1],
           "per_seed_successes": [2, 2], "seed_ci95": None,
           "outcomes": {"push": {"0": "11", "1": "10"}, "close_drawer": {"0": "00", "1": "01"}}}
    text = markdown({"task": "all", "env": "DustFranka-v0", "eval_seeds": [10000, 10001], "main_demos": 100,
                     "recipe": "plain", "train": {"optim": {"steps": 2000}}, "arms": {}, "rows": [row],
                     "comparisons": [], "validation": None}, None)
    assert "| variant | close_drawer | push |" in text
    assert "| dust | 25% (1/4) | 75% (3/4) |" in text
    single = markdown({"task": "push", "env": "DustFranka-v0", "eval_seeds": [10000, 10001], "main_demos": 100,
                       "recipe": "plain", "train": {"optim": {"steps": 2000}}, "arms": {},
                       "rows": [{**row, "outcomes": {"push": row["outcomes"]["push"]}}], "comparisons": [],
                       "validation": None}, None)
    assert "## Per task" not in single
