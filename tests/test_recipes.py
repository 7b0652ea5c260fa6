"""Named recipes: each is the measured command it names, and ``dust-rl train`` picks one by the dataset."""

from __future__ import annotations

import json
import pathlib
import re
import shlex
import shutil
from dataclasses import replace

import pytest
import tyro
from test_train import TINY_ARGS, tiny_config

from dust_rl.agents import PolicyConfig, save_image_encoder
from dust_rl.cli import main, with_preset
from dust_rl.quickstart import QuickstartConfig
from dust_rl.storage.config_json import config_json
from dust_rl.train.imitation import TrainConfig, train
from dust_rl.train.recipes import RECIPES, default_recipe, plain, vision_readout
from dust_rl.train.settings import GROUPED_SETTINGS, DataSettings, OptimSettings, ReadoutSettings, TrainSettings

pytestmark = pytest.mark.usefixtures("one_thread")
# How a command ran, not what it trains.
RUN_ONLY = ("dataset", "out", "resume", "recipe", "cache_dir")
RUN_ONLY_RUNTIME = ("threads", "progress")


def trains(settings: object) -> dict:
    """What ``settings`` (TrainSettings or TrainConfig) train, as JSON values."""
    values = {k: v for k, v in config_json(settings).items() if k not in RUN_ONLY}
    values["runtime"] = {k: v for k, v in values["runtime"].items() if k not in RUN_ONLY_RUNTIME}
    return values


def todays_flag(arg: str) -> str:
    """``arg`` of a train command line as today's: a setting's top-level flag of before the groups (``--lr``,
    ``--no-readout-demos``) becomes its group's (``--optim.lr``, ``--readout.no-demos``)."""
    flag, equals, value = arg.partition("=")
    negated = flag.startswith("--no-")
    name = GROUPED_SETTINGS.get(flag.removeprefix("--no-" if negated else "--").replace("-", "_"))
    if not flag.startswith("--") or name is None:
        return arg
    group, _, setting = name.partition(".")
    return f"--{group}.{'no-' if negated else ''}{setting}".replace("_", "-") + equals + value


def settings_of(command: str) -> dict:
    """What a documented ``dust-rl train`` command trains, in the command line of its date (one without ``--recipe``
    predates them: from every setting's own default; one with top-level flags predates the groups)."""
    args, default = with_preset("train", ["--recipe=defaults", "--dataset", "d",
                                          *map(todays_flag, shlex.split(command.replace("\\\n", " ")))])
    return trains(tyro.cli(TrainConfig, args=args, default=default))


def test_each_recipe_is_the_command_its_result_was_measured_with():
    script = pathlib.Path("scripts/recipe.sh").read_text()
    base = re.search(r"dust-rl train (.*?)\"\$\{resume", script, re.S).group(1).replace('"$steps"', "20000")
    readme = pathlib.Path("README.md").read_text()
    row3 = re.search(r"# 3 .*?pp200_tokro_g16_h4_f32k_w16k_20k (.*?)\n(?:STEPS|#)", readme, re.S).group(1)
    assert settings_of(f"{base} {row3}") == trains(RECIPES["pick-place-readout"].settings())
    diagnosis = pathlib.Path("docs/results/2026-11-28-world-model-diagnosis.md").read_text()
    plain_command = re.search(r"--out runs/train/pb_dust_plain (.*?)\n\S", diagnosis, re.S).group(1)
    assert settings_of(plain_command) == trains(plain())
    # The quickstart's recipe, as it was measured (README row 10): its numbers stay.
    quickstart = TrainSettings(policy=PolicyConfig(image_encoder="efficientnet-lite0-s8", cond_grid=(8, 8),
                                                   text_fusion=True, readout="tokens", readout_grid=(16, 16),
                                                   lambda_aux=1.0, aux_state_input=True),
                               optim=OptimSettings(steps=2000, lr=3e-4),
                               data=DataSettings(start_rows=4, start_fraction=0.75),
                               readout=ReadoutSettings(aux_frames=8000, warmup_steps=4000, demos=False))
    assert vision_readout() == quickstart == QuickstartConfig().train
    assert RECIPES["defaults"].settings() == TrainSettings()


