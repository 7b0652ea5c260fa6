"""``dust-rl bench average``: single-task studies (real, on a tiny budget) pooled into one suite table."""

from __future__ import annotations

import json
import pathlib
import re
import shutil

import pytest
from conftest import as_before_the_groups, make_tiny_encoder
from test_train import TINY_POLICY

from dust_rl.agents import PolicyConfig, save_image_encoder
from dust_rl.bench.average import AverageConfig, average, average_command
from dust_rl.bench.suite import AS_TRAINED, CellTraining, SuiteConfig, run_suite
from dust_rl.errors import ConfigError
from dust_rl.evaluate.records import t_interval
from dust_rl.runtime.settings import RuntimeSettings
from dust_rl.storage.config_json import config_json
from dust_rl.train.imitation import TrainSettings
from dust_rl.train.recipes import plain
from dust_rl.train.settings import LoggingSettings, OptimSettings, TrainRuntime

pytestmark = pytest.mark.usefixtures("one_thread")
KEPT = pathlib.Path(__file__).parent.parent / "docs" / "results" / "franka_100"  # studies from before the outcomes


@pytest.fixture(scope="module")
def two_studies(one_thread, tmp_path_factory):
    """press_button with training seeds 0 and 1, close_drawer with seed 0 only: two real tiny studies."""
    tmp_path = tmp_path_factory.mktemp("studies")
    encoder = save_image_encoder(make_tiny_encoder(), tmp_path / "encoder.pt")
    train = CellTraining.of(TrainSettings(policy=PolicyConfig(**TINY_POLICY, image_encoder=str(encoder)),
                                          optim=OptimSettings(steps=2, batch_size=8),
                                          logging=LoggingSettings(log_every=1, checkpoint_every=2)))
    configs = [SuiteConfig(out=tmp_path / task, task=task, demos=(1,), variants=("dust", "action_only"), seeds=seeds,
                           train=train, vision_steps=(), eval_episodes=2, diagnose_episodes=0, image_size=32,
                           max_steps=6, runtime=RuntimeSettings(threads=1, progress=False))
               for task, seeds in (("press_button", (0, 1)), ("close_drawer", (0,)))]
    return [(config, run_suite(config)) for config in configs]


