"""``dust-rl bench average``: single-task studies (real, on a tiny budget) pooled into one suite table."""

from __future__ import annotations

import json
import shutil

import pytest
from conftest import as_before_the_groups
from test_train import TINY_POLICY

from dust_rl.agents import PolicyConfig, save_image_encoder
from dust_rl.bench.average import AverageConfig, average, average_command
from dust_rl.bench.suite import AS_TRAINED, SuiteConfig, run_suite
from dust_rl.errors import ConfigError
from dust_rl.storage.config_json import config_json
from dust_rl.train.imitation import TrainSettings
from dust_rl.train.settings import LoggingSettings, OptimSettings, RuntimeSettings

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture
def two_studies(tiny_encoder, tmp_path):
    """press_button with training seeds 0 and 1, close_drawer with seed 0 only: two real tiny studies."""
    encoder = save_image_encoder(tiny_encoder, tmp_path / "encoder.pt")
    train = TrainSettings(policy=PolicyConfig(**TINY_POLICY, image_encoder=str(encoder)),
                          optim=OptimSettings(steps=2, batch_size=8),
                          logging=LoggingSettings(log_every=1, checkpoint_every=2),
                          runtime=RuntimeSettings(threads=1, progress=False))
    configs = [SuiteConfig(out=tmp_path / task, task=task, demos=(1,), variants=("dust", "action_only"), seeds=seeds,
                           train=train, vision_steps=(), eval_episodes=2, image_size=32, max_steps=6, progress=False)
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
    table = (out / "average.md").read_text()
    assert "| **suite average** |" in table and "left out training seeds 1" in table
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

    today = {"train": config_json(TrainSettings(optim=OptimSettings(lr=3e-4), runtime=RuntimeSettings(threads=2)))}
    before = {"train": as_before_the_groups(today["train"])}
    assert "lr" in before["train"] and "optim" not in before["train"]
    assert recipe(before) == recipe(today) and recipe(today)["optim.lr"] == 3e-4
    assert "runtime.threads" not in recipe(today)  # how a run was carried out, not what it trained
    assert recipe({"train": {**before["train"], "lr": 1e-4}}) == {**recipe(today), "optim.lr": 1e-4}
