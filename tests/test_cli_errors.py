"""The ``dust-rl`` command on bad input: one-line errors, nothing lost on disk, settings that take effect."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
import time

import pytest
import torch
import tyro
from tensordict import TensorDict
from test_evaluate import tiny_policy_file
from test_train import TINY_ARGS

from dust_rl.agents import load_policy, save_image_encoder, save_policy
from dust_rl.cli import main
from dust_rl.data import DemoDataset
from dust_rl.data.layout import STAGING_DIR
from dust_rl.envs import list_tasks
from dust_rl.envs.factory import env_tasks
from dust_rl.errors import ConfigError
from dust_rl.storage.lock import folder_lock

pytestmark = pytest.mark.usefixtures("one_thread")


def error_of(args: list[str]) -> str:
    """The message ``dust-rl`` exits with; it must be one ``dust-rl: error:`` line."""
    with pytest.raises(SystemExit) as exit_info:
        main(args)
    message = str(exit_info.value.code)
    assert message.startswith("dust-rl: error: ") and "\n" not in message, message
    return message


def collect_args(out, episodes: int = 3, task: str = "press_button,open_drawer") -> list[str]:
    """``dust-rl collect`` with the settings of the conftest ``demo_dir`` (so a copy of it resumes)."""
    return ["collect", "--task", task, "--episodes", str(episodes), "--image-size", "32", "--out", str(out)]


@pytest.fixture
def dataset_copy(demo_dir, tmp_path):
    return shutil.copytree(demo_dir, tmp_path / "ds")


def test_smaller_episode_count_keeps_every_episode(dataset_copy, capsys):
    before = DemoDataset(dataset_copy).meta["episodes"]
    episode_dirs = sorted(p.relative_to(dataset_copy) for p in (dataset_copy / "episodes").rglob("*"))
    for _ in range(2):  # the second run used to fail on the episodes the first one deleted
        main(collect_args(dataset_copy, episodes=1))
        printed = capsys.readouterr().out
        assert "press_button already holds 3 episodes, more than the 1 asked; keeping them all" in printed
        dataset = DemoDataset(dataset_copy)
        assert dataset.meta["episodes"] == before and dataset.meta["episodes_per_task"] == {
            "press_button": 3, "open_drawer": 3}
        assert sorted(p.relative_to(dataset_copy) for p in (dataset_copy / "episodes").rglob("*")) == episode_dirs
        assert len(dataset.episode(5)) == before[5]["length"]  # the rows are all still there


@pytest.mark.parametrize("progress", ["--runtime.progress", "--runtime.no-progress"])
def test_collection_progress_bars_can_be_turned_off(progress, dataset_copy, capsys):
    main([*collect_args(dataset_copy, episodes=4, task="press_button"), progress])  # one more episode
    assert DemoDataset(dataset_copy).meta["episodes_per_task"]["press_button"] == 4
    assert ("collecting press_button" in capsys.readouterr().err) == (progress == "--runtime.progress")


def test_bad_task_list_writes_nothing(dataset_copy, tmp_path):
    meta = (dataset_copy / "meta.json").read_bytes()
    assert "unknown franka task 'nope'" in error_of(collect_args(dataset_copy, task="press_button,nope"))
    assert (dataset_copy / "meta.json").read_bytes() == meta
    main(collect_args(dataset_copy))  # later collects into the folder still work
    new = tmp_path / "new"
    for args in (collect_args(new, task="nope"), collect_args(new, episodes=0),
                 [*collect_args(new), "--cameras", "front", "nope"], ["collect", "--env", "Nope-v0", "--out", str(new)],
                 ["collect", "--task", "all", "--env", "Nope-v0", "--out", str(new)]):
        error_of(args)
    assert not new.exists()


def hold_lock(folder) -> subprocess.Popen:
    """A process that holds ``folder``'s dataset lock until a line arrives on its stdin."""
    script = ("import pathlib, sys, time; from dust_rl.storage.lock import folder_lock; "
              f"lock = folder_lock(pathlib.Path({str(folder)!r})); lock.__enter__(); "
              "print('locked', flush=True); sys.stdin.readline(); lock.__exit__(None, None, None); time.sleep(120)")
    holder = subprocess.Popen([sys.executable, "-c", script], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline() == "locked\n"
    return holder


def test_a_second_collector_is_refused_and_told_who_holds_the_folder(dataset_copy):
    holder = hold_lock(dataset_copy)
    try:
        message = error_of(collect_args(dataset_copy))
        assert f"is being written by another process (pid {holder.pid} on " in message and "folder_lock" in message
    finally:
        holder.kill()
        holder.wait()
    main(collect_args(dataset_copy))  # the kernel released the lock of the killed process


def test_a_lock_file_that_is_a_symlink_is_refused_and_its_target_kept(dataset_copy, tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    lock = dataset_copy / ".lock"
    lock.unlink(missing_ok=True)
    os.symlink(victim, lock)
    message = error_of(collect_args(dataset_copy))
    assert f"{lock}: cannot open the lock file" in message and "symlink" in message
    assert victim.read_text() == "precious\n"
    os.symlink(tmp_path / "no-such-file", tmp_path / "dangling")  # nor is a file created through a dangling link
    os.replace(tmp_path / "dangling", lock)
    error_of(collect_args(dataset_copy))
    assert not (tmp_path / "no-such-file").exists()


def test_a_lock_file_that_is_a_hard_link_is_refused_and_its_target_kept(dataset_copy):
    """A hard link survives ``tar``: a shipped dataset whose ``.lock`` names ``meta.json`` must not lose it."""
    meta, lock = dataset_copy / "meta.json", dataset_copy / ".lock"
    before = meta.read_bytes()
    lock.unlink(missing_ok=True)
    os.link(meta, lock)
    message = error_of(collect_args(dataset_copy))
    assert f"{lock}: the lock file is a hard link" in message
    assert meta.read_bytes() == before
    lock.unlink()
    main(collect_args(dataset_copy))  # the dataset is intact and collects again once the link is gone
    assert lock.read_bytes() == b""  # a copy of the folder names no stale holder


def test_a_waiting_writer_takes_the_lock_when_the_holder_lets_go(tmp_path, capsys):
    holder, acquired = hold_lock(tmp_path), threading.Event()

    def take_lock() -> None:
        with folder_lock(tmp_path, wait=True):
            acquired.set()

    waiter = threading.Thread(target=take_lock)
    try:
        waiter.start()
        said = ""
        for _ in range(600):  # until it says whom it waits for (printed just before it blocks)
            said += capsys.readouterr().err
            if f"(pid {holder.pid} on " in said:
                break
            time.sleep(0.1)
        assert "waiting for it to finish" in said and not acquired.is_set()
        holder.stdin.write("release\n")
        holder.stdin.flush()
        waiter.join(60)
        assert acquired.is_set()
    finally:
        holder.kill()
        holder.wait()


def test_eval_max_steps_above_the_task_default_is_used(tmp_path, minilm):
    torch.manual_seed(0)  # an untrained policy: it never presses the button, so episodes run to the limit
    policy = tiny_policy_file(tmp_path / "policy.pt", minilm)
    out = tmp_path / "eval"
    main(["eval", "--policy", str(policy), "--out", str(out), "--episodes", "1", "--workers", "1",
          "--max-steps", "103", "--execute-steps", "3", "--videos", "0", "--runtime.no-progress"])  # default limit: 100
    report = json.loads((out / "report.json").read_text())
    assert report["env_kwargs"]["max_episode_steps"] == 103 and report["execute_steps"] == 3
    episode = report["tasks"][0]["per_episode"][0]
    assert (episode["success"], episode["length"]) == (False, 103)
    assert not list(out.glob(".*.tmp"))  # the report files were moved into place
    for args in (["--episodes", "0"], ["--max-steps", "0"], ["--tasks", "press_button", "fly"],
                 ["--execute-steps", "0"], ["--runtime.device", "tpu"]):
        error_of(["eval", "--policy", str(policy), "--out", str(tmp_path / "bad"), *args])
    horizon = load_policy(policy).config.horizon
    assert "execute_steps must be in [1, " in error_of(["eval", "--policy", str(policy), "--out", str(tmp_path / "bad"),
                                                        "--execute-steps", str(horizon + 1)])
    assert "no such checkpoint file" in error_of(["eval", "--policy", str(tmp_path / "missing.pt")])
    assert not (tmp_path / "bad").exists()


EVAL_ARGS = ["--episodes", "1", "--workers", "1", "--max-steps", "5", "--runtime.no-progress"]


def test_an_eval_folder_holds_one_evaluation_and_never_a_run(tmp_path, minilm):
    policy, out = tiny_policy_file(tmp_path / "run" / "policy.pt", minilm), tmp_path / "eval"
    out.mkdir()
    holder = hold_lock(out)
    try:  # a second evaluation into a folder another one writes is refused, naming the holder
        assert f"is being written by another process (pid {holder.pid} on " in error_of(
            ["eval", "--policy", str(policy), "--out", str(out), *EVAL_ARGS])
    finally:
        holder.kill()
        holder.wait()
    (out / "videos").mkdir()
    (out / "videos" / "open_drawer_seed10007.mp4").write_bytes(b"an earlier evaluation's")
    main(["eval", "--policy", str(policy), "--out", str(out), *EVAL_ARGS, "--videos", "1"])
    assert [p.name for p in (out / "videos").iterdir()] == ["press_button_seed10000.mp4"]  # no other policy's
    run = tmp_path / "run"
    (run / "config.json").write_text("{}")
    (run / "loss.png").write_bytes(b"the run's")
    assert "holds a training run or a policy (config.json)" in error_of(
        ["eval", "--policy", str(policy), "--out", str(run), *EVAL_ARGS])
    assert (run / "loss.png").read_bytes() == b"the run's"
    assert "close_drawer given more than once" in error_of(
        ["eval", "--policy", str(policy), "--out", str(out), *EVAL_ARGS, "--tasks", "close_drawer", "close_drawer"])


@pytest.mark.parametrize("spelling", [["--out", ""], ["--out="]])
def test_an_empty_out_is_refused_rather_than_the_current_folder(spelling, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert "--out is given an empty value" in error_of(["collect", "--task", "close_drawer", "--episodes", "1",
                                                         "--image-size", "32", *spelling])
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("args,old,new", [
    (["eval", "--policy", "X", "--threads", "1"], "--threads", "--runtime.threads"),
    (["collect", "--task", "press_button", "--episodes", "1", "--no-progress"], "--no-progress",
     "--runtime.no-progress"),
    (["finetune", "steer", "--policy", "X", "--device=cpu"], "--device", "--runtime.device"),
    (["diagnose", "world-model", "--policy", "X", "--dataset", "d", "--precision", "bf16"], "--precision",
     "--runtime.precision"),
    (["bench", "train-speed", "--compile"], "--compile", "--runtime.compile"),
    (["quickstart", "--progress"], "--progress", "--runtime.progress"),
])
def test_a_runtime_flag_of_earlier_versions_ends_in_one_line_naming_todays(args, old, new, tmp_path, monkeypatch):
    """Every command's runtime settings are one group (`--runtime.*`): an earlier spelling is refused, naming
    today's, before anything runs (no policy read, no folder made)."""
    monkeypatch.chdir(tmp_path)
    message = error_of([*args, "--out", str(tmp_path / "out")])
    assert f"{old} is spelled {new}: every command's runtime settings are one group" in message
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(("args", "new"), [(["train", "--dataset", "d", "--policy.d-model", "64"], "--model.d-model"),
                                           (["quickstart", "--train.policy.variant=joint"], "--train.model.variant"),
                                           (["bench", "suite", "--train.policy.lambda-wm", "0"],
                                            "--train.model.lambda-wm")])
def test_the_policy_built_is_the_model_group_and_its_earlier_spelling_is_refused(args, new, tmp_path, monkeypatch):
    """`--policy PATH` is always a policy file; the policy a command builds is `--model.*`, and a setting spelled as
    the group was before is refused naming today's flag, before anything runs."""
    monkeypatch.chdir(tmp_path)
    message = error_of([*args, "--out", str(tmp_path / "out")])
    assert f"is spelled {new}: the policy a command builds is the group --model.*" in message
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("args", [["pretrain-encoder", "--dataset", "d", "--runtime.precision", "bf16"],
                                  ["bench", "gpu", "--runtime.compile"]])
def test_a_command_that_runs_at_fp32_refuses_another_precision_or_compilation(args, tmp_path):
    """Its runtime group is every command's, but it cannot honour these two: refused, not ignored."""
    message = error_of([*args, "--out", str(tmp_path / "out")])
    assert "runs at fp32, uncompiled: drop --runtime." in message and not (tmp_path / "out").exists()


@pytest.mark.parametrize("command", [["quickstart"], ["bench", "suite"], ["finetune", "self-imitation"]])
def test_a_nested_training_runs_under_the_commands_own_runtime(command):
    """quickstart, bench suite and self-imitation's rounds train under the command's --runtime.*: the training's
    own group is not offered."""
    assert "--train.runtime.threads is spelled --runtime.threads: the command's training runs under its own " \
        "--runtime.*" in error_of([*command, "--train.runtime.threads", "1"])


def test_pretrain_encoder_does_not_overwrite_a_policy(demo_dir, tmp_path, minilm):
    policy = tiny_policy_file(tmp_path / "policy.pt", minilm)
    before = policy.read_bytes()
    assert "is not a 'dust-rl-image-encoder' checkpoint file" in error_of(
        ["pretrain-encoder", "--dataset", str(demo_dir), "--out", str(policy), "--steps", "2", "--batch-size", "4",
         "--image-size", "32", "--width", "8", "--dim", "16", "--runtime.device", "cpu"])
    assert policy.read_bytes() == before


@pytest.mark.parametrize("workers", ["1", "2"])  # a worker process's error comes back with its traceback appended
def test_a_policy_that_acts_nan_ends_eval_in_one_line_naming_it(workers, tmp_path, minilm):
    """Statistics near zero pass the load checks (they are > 0) and overflow into NaN actions, which the env would
    refuse with a traceback from inside the collector."""
    policy = load_policy(tiny_policy_file(tmp_path / "policy.pt", minilm))
    policy.normalizer.state_std.fill_(1e-30)
    path = save_policy(policy, tmp_path / "overflows.pt")
    message = error_of(["eval", "--policy", str(path), "--out", str(tmp_path / "eval"), "--episodes", "1",
                        "--workers", workers, "--max-steps", "5", "--videos", "0", "--runtime.no-progress"])
    assert f"{path}: the policy's action holds NaN or infinity (at episode seed " in message
    assert not list((tmp_path / "eval").glob("report.*"))


@pytest.fixture
def train_args(dataset_copy, tiny_encoder, tmp_path):
    encoder = save_image_encoder(tiny_encoder, tmp_path / "encoder.pt")
    return ["train", "--dataset", str(dataset_copy), "--model.image-encoder", str(encoder), "--runtime.threads", "1",
            "--runtime.no-progress", "--logging.log-every", "1", "--logging.checkpoint-every", "1", *TINY_ARGS]


def test_train_refuses_bad_settings_before_writing(train_args, tmp_path, capsys):
    out = tmp_path / "run"
    for flags, field in ((["--optim.lr", "inf"], "lr"), (["--optim.grad-clip", "nan"], "grad_clip"),
                         (["--optim.lr", "0"], "lr"),
                         (["--optim.steps", "0"], "steps"), (["--optim.batch-size", "0"], "batch_size"),
                         (["--optim.warmup", "1"], "warmup"), (["--runtime.device", "tpu"], "device"),
                         (["--data.start-fraction", "1"], "start_fraction"),
                         (["--optim.batch-size", "7", "--runtime.nproc", "2"], "split evenly")):
        assert field in error_of([*train_args, "--out", str(out), *flags])
    # The nested policy settings are checked while tyro parses: a usage error (exit 2) naming the group and rule.
    for flags, reason in ((["--model.execute-steps", "9"], "execute_steps must be in [1, horizon=4], got 9"),
                          (["--model.n-heads", "3"], "d_model must be divisible by n_heads")):
        with pytest.raises(SystemExit) as exit_info:
            main([*train_args, "--out", str(out), *flags])
        stderr = " ".join(capsys.readouterr().err.split())
        assert exit_info.value.code == 2 and "Error parsing policy:" in stderr and reason in stderr, stderr
    assert "not a dust-rl dataset" in error_of(["train", "--dataset", str(tmp_path / "none"), "--out", str(out)])
    assert not out.exists()


def test_diverging_training_stops_at_the_first_non_finite_loss(train_args, tmp_path):
    out = tmp_path / "run"
    message = error_of([*train_args, "--out", str(out), "--optim.steps", "6", "--optim.lr", "1e30"])
    step = int(message.split("diverged at step ")[1].split(":")[0])
    assert not (out / "policy.pt").exists()
    checkpoints = sorted((out / "checkpoints").iterdir())
    assert [int(p.name.split("-")[1]) for p in checkpoints] == list(range(max(1, step - 2), step))
    for checkpoint in checkpoints:  # the weights and their average that were saved are finite
        for component in ("model", "ema"):
            (state,) = checkpoint.glob(f"components/*-{component}/state")
            tensors = TensorDict.load_memmap(state).values(include_nested=True, leaves_only=True)
            assert all(torch.isfinite(t).all() for t in tensors if t.is_floating_point()), checkpoint


def test_collect_privileged_state_reaches_the_env_and_the_dataset(tmp_path):
    out = tmp_path / "oracle"
    main([*collect_args(out, episodes=1, task="pick_place"), "--privileged-state"])
    dataset = DemoDataset(out)
    assert dataset.meta["env_kwargs"]["privileged_state"] is True
    rows = dataset.episode(0)
    objects = rows.get(("observation", "environment_state"))
    torch.testing.assert_close(rows.get(("observation", "state"))[:, -objects.shape[-1]:], objects, rtol=0, atol=0)


def test_task_all_is_the_suite_of_the_env_ids_robot():
    assert env_tasks("DustHumanoid-v0", "all") == list_tasks("humanoid") != list_tasks("franka")
    assert env_tasks("DustFranka-v0", "press_button, open_drawer") == ["press_button", "open_drawer"]
    with pytest.raises(ConfigError, match="unknown humanoid task 'press_button'"):
        env_tasks("DustHumanoid-v0", "press_button")


def test_preset_sets_the_policy_size_over_the_recipe_and_flags_override_both(train_args, tmp_path):
    from dust_rl.agents.config import POLICY_PRESETS
    from dust_rl.cli import with_preset
    from dust_rl.train.imitation import TrainConfig

    args, default = with_preset("train", ["--dataset", "d", "--preset", "gpu-base", "--model.n-dit", "2",
                                          "--recipe=plain"])
    assert args == ["--dataset", "d", "--model.n-dit", "2"]
    config = tyro.cli(TrainConfig, args=args, default=default)
    gpu = POLICY_PRESETS["gpu-base"]
    assert (config.policy.d_model, config.policy.n_mmdit, config.policy.n_dit) == (gpu.d_model, gpu.n_mmdit, 2)
    assert (config.recipe, config.policy.image_encoder, config.optim.steps) == ("plain", "efficientnet-lite0-s8", 2000)
    assert with_preset("train", ["--help"]) == (["--help"], None)  # --help shows every setting's own default
    assert "one of ['cpu-small', 'gpu-base'], got huge" in error_of([*train_args, "--out", str(tmp_path / "r"),
                                                                        "--preset", "huge"])
    assert ("--recipe takes one of ['action-only', 'defaults', 'pick-place-readout', 'plain', 'vision-readout'], "
            "got fast") in error_of([*train_args, "--out", str(tmp_path / "r"), "--recipe", "fast"])
    assert "--preset applies to dust-rl train, not dust-rl quickstart" in error_of(["quickstart", "--preset",
                                                                                  "gpu-base"])
    for flag in ("--preset", "--recipe=plain"):
        assert "applies to dust-rl train, quickstart and bench suite" in error_of(["eval", "--policy", "p.pt", flag,
                                                                                  "gpu-base"])
    assert not (tmp_path / "r").exists()


def _corrupt_studies(tmp_path, demo_dir) -> list[str]:
    for name, text in (("a", '{"env": "DustFranka-v0", '), ("b", "{}")):
        (tmp_path / name).mkdir()
        (tmp_path / name / "results.json").write_text(text)
    return ["bench", "average", "--studies", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(tmp_path / "avg")]


def _no_spec(tmp_path, demo_dir) -> list[str]:
    dataset = shutil.copytree(demo_dir, tmp_path / "ds")
    meta = json.loads((dataset / "meta.json").read_text())
    del meta["spec"]
    (dataset / "meta.json").write_text(json.dumps(meta))
    return ["dataset", "info", str(dataset)]


def _run_config(text: str):
    """A run folder whose ``config.json`` is ``text``, resumed."""
    def make(tmp_path, demo_dir) -> list[str]:
        (tmp_path / "run").mkdir()
        (tmp_path / "run" / "config.json").write_text(text)
        return ["train", "--dataset", str(demo_dir), "--out", str(tmp_path / "run"), "--resume"]
    return make


def _fifo_policy(tmp_path, demo_dir) -> list[str]:
    os.mkfifo(tmp_path / "policy.pt")  # opening it would wait for a writer forever
    return ["eval", "--policy", str(tmp_path / "policy.pt"), "--out", str(tmp_path / "eval")]


def _odd_size_export(tmp_path, demo_dir) -> list[str]:
    main(["collect", "--task", "press_button", "--episodes", "1", "--image-size", "31", "--out", str(tmp_path / "ds"),
          "--runtime.no-progress"])
    return ["dataset", "export", str(tmp_path / "ds"), "--out", str(tmp_path / "lerobot")]


BAD_INPUT = {
    "run-config-not-settings": (_run_config('{"config": 5}'),
                                "run/config.json: unreadable run config (TypeError(\"'config' is 5, not an object"),
    "run-config-too-deep": (_run_config("[" * 200_000 + "]" * 200_000), "unreadable run config (RecursionError("),
    "policy-fifo": (_fifo_policy, "policy.pt: not a regular file (a FIFO, device or socket)"),
    "eval-seed-overflow": (lambda tmp, demos: ["eval", "--policy", str(tmp / "p.pt"), "--seed", str(2**63 - 1),
                                               "--episodes", "1", "--workers", "1"],
                           f"--seed {2**63 - 1}: the 2 episode seeds from it must fit in [0, {2**63 - 1}] (an "
                           f"episode's seed is stored as an int64); give --seed in [0, {2**63 - 2}]"),
    "collect-seed-overflow": (lambda tmp, demos: [*collect_args(tmp / "ds", 1, "press_button"), "--seed",
                                                  str(2**64 - 1)],
                              f"--seed {2**64 - 1}: the 14 episode seeds from it must fit in [0, {2**63 - 1}]"),
    "tau-buckets": (lambda tmp, demos: ["diagnose", "world-model", "--policy", str(tmp / "p.pt"), "--dataset",
                                        str(demos), "--tau-buckets", "100000"],
                    "tau_buckets must be at most 50 (each is one more pass over every window), got 100000"),
    "export-odd-size": (_odd_size_export, "ds: its frames are 31x31 px; a LeRobot dataset stores frames as H.264 "
                                          "(yuv420p) video, which needs even sizes"),
    "vision-steps-0": (lambda tmp, demos: ["bench", "suite", "--vision-steps", "0", "--out", str(tmp / "s")],
                       r"vision_steps must be multiples of N_A = 4 in [4, 1024], got (0,)"),
    "vision-steps-5000": (lambda tmp, demos: ["bench", "suite", "--vision-steps", "8", "5000", "--out", str(tmp / "s")],
                          r"vision_steps must be multiples of N_A = 4 in [4, 1024], got (8, 5000)"),
    "corrupt-results": (_corrupt_studies, "results.json: not a readable results file"),
    "video-not-mp4": (lambda tmp, demos: ["dataset", "video", str(demos), "--out", str(tmp / "grid.avi")],
                      "--out must name an .mp4 file"),
    "no-spec": (_no_spec, "meta.json: missing or malformed spec; the file was edited"),
    "nproc-above-cores": (lambda tmp, demos: ["train", "--dataset", str(demos), "--out", str(tmp / "run"),
                                              "--runtime.device", "cpu", "--recipe", "plain",
                                              "--runtime.nproc", str((os.cpu_count() or 1) + 1),
                                              "--optim.batch-size", str((os.cpu_count() or 1) + 1)],
                          f"give --runtime.nproc at most {os.cpu_count() or 1}"),
    "non-utf8-path": (lambda tmp, demos: ["dataset", "info", os.fsdecode(bytes(tmp / "ds") + b"\xff")],
                      "is not UTF-8 text; rename"),
}


@pytest.mark.parametrize("case", BAD_INPUT)
def test_bad_input_ends_in_one_line_naming_it(case, demo_dir, tmp_path):
    make_args, problem = BAD_INPUT[case]
    before = sorted(tmp_path.iterdir())
    args = make_args(tmp_path, demo_dir)
    made = sorted(tmp_path.iterdir())
    assert problem in error_of(args)
    assert sorted(tmp_path.iterdir()) == made and len(made) >= len(before)  # nothing written by the command


def test_a_full_disk_ends_collection_in_one_line_and_a_rerun_resumes(tmp_path, monkeypatch):
    real = shutil.disk_usage
    episodes = []

    def filling_up(path):  # the disk is full once the first episode is written
        episodes.append(path)
        usage = real(path)
        return usage._replace(free=0) if len(episodes) > 1 else usage

    monkeypatch.setattr(shutil, "disk_usage", filling_up)
    out = tmp_path / "ds"
    message = error_of(collect_args(out, episodes=2, task="press_button"))
    assert f"no space left on device while collecting into {out}" in message and "re-run the same command" in message
    assert not (out / STAGING_DIR).exists()  # nothing half written is left
    assert sorted(p.name for p in (out / "episodes" / "press_button").iterdir()) == ["seed-000000"]
    monkeypatch.undo()
    main(collect_args(out, episodes=2, task="press_button"))
    assert DemoDataset(out).meta["episodes_per_task"] == {"press_button": 2}