def test_average_pools_the_shared_seeds_and_refuses_unlike_studies(two_studies, tmp_path, capsys):
    (press, press_results), (drawer, drawer_results) = two_studies
    out = tmp_path / "average"
    result = average_command(AverageConfig(studies=(press.out, drawer.out), out=out), "dust-rl bench average ...")
    assert result["tasks"] == ["close_drawer", "press_button"]
    for variant in ("dust", "action_only"):
        column = result["variants"][variant]
        assert column["seeds"] == [0] and column["left_out_seeds"] == {"press_button": [1]}
        expected = 0
        for results in (press_results, drawer_results):
            row = next(r for r in results["rows"] if r["variant"] == variant and r["sampler"] == AS_TRAINED)
            seed0 = round(row["per_seed"][row["seeds"].index(0)] * 2)
            assert column["per_task"][results["task"]]["successes"] == seed0
            expected += seed0
        assert (column["successes"], column["episodes"]) == (expected, 4)
        assert 0 <= column["ci95"][0] <= column["success_rate"] <= column["ci95"][1] <= 1
        assert column["per_seed"] == {"0": {"successes": expected, "episodes": 4, "success_rate": expected / 4}}
        assert column["seed_ci95"] is None  # one training seed shared
    assert result["recipes"] == ["vision-readout"] and result["without_outcomes"] == []
    [comparison] = result["comparisons"]
    assert {k: comparison[k] for k in ("variant", "reference", "demos", "episodes")} == {
        "variant": "dust", "reference": "action_only", "demos": 1, "episodes": 4}  # seed 0 of two tasks, 2 each
    table = (out / "average.md").read_text()
    assert "| **suite average** |" in table and "left out training seeds 1" in table
    assert "| per training seed | 0: " in table and "| seed 95% CI (t) | - | - |" in table
    assert f"| dust | action_only | 1 | 4 | {comparison['gained']} | {comparison['lost']} |" in table
    assert table in capsys.readouterr().out
    assert json.loads((out / "average.json").read_text()) == result
    assert (out / "average.png").read_bytes()[:4] == b"\x89PNG"
    kept = tmp_path / "kept" / "close_drawer.json"  # a study's results.json kept apart from its folder
    kept.parent.mkdir()
    shutil.copy(drawer.out / "results.json", kept)
    assert average(AverageConfig(studies=(press.out, kept)))["variants"] == result["variants"]

    # Unlike studies are refused: a task twice, another recipe, other evaluation seeds, a folder without results.
    with pytest.raises(ConfigError, match="more than one study"):
        average(AverageConfig(studies=(press.out, drawer.out, press.out)))
    other = tmp_path / "other_recipe"
    shutil.copytree(drawer.out, other)
    results = json.loads((other / "results.json").read_text())
    results["train"]["policy"]["lambda_wm"] = 0.1
    (other / "results.json").write_text(json.dumps(results))
    with pytest.raises(ConfigError, match=r"other settings \(policy.lambda_wm\)"):
        average(AverageConfig(studies=(press.out, other)))
    results["train"]["policy"]["lambda_wm"] = drawer.train.policy.lambda_wm
    results["eval_seeds"] = [5000, 5001]
    (other / "results.json").write_text(json.dumps(results))
    with pytest.raises(ConfigError, match="eval_seeds"):
        average(AverageConfig(studies=(press.out, other)))
    results["eval_seeds"] = drawer_results["eval_seeds"]
    results["arms"]["dust"]["steps"] = drawer.train.optim.steps + 1  # --arm-steps dust=3 in one study only
    (other / "results.json").write_text(json.dumps(results))
    with pytest.raises(ConfigError, match=r"trained dust for other step counts \(3 against 2\)"):
        average(AverageConfig(studies=(press.out, other)))
    with pytest.raises(ConfigError, match="holds no results.json"):
        average(AverageConfig(studies=(press.out, tmp_path / "nothing")))
    with pytest.raises(ConfigError, match="no such results file"):
        average(AverageConfig(studies=(press.out, tmp_path / "kept" / "nothing.json")))
    with pytest.raises(ConfigError, match="at least two"):
        AverageConfig(studies=(press.out,))

    # How a run was carried out (threads, device, logging) is not the recipe: such a study averages.
    results = {**drawer_results, "train": {**drawer_results["train"], "threads": 2, "log_every": 7}}
    (other / "results.json").write_text(json.dumps(results))
    assert average(AverageConfig(studies=(press.out, other)))["variants"] == result["variants"]

    # The settings are compared, not the recipe's name: another recipe is refused, the same settings named
    # otherwise average.
    (other / "results.json").write_text(json.dumps({**drawer_results, "recipe": "plain",
                                                    "train": config_json(plain())}))
    with pytest.raises(ConfigError, match="other settings"):
        average(AverageConfig(studies=(press.out, other)))
    (other / "results.json").write_text(json.dumps({**drawer_results, "recipe": "plain"}))
    assert average(AverageConfig(studies=(press.out, other)))["recipes"] == ["plain", "vision-readout"]


def with_outcomes(study: dict, variant: str, flags: dict[int, str]) -> dict:
    """``study`` (one task) with ``variant``'s episodes set to ``flags`` per training seed ("1" a success), its
    per-seed successes to match."""
    rows = []
    for row in study["rows"]:
        if row["variant"] == variant and row["sampler"] == AS_TRAINED:
            per_seed = [flags[s].count("1") for s in row["seeds"]]
            row = {**row, "outcomes": {study["task"]: {str(s): flags[s] for s in row["seeds"]}},
                   "per_seed_successes": per_seed, "per_seed": [k / len(flags[s]) for k, s in zip(per_seed,
                                                                                                row["seeds"])]}
        rows.append(row)
    return {**study, "rows": rows}


