"""Named recipes: each is the measured command it names, and ``dust-rl train`` picks one by the dataset."""

from __future__ import annotations

import json
import pathlib
import re
import shlex
import shutil
from dataclasses import replace

import pytest
import torch
import tyro
from test_train import TINY_ARGS, tiny_config, trained_weights

from dust_rl.agents import PolicyConfig, save_image_encoder
from dust_rl.cli import main, with_preset
from dust_rl.quickstart import QuickstartConfig
from dust_rl.storage.config_json import config_json
from dust_rl.train.imitation import TrainConfig, train
from dust_rl.train.recipes import RECIPES, default_recipe, plain, scaled_to_steps, vision_readout
from dust_rl.train.settings import (
    GROUPED_SETTINGS,
    DataSettings,
    NestedTrainSettings,
    OptimSettings,
    ReadoutSettings,
    TrainSettings,
    as_class,
)

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
    ``--no-readout-demos``) becomes its group's (``--optim.lr``, ``--readout.no-demos``), and ``--policy.*``
    ``--model.*``."""
    flag, equals, value = arg.partition("=")
    if flag.startswith("--policy."):  # the policy group's flags of before --model.*
        return f"--model.{flag.removeprefix('--policy.')}{equals}{value}"
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
    log = pathlib.Path("docs/franka_results.md").read_text()
    base = re.search(r"--out\s+runs/train/pp2000_ao_start75_20k (.*?)`", log, re.S).group(1)
    assert settings_of(base) == trains(RECIPES["action-only"].settings())
    row3 = re.search(r"`STEPS=20000 bash scripts/recipe.sh pick_place 200 pp200_tokro_g16_h4_f32k_w16k_20k\s(.*?)`",
                     log, re.S).group(1)
    assert settings_of(f"{base} {row3}") == trains(RECIPES["pick-place-readout"].settings())
    # the script and the README name them rather than restate their flags
    assert "--recipe action-only" in pathlib.Path("scripts/recipe.sh").read_text()
    readme = pathlib.Path("README.md").read_text()
    assert "pp200_tokro_g16_h4_f32k_w16k_20k --recipe pick-place-readout\n" in readme
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
    assert vision_readout() == quickstart and QuickstartConfig().train == as_class(NestedTrainSettings, quickstart)
    assert RECIPES["defaults"].settings() == TrainSettings()


def test_flags_override_the_recipe_and_quickstart_takes_one(capsys):
    args, default = with_preset("train", ["--recipe", "vision-readout", "--dataset", "d", "--readout.aux-frames", "16",
                                          "--model.readout-heads", "2"])
    config = tyro.cli(TrainConfig, args=args, default=default)
    assert (config.recipe, config.readout.aux_frames, config.readout.warmup_steps, config.policy.readout_heads,
            config.policy.readout) == ("vision-readout", 16, 4000, 2, "tokens")
    args, default = with_preset("quickstart", ["--recipe", "plain", "--train.optim.steps", "5"])
    config = tyro.cli(QuickstartConfig, args=args, default=default)
    assert config.recipe == "plain" and config.train == as_class(
        NestedTrainSettings, replace(plain(), optim=replace(plain().optim, steps=5)))
    assert capsys.readouterr().out == ""  # a recipe given is not announced


def test_train_without_a_recipe_picks_one_by_the_dataset(demo_dir, tiny_encoder, tmp_path, capsys):
    dataset = shutil.copytree(demo_dir, tmp_path / "data")
    encoder = save_image_encoder(tiny_encoder, tmp_path / "encoder.pt")
    out = tmp_path / "run"
    tiny = [a for a in TINY_ARGS if not a.startswith("--recipe")]
    main(["train", "--dataset", str(dataset), "--out", str(out), "--optim.steps", "2",
          "--model.image-encoder", str(encoder),
          "--model.cond-grid", "4", "4", "--model.readout-grid", "4", "4", "--readout.aux-frames", "8",
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
    name, why = default_recipe(dataset)
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
          "--logging.checkpoint-every", "2", "--logging.log-every", "3", "--model.image-encoder", str(encoder),
          "--runtime.threads", "1", "--runtime.no-progress",
          *[a for a in TINY_ARGS if not a.startswith("--recipe")]])
    assert f"recipe defaults: the one {out} started with" in capsys.readouterr().out
    assert (out / "policy.pt").is_file()
    saved["config"]["recipe"] = "fastest"
    (out / "config.json").write_text(json.dumps(saved))
    with pytest.raises(SystemExit, match="trained with recipe 'fastest', which this version does not have"):
        main(["train", "--dataset", str(dataset), "--out", str(out), "--resume"])


def parsed(args: list[str]) -> TrainConfig:
    """What ``dust-rl train ARGS`` trains with, parsed as the command parses it."""
    args, default = with_preset("train", args)
    return tyro.cli(TrainConfig, args=args, default=default)


def test_fewer_steps_than_the_recipes_scale_its_readout_down(run_inputs, tmp_path, capsys):
    for recipe in RECIPES.values():  # at its own step count and above, every recipe is as measured
        own = recipe.settings()
        assert scaled_to_steps(own, own.optim.steps) == own == scaled_to_steps(own, 2 * own.optim.steps)
    readout = parsed(["--dataset", "d", "--recipe", "vision-readout", "--optim.steps", "20"]).readout
    assert (readout.aux_frames, readout.warmup_steps) == (80, 40)  # 8,000 and 4,000 at 2,000 steps
    readout = parsed(["--dataset", "d", "--recipe", "pick-place-readout", "--optim.steps=1"]).readout
    assert (readout.aux_frames, readout.warmup_steps) == (1, 1)  # 32,000 and 16,000 at 20,000: at least one each
    given = parsed(["--dataset", "d", "--recipe", "vision-readout", "--optim.steps", "20", "--readout.aux-frames",
                    "8000"]).readout
    assert (given.aux_frames, given.warmup_steps) == (8000, 40)  # a value given is kept
    assert capsys.readouterr().out == ""
    # The run says what its read-out will do before it renders a frame, with no progress bar too.
    dataset, encoder = run_inputs
    out = tmp_path / "run"
    main(["train", "--dataset", str(dataset), "--out", str(out), "--optim.steps", "2", "--runtime.threads", "1",
          "--runtime.no-progress", "--model.image-encoder", str(encoder), "--model.cond-grid", "4", "4",
          "--model.readout-grid", "4", "4", *[a for a in TINY_ARGS if not a.startswith("--recipe")]])
    printed = capsys.readouterr().out.splitlines()
    assert printed[0].startswith("recipe vision-readout: ")
    assert printed[1] == ("read-out: 8 aux frames and 8 held out (rendered once per dataset), 4 warm-up steps, then "
                          "the 2 training steps (--readout.aux-frames and --readout.warmup-steps set them)")
    stored = json.loads((out / "config.json").read_text())["config"]
    assert (stored["readout"]["aux_frames"], stored["readout"]["warmup_steps"]) == (8, 4)
    # A run stopped before its first checkpoint (in its warm-up, say) is told apart from one with checkpoints.
    stopped = tmp_path / "stopped"
    stopped.mkdir()
    shutil.copy(out / "config.json", stopped)
    with pytest.raises(SystemExit, match=f"{stopped} holds a run stopped before its first checkpoint; pass --resume "
                       "to start it again with its own settings, delete the folder to start another there"):
        main(["train", "--dataset", str(dataset), "--out", str(stopped), "--recipe", "plain"])


def test_resume_restores_the_runs_own_settings_and_refuses_a_flag_against_them(run_inputs, tmp_path, capsys):
    dataset, encoder = run_inputs
    out = tmp_path / "run"
    main(["train", "--dataset", str(dataset), "--out", str(out), "--optim.steps", "6", "--optim.lr", "3e-3",
          "--data.start-rows", "2", "--seed", "3", "--logging.checkpoint-every", "3", "--logging.log-every", "3",
          "--model.image-encoder", str(encoder), "--runtime.threads", "1", "--runtime.no-progress", *TINY_ARGS])
    uninterrupted = trained_weights(out / "policy.pt")
    shutil.rmtree(sorted((out / "checkpoints").glob("checkpoint-*"))[-1])  # as a run stopped at step 3 leaves it
    (out / "policy.pt").unlink()
    capsys.readouterr()
    main(["train", "--out", str(out), "--resume"])  # its dataset, recipe and flags are the run's own
    assert f"recipe defaults: the one {out} started with, resumed with the settings it saved" in capsys.readouterr().out
    resumed = trained_weights(out / "policy.pt")
    assert all(torch.equal(uninterrupted[k], resumed[k]) for k in uninterrupted)
    logged = (out / "logs" / "train" / "scalars" / "train" / "loss.csv").read_text().split()
    assert [int(row.split(",")[0]) for row in logged] == [3, 6, 6]  # continued from step 3
    # A flag may repeat the run's value or change one a run may change between sittings; one against it is refused.
    main(["train", "--dataset", str(dataset), "--out", str(out), "--resume", "--optim.lr", "0.003",
          "--logging.eval-episodes", "3"])
    for args, message in [
        (["--optim.lr", "1e-3"], f"dust-rl: error: {out} was started with other settings (optim.lr): --optim.lr 0.001 "
         "given, the run's is 0.003; resume without those flags (or with the run's values) or use a new --out"),
        (["--optim.steps", "9", "--model.text-fusion"], "(policy.text_fusion, optim.steps): --model.text-fusion "
         "given, the run's is False; --optim.steps 9 given, the run's is 6;"),
        (["--recipe", "plain"], f"dust-rl: error: --recipe plain: {out} was started with recipe defaults, whose saved "
         "settings --resume restores; drop --recipe, or start a new run with another --out")]:
        with pytest.raises(SystemExit) as refused:
            main(["train", "--out", str(out), "--resume", *args])
        assert message in str(refused.value) and "\n" not in str(refused.value)


@pytest.fixture
def run_inputs(demo_dir, tiny_encoder, tmp_path):
    dataset = shutil.copytree(demo_dir, tmp_path / "data")
    return dataset, save_image_encoder(tiny_encoder, tmp_path / "encoder.pt")