def test_flags_override_the_recipe_and_quickstart_takes_one(capsys):
    args, default = with_preset("train", ["--recipe", "vision-readout", "--dataset", "d", "--readout.aux-frames", "16",
                                          "--policy.readout-heads", "2"])
    config = tyro.cli(TrainConfig, args=args, default=default)
    assert (config.recipe, config.readout.aux_frames, config.readout.warmup_steps, config.policy.readout_heads,
            config.policy.readout) == ("vision-readout", 16, 4000, 2, "tokens")
    args, default = with_preset("quickstart", ["--recipe", "plain", "--train.optim.steps", "5"])
    config = tyro.cli(QuickstartConfig, args=args, default=default)
    assert config.recipe == "plain" and config.train == replace(plain(), optim=replace(plain().optim, steps=5))
    assert capsys.readouterr().out == ""  # a recipe given is not announced


def test_train_without_a_recipe_picks_one_by_the_dataset(demo_dir, tiny_encoder, tmp_path, capsys):
    dataset = shutil.copytree(demo_dir, tmp_path / "data")
    encoder = save_image_encoder(tiny_encoder, tmp_path / "encoder.pt")
    out = tmp_path / "run"
    tiny = [a for a in TINY_ARGS if not a.startswith("--recipe")]
    main(["train", "--dataset", str(dataset), "--out", str(out), "--optim.steps", "2",
          "--policy.image-encoder", str(encoder),
          "--policy.cond-grid", "4", "4", "--policy.readout-grid", "4", "4", "--readout.aux-frames", "8",
          "--readout.warmup-steps", "2", "--runtime.threads", "1", "--runtime.no-progress", *tiny])
    printed = capsys.readouterr().out
    assert "recipe vision-readout: " in printed and "--recipe plain trains without it" in printed
    stored = json.loads((out / "config.json").read_text())["config"]
    assert stored["recipe"] == "vision-readout"
    assert (stored["policy"]["readout"], stored["policy"]["text_fusion"], stored["readout"]["demos"]) == (
        "tokens", True, False)
    # A dataset without the object state gets the plain recipe.
    meta = json.loads((dataset / "meta.json").read_text())
    del meta["stats"]["observation.environment_state"]
    (dataset / "meta.json").write_text(json.dumps(meta))
    name, why = default_recipe(dataset, tmp_path / "new", resume=False)
    assert name == "plain" and "records no observation.environment_state" in why


def test_resume_keeps_the_recipe_the_run_started_with(run_inputs, tmp_path, capsys):
    out = tmp_path / "run"
    train(tiny_config(run_inputs, out, steps=4, checkpoint_every=2))
    saved = json.loads((out / "config.json").read_text())
    del saved["config"]["recipe"]  # a run from before recipes
    (out / "config.json").write_text(json.dumps(saved))
    (out / "policy.pt").unlink()
    dataset, encoder = run_inputs
    main(["train", "--dataset", str(dataset), "--out", str(out), "--resume", "--optim.steps", "4",
          "--logging.checkpoint-every", "2", "--logging.log-every", "3", "--policy.image-encoder", str(encoder),
          "--runtime.threads", "1", "--runtime.no-progress",
          *[a for a in TINY_ARGS if not a.startswith("--recipe")]])
    assert f"recipe defaults: the one {out} started with" in capsys.readouterr().out
    assert (out / "policy.pt").is_file()
    saved["config"]["recipe"] = "fastest"
    (out / "config.json").write_text(json.dumps(saved))
    with pytest.raises(SystemExit, match="trained with recipe 'fastest', which this version does not have"):
        main(["train", "--dataset", str(dataset), "--out", str(out), "--resume"])


@pytest.fixture
def run_inputs(demo_dir, tiny_encoder, tmp_path):
    dataset = shutil.copytree(demo_dir, tmp_path / "data")
    return dataset, save_image_encoder(tiny_encoder, tmp_path / "encoder.pt")