def write_study(path: pathlib.Path, study: dict) -> pathlib.Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(study))
    return path


def test_average_gives_each_training_seed_and_pairs_episodes_over_tasks_and_seeds(two_studies, tmp_path):
    (_, press), _ = two_studies  # press_button with training seeds 0 and 1, and the same study as open_drawer
    studies = []
    for task in ("press_button", "open_drawer"):
        study = with_outcomes({**press, "task": task}, "dust", {0: "11", 1: "10"})
        studies.append(write_study(tmp_path / f"{task}.json", with_outcomes(study, "action_only", {0: "01", 1: "00"})))
    result = average(AverageConfig(studies=tuple(studies)))
    dust = result["variants"]["dust"]
    assert dust["seeds"] == [0, 1] and (dust["successes"], dust["episodes"]) == (6, 8)
    assert dust["per_seed"] == {"0": {"successes": 4, "episodes": 4, "success_rate": 1.0},
                                "1": {"successes": 2, "episodes": 4, "success_rate": 0.5}}
    assert dust["seed_ci95"] == t_interval([1.0, 0.5])
    # dust wins each task's first episode of seed 0 and of seed 1: 4 won, none lost, p = 2 / 2**4; of each training
    # seed's 4 episodes (2 per task) it wins 2 more: a suite-average difference of +0.5 for both seeds
    assert result["comparisons"] == [{"variant": "dust", "reference": "action_only", "demos": 1, "episodes": 8,
                                      "gained": 4, "lost": 0, "p_value": 0.125,
                                      "seed_differences": {"0": 0.5, "1": 0.5}, "difference_ci95": [0.5, 0.5]}]
    assert average(AverageConfig(studies=tuple(studies), reference="dust"))["comparisons"] == [
        {"variant": "action_only", "reference": "dust", "demos": 1, "episodes": 8, "gained": 0, "lost": 4,
         "p_value": 0.125, "seed_differences": {"0": -0.5, "1": -0.5}, "difference_ci95": [-0.5, -0.5]}]
    with pytest.raises(ConfigError, match="--reference joint was not evaluated in every study"):
        average(AverageConfig(studies=tuple(studies), reference="joint"))

    # A study from before the outcomes and the recipe were recorded still averages, without paired comparisons.
    old = {k: v for k, v in json.loads(studies[1].read_text()).items() if k not in ("recipe", "arms", "validation",
                                                                                     "comparisons")}
    old["rows"] = [{k: v for k, v in row.items() if k not in ("outcomes", "per_seed_successes", "seed_ci95")}
                   for row in old["rows"]]
    old_path = write_study(tmp_path / "old" / "open_drawer.json", old)
    before = average_command(AverageConfig(studies=(studies[0], old_path), out=tmp_path / "average"))
    assert before["variants"] == result["variants"] and before["recipes"] == ["vision-readout"]
    assert before["comparisons"] == [] and before["without_outcomes"] == [str(old_path)]
    assert "No paired comparisons: " + str(old_path) in (tmp_path / "average" / "average.md").read_text()


def test_the_kept_studies_from_before_the_outcomes_still_average():
    result = average(AverageConfig(studies=tuple(sorted(KEPT.glob("*.json")))))
    assert len(result["tasks"]) == 8 and result["recipes"] == [] and result["comparisons"] == []
    dust, action_only = result["variants"]["dust"], result["variants"]["action_only"]
    assert (dust["successes"], dust["episodes"], action_only["successes"]) == (175, 400, 196)  # as documented
    assert dust["per_seed"] == {"0": {"successes": 175, "episodes": 400, "success_rate": 175 / 400}}


def test_a_study_from_before_a_setting_was_retired_compares_at_its_retired_value_only():
    from dust_rl.bench.average import recipe

    now = {"train": {"optim": {"lr": 3e-4}, "policy": {"d_model": 32}}}
    before = {"train": {**now["train"], "aux_approach_fraction": 0.0,
                        "policy": {**now["train"]["policy"], "readout_coords": False}}}
    assert recipe(before) == recipe(now)
    other = {"train": {**before["train"], "policy": {**before["train"]["policy"], "readout_coords": True}}}
    assert recipe(other) == {**recipe(now), "policy.readout_coords": True}


def test_a_study_from_before_the_settings_groups_compares_as_todays():
    from dust_rl.bench.average import recipe

    today = {"train": config_json(TrainSettings(optim=OptimSettings(lr=3e-4), runtime=TrainRuntime(threads=2)))}
    before = {"train": as_before_the_groups(today["train"])}
    assert "lr" in before["train"] and "optim" not in before["train"]
    assert recipe(before) == recipe(today) and recipe(today)["optim.lr"] == 3e-4
    assert "runtime.threads" not in recipe(today)  # how a run was carried out, not what it trained
    assert recipe({"train": {**before["train"], "lr": 1e-4}}) == {**recipe(today), "optim.lr": 1e-4}


def _each_row(change):
    def edit(study: dict) -> None:
        for row in study["rows"]:
            change(row)
    return edit


HOSTILE_STUDIES = {
    "rows-null": (lambda s: s.update(rows=None), "rows must be a list of results rows"),
    "successes-above-the-episodes": (_each_row(lambda r: r.update(per_seed_successes=[51])),
                                     r"row 'dust' \('as trained', 100 demos\): per_seed_successes must be one count in "
                                     r"\[0, 50\] per training seed \[0\], got \[51\]"),
    "successes-negative": (_each_row(lambda r: r.update(per_seed_successes=[-3])), r"got \[-3\]"),
    "successes-text": (_each_row(lambda r: r.update(per_seed_successes=["x"])), r"got \['x'\]"),
    "rate-nan": (_each_row(lambda r: r.update(per_seed=[float("nan")])),
                 r"per_seed must be one rate in \[0, 1\] per training seed \[0\], got \[nan\]"),
    "task-with-markup": (lambda s: s.update(task="open_drawer|<script>alert(1)</script>\n# x"),
                         r"task 'open_drawer\|<script>.* is not a task name"),
}


@pytest.mark.parametrize("case", HOSTILE_STUDIES)
def test_a_hostile_results_file_is_refused_naming_it_before_anything_is_written(case, tmp_path):
    """The counts feed Wilson intervals and the task name is written raw into average.md: each is checked on load."""
    edit, problem = HOSTILE_STUDIES[case]
    study = json.loads((KEPT / "open_drawer.json").read_text())
    edit(study)
    path = write_study(tmp_path / "open_drawer.json", study)
    with pytest.raises(ConfigError, match=rf"{re.escape(str(path))}: .*{problem}.*the file was edited: run `dust-rl "
                                          "bench suite` again"):
        average_command(AverageConfig(studies=(KEPT / "push.json", path), out=tmp_path / "average"))
    assert not (tmp_path / "average").exists()


def test_a_cell_report_that_is_no_evaluation_is_refused_naming_it(two_studies):
    """A study reuses the evaluations on disk: one that is not a report (``{}``) ended in a KeyError."""
    (press, results), _ = two_studies
    report = next((press.out / "eval").rglob("report.json"))
    kept = report.read_bytes()
    try:
        report.write_text("{}")
        with pytest.raises(ConfigError, match=rf"{re.escape(str(report))}: not an evaluation report \(no seeds, "
                                              r"env_kwargs, .*\); delete it and run the same command again"):
            run_suite(press)
    finally:
        report.write_bytes(kept)
    assert run_suite(press)["rows"] == results["rows"]
