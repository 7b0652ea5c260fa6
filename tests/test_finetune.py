"""``dust-rl finetune``: SB3 trains on the steering and residual envs, the base row is the evaluated policy."""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import shutil
import time

import numpy as np
import pytest
import torch
from conftest import as_before_the_groups, kill_after_first_checkpoint
from crafted import CRAFTS
from tensordict import TensorDict
from torchrl.checkpoint import Checkpoint, CheckpointRotation

from dust_rl.agents import AutoencoderConfig, ConvAutoencoder, load_policy, make_policy, save_policy
from dust_rl.data.collect import MAX_SEEDS_PER_EPISODE, SuccessesOutOfReachError
from dust_rl.data.episodes import scan_episodes
from dust_rl.errors import CheckpointError, ConfigError, NoSpaceError
from dust_rl.evaluate.closed_loop import EvalConfig, evaluate
from dust_rl.evaluate.report import loss_csvs
from dust_rl.rl.checkpoint import SB3LearningState
from dust_rl.rl.config import (
    RL_AGENT_FILE,
    LatentSettings,
    PpoSettings,
    ResidualConfig,
    RoundData,
    RoundTraining,
    SacSettings,
    SelfImitationConfig,
    SteerConfig,
    SteeringCollection,
    SteeringObservation,
    as_this_version,
    rl_config_from_json,
)
from dust_rl.rl.critic_limits import LayerNormReLU
from dust_rl.rl.finetune import RL_AGENT_KIND, build_agent, finetune, finetune_env_factory
from dust_rl.rl.self_imitation import ROUND_SECONDS, _add_seconds, control_row
from dust_rl.rl.vector import SB3SteeringVecEnv
from dust_rl.runtime.settings import RuntimeSettings
from dust_rl.storage.checkpoint_files import load_checkpoint, save_checkpoint
from dust_rl.storage.config_json import config_from_json, config_json
from dust_rl.storage.lock import FolderLockedError, folder_lock
from dust_rl.storage.run_folder import RunRNGState, restore
from dust_rl.train.imitation import NonFiniteLossError
from dust_rl.train.settings import LoggingSettings, OptimSettings

pytestmark = pytest.mark.usefixtures("one_thread")

EPISODE_STEPS = 10
QUIET = RuntimeSettings(threads=1, progress=False)
METHODS = {"steer": SteerConfig, "residual": ResidualConfig}

DSRL = {"reward": "penalty", "finite_horizon": True, "noise_bound": 1.5, "latent": LatentSettings(7),
        "observation": SteeringObservation(instruction=False, privileged_critic=True),
        "collection": SteeringCollection(envs=2, base_warmup=True)}
"""DSRL's design at test sizes: a latent of one noise row, an asymmetric critic, -1 per step, 2 envs per plan."""
DSRL_FLAGS = ["--reward", "penalty", "--finite-horizon", "--noise-bound", "1.5", "--latent-dim", "7",
              "--no-instruction", "--privileged-critic", "--envs", "2", "--base-warmup"]


@pytest.fixture(scope="module")
def policy_path(tmp_path_factory, minilm):
    """A tiny untrained policy for 32 px front + wrist cameras, its weights moved off their initialisation."""
    encoder = ConvAutoencoder(AutoencoderConfig(image_size=32, dim=16, width=8, max_width=16))
    policy = make_policy("dust", image_encoder=encoder, text_encoder=minilm, cameras=["front", "wrist"], action_dim=7,
                         state_dim=17, horizon=4, execute_steps=2, d_model=32, n_heads=2, n_mmdit=2, n_dit=0)
    policy.set_action_bounds(-torch.ones(7), torch.ones(7))  # DustFranka-v0's action box, as training sets it
    with torch.no_grad():
        for p in policy.trainable_parameters():
            p.add_(0.1 * torch.randn(p.shape, generator=torch.Generator().manual_seed(0)))
    policy.info = {"env_id": "DustFranka-v0", "env_kwargs": {"image_size": 32}, "tasks": ["press_button"],
                   "image_size": [32, 32]}
    return save_policy(policy, tmp_path_factory.mktemp("policy") / "policy.pt")


@pytest.mark.parametrize("method,algorithm,reward", [("steer", "sac", "sparse"), ("residual", "ppo", "dense")])
def test_finetune_trains_saves_and_compares_with_the_evaluated_policy(method, algorithm, reward, policy_path,
                                                                        tmp_path):
    settings = SacSettings(learning_starts=4) if algorithm == "sac" else PpoSettings()
    config = METHODS[method](policy=policy_path, out=tmp_path / "ft", algorithm=settings, steps=8, reward=reward,
                             batch_size=4, net_arch=(16,), eval_episodes=2, max_steps=EPISODE_STEPS, eval_every=4,
                             curve_episodes=1, runtime=QUIET)
    report = finetune(config, command="dust-rl finetune ...")
    # Steering also runs the base policy at the centre of its noise, where a deterministic steering agent starts.
    assert [row["episodes"] for row in report["rows"]] == [2] * (3 if method == "steer" else 2)
    assert report["task"] == "press_button"
    # A learning curve: the base policy, then a validation point every eval_every RL steps (PPO learns in whole
    # rollouts of 8 here, so one point after the base), env steps counted as executed.
    curve = json.loads((tmp_path / "ft" / "learning_curve.json").read_text())
    assert [p["rl_steps"] for p in curve] == ([0, 4, 8] if algorithm == "sac" else [0, 8])
    assert curve[0]["task"] == "base policy" and curve[0]["env_steps"] == 0 and all(p["episodes"] == 1 for p in curve)
    assert all(a["env_steps"] < b["env_steps"] for a, b in zip(curve, curve[1:]))
    assert curve[1]["env_steps"] >= curve[1]["rl_steps"]
    assert (tmp_path / "ft" / "learning_curve.png").read_bytes()[:4] == b"\x89PNG"
    # The base row is the policy's own evaluation, episode for episode (same seeds, same noise, same actions).
    evaluated = evaluate(EvalConfig(policy=policy_path, out=tmp_path / "eval", episodes=2, workers=1, videos=0,
                                    max_steps=EPISODE_STEPS, seed=config.eval_seed, runtime=QUIET))
    assert report["per_episode"]["base policy"] == evaluated["tasks"][0]["per_episode"]
    agent = load_checkpoint(tmp_path / "ft" / "rl_agent.pt", RL_AGENT_KIND)
    assert agent["config"]["method"] == method and all(torch.isfinite(v).all() for v in agent["state_dict"].values())
    assert rl_config_from_json(agent["config"]) == config  # the saved config rebuilds the run's
    saved = json.loads((tmp_path / "ft" / "config.json").read_text())["config"]
    assert (saved["method"], saved["algorithm"]["name"]) == (method, algorithm)
    assert "| base policy | 2 |" in (tmp_path / "ft" / "report.md").read_text()
    # SB3's scalars go through torchrl's CSV logger, one file per scalar of (step, value) rows.
    scalars = tmp_path / "ft" / "logs" / "finetune" / "scalars"
    fine_tuned = (scalars / "eval" / "success_rate_fine_tuned.csv").read_text().splitlines()
    assert [float(v) for v in fine_tuned[-1].split(",")] == [8, report["rows"][-1]["success_rate"]]
    assert (scalars / "train" / "learning_rate.csv").is_file()
    assert_eval_runs_the_agent(report, tmp_path, config.eval_seed)


def assert_eval_runs_the_agent(report: dict, tmp_path: pathlib.Path, seed: int) -> None:
    """``dust-rl eval`` of the run's ``rl_agent.pt`` alone (no base policy file, no flag on the run's settings)
    replays the report's fine-tuned row, seed for seed, on the run's task and time limit."""
    from dust_rl.cli import main

    policy_dir = pathlib.Path(report["policy"]).parent
    hidden = policy_dir.rename(policy_dir.with_name(policy_dir.name + "_moved"))  # the file must not need the base's
    try:
        main(["eval", "--policy", str(tmp_path / "ft" / "rl_agent.pt"), "--out", str(tmp_path / "eval_agent"),
              "--episodes", "2", "--seed", str(seed), "--videos", "1", "--runtime.no-progress"])
    finally:
        hidden.rename(policy_dir)
    evaluated = json.loads((tmp_path / "eval_agent" / "report.json").read_text())
    fine_tuned = next(name for name in report["per_episode"] if name.startswith("fine-tuned"))
    assert evaluated["tasks"][0]["per_episode"] == report["per_episode"][fine_tuned]
    assert evaluated["tasks"][0]["per_episode"] != report["per_episode"]["base policy"]  # the agent, not the base
    assert evaluated["rl_agent"]["method"] == report["method"] and evaluated["tasks"][0]["task"] == report["task"]
    assert "acting through a fine-tuned RL agent" in (tmp_path / "eval_agent" / "report.md").read_text()
    assert [video["seed"] for video in evaluated["tasks"][0]["videos"]] == [seed]  # the agent's episode, recorded
    assert loss_csvs(tmp_path / "ft")  # SB3's actor_loss ... or PPO's loss ...
    assert pathlib.Path(evaluated["loss_plot"]).read_bytes()[:4] == b"\x89PNG"  # ... are the report's loss plot
    assert pathlib.Path(evaluated["tasks"][0]["videos"][0]["path"]).stat().st_size > 0


def test_eval_of_an_rl_agent_file_says_what_it_cannot_run(tmp_path):
    from dust_rl.cli import main

    older = save_checkpoint({"config": {"method": "steer"}, "state_dict": {}}, tmp_path / "rl_agent.pt", RL_AGENT_KIND)
    for flags, refused in ((["--execute-steps", "1"], "--execute-steps"),
                           (["resample", "--noise-scale", "0"], "resample")):
        with pytest.raises(SystemExit, match=f"runs as it was trained, in this process; drop {refused}$"):
            main(["eval", "--policy", str(older), *flags])
    with pytest.raises(SystemExit, match="written before an RL agent's file held its base policy"):
        main(["eval", "--policy", str(older)])


def test_dsrl_design_trains_saves_and_its_actor_acts_without_the_object_state(policy_path, tmp_path):
    config = SteerConfig(policy=policy_path, out=tmp_path / "ft", steps=8, batch_size=4, net_arch=(16, 16),
                         layer_norm=True, eval_episodes=2, max_steps=EPISODE_STEPS, eval_every=4, curve_episodes=1,
                         runtime=QUIET, algorithm=SacSettings(learning_starts=4, updates_per_step=2), **DSRL)
    report = finetune(config, command="dust-rl finetune ...")
    assert [row["episodes"] for row in report["rows"]] == [2, 2, 2]  # base, noise centre, fine-tuned
    curve = json.loads((tmp_path / "ft" / "learning_curve.json").read_text())
    assert [p["rl_steps"] for p in curve] == [0, 4, 8] and curve[1]["env_steps"] >= 2 * curve[1]["rl_steps"]
    assert (tmp_path / "ft" / "learning_curve.png").read_bytes()[:4] == b"\x89PNG"
    saved = load_checkpoint(tmp_path / "ft" / "rl_agent.pt", RL_AGENT_KIND)
    assert rl_config_from_json(saved["config"]) == config  # the groups read back
    assert_eval_runs_the_agent(report, tmp_path, config.eval_seed)  # finite horizon: time_left from the run's limit
    from dust_rl.cli import main

    with pytest.raises(SystemExit, match=f"time left of its {EPISODE_STEPS}-step episodes .*; drop --max-steps"):
        main(["eval", "--policy", str(tmp_path / "ft" / "rl_agent.pt"), "--max-steps", str(EPISODE_STEPS + 1)])
    # The saved agent acts from the actor's view, without the object state its critic was trained with.
    env = finetune_env_factory(config, load_policy(policy_path))[0]()
    assert isinstance(env, SB3SteeringVecEnv) and env.num_envs == 2
    agent = build_agent(config, env)
    agent.policy.load_state_dict(saved["state_dict"])
    assert agent.gradient_steps == 2
    obs = {k: v[0] for k, v in env.reset().items() if k != "object_state"}
    action = agent.predict(obs, deterministic=True)[0]
    assert action.shape == (7,) and np.abs(action).max() <= 1
    env.close()


def test_ppo_rolls_out_n_steps_over_all_envs(policy_path):
    config = SteerConfig(policy=policy_path, steps=8, batch_size=4, net_arch=(16,), max_steps=EPISODE_STEPS,
                         runtime=QUIET, algorithm=PpoSettings(n_steps=8, n_epochs=1),
                         collection=SteeringCollection(envs=2))
    env = finetune_env_factory(config, load_policy(policy_path))[0]()
    agent = build_agent(config, env)
    assert agent.n_steps == 4 and agent.n_envs == 2  # 8 transitions a rollout: 4 steps of 2 envs
    agent.learn(total_timesteps=8)
    assert agent.num_timesteps == 8 and agent._n_updates == 1
    env.close()


@pytest.mark.parametrize("algorithm", ["sac", "ppo"])
def test_initial_std_starts_the_agent_at_the_base_policy(algorithm, policy_path):
    settings = SacSettings(learning_starts=8) if algorithm == "sac" else PpoSettings()
    config = ResidualConfig(policy=policy_path, algorithm=settings, steps=16, batch_size=4, net_arch=(16,),
                            max_steps=EPISODE_STEPS, initial_std=0.05, runtime=QUIET)
    env = finetune_env_factory(config, load_policy(policy_path))[0]()
    agent = build_agent(config, env)
    obs, _ = env.reset(seed=0)
    assert np.array_equal(agent.predict(obs, deterministic=True)[0], np.zeros(env.action_space.shape, np.float32))
    log_std = agent.actor.log_std.bias if algorithm == "sac" else agent.policy.log_std
    agent.learn(total_timesteps=16)
    # The exploration stays where it started, through updates (SAC: 8 after its warm-up; PPO: one rollout's epochs).
    assert torch.equal(log_std, torch.full_like(log_std, float(np.log(np.float32(0.05)))))
    if algorithm == "sac":  # warm-up steps act with that actor: small actions, where SB3's are uniform in [-1, 1]
        warm_up = agent.replay_buffer.actions[:8]
        assert 0 < np.abs(warm_up).max() < 0.5
        assert agent.ent_coef_tensor.item() == 0.0  # a fixed std leaves the entropy bonus nothing to do
    env.close()


def test_a_learnt_entropy_moves_the_std_that_starts_at_the_base_policy(policy_path):
    config = SteerConfig(policy=policy_path, steps=12, batch_size=4, net_arch=(16,), max_steps=EPISODE_STEPS,
                         initial_std=0.5, runtime=QUIET,
                         algorithm=SacSettings(learning_starts=4, target_entropy=0.0, initial_alpha=0.01,
                                               updates_per_step=3))
    env = finetune_env_factory(config, load_policy(policy_path))[0]()
    agent = build_agent(config, env)
    obs, _ = env.reset(seed=0)
    assert np.array_equal(agent.predict(obs, deterministic=True)[0], np.zeros(env.action_space.shape, np.float32))
    assert agent.ent_coef_optimizer is not None  # learnt, from 0.01
    assert agent.log_ent_coef.exp().item() == pytest.approx(0.01) and agent.target_entropy == 0.0
    start = agent.actor.log_std.bias.detach().clone()
    agent.learn(total_timesteps=12)
    assert agent._n_updates == 3 * (12 - 4)  # updates_per_step per RL step once learning starts
    assert not torch.equal(agent.actor.log_std.bias, start)  # the std is learnt
    assert agent.log_ent_coef.exp().item() != pytest.approx(0.01)
    env.close()


def test_layer_norm_caps_the_critic_off_its_data(policy_path):
    config = SteerConfig(policy=policy_path, steps=8, net_arch=(16, 16), layer_norm=True, max_steps=EPISODE_STEPS,
                         runtime=QUIET)
    env = finetune_env_factory(config, load_policy(policy_path))[0]()
    agent = build_agent(config, env)
    obs, _ = env.reset(seed=0)
    obs_t, _ = agent.policy.obs_to_tensor(obs)
    q_net = agent.critic.q_networks[0]
    assert sum(isinstance(m, LayerNormReLU) for m in q_net) == 2  # after each hidden layer
    last = q_net[-1]
    # Each normalised-then-rectified hidden entry is at most sqrt(width), so |Q| <= |w|_1 sqrt(16) + |b| for any
    # action, however far off the box it is.
    bound = float(last.weight.abs().sum() * 16 ** 0.5 + last.bias.abs().sum())
    with torch.no_grad():
        far = torch.full((1, env.action_space.shape[0]), 1e6)
        q = agent.critic(obs_t, far)[0]
    assert q.abs().item() <= bound * (1 + 1e-5)
    env.close()


def test_bad_finetune_settings_are_named(policy_path, tmp_path):
    with pytest.raises(ConfigError, match="noise_bound"):
        SteerConfig(policy=policy_path, noise_bound=0.0)
    with pytest.raises(ConfigError, match=r"noise_bound must be at most 10.0, got 1e\+30: the policy draws its noise "):
        SteerConfig(policy=policy_path, noise_bound=1e30)  # used to overflow the sampler into NaN actions
    with pytest.raises(ConfigError, match=r"seed must be in \[0, 4294967295\] \(SB3 seeds numpy's generator"):
        SteerConfig(policy=policy_path, seed=2**40)
    for flag, field in (("--eval-seed", "eval_seed"), ("--curve-seed", "curve_seed")):
        with pytest.raises(ConfigError, match=rf"give {flag} in \[0, {2**63 - 21}\]"):  # 20 episodes, one more started
            SteerConfig(policy=policy_path, **{field: 2**63 - 1}, eval_episodes=20, curve_episodes=20)
    with pytest.raises(ConfigError, match="residual_scale"):
        ResidualConfig(policy=policy_path, residual_scale=float("inf"))
    with pytest.raises(ConfigError, match="initial_std must be a finite number > 0"):
        SteerConfig(policy=policy_path, initial_std=0.0)
    with pytest.raises(ConfigError, match="target_entropy must be a finite number"):
        SacSettings(target_entropy=float("nan"))
    with pytest.raises(ConfigError, match="updates_per_step"):
        SacSettings(updates_per_step=0)
    with pytest.raises(ConfigError, match="lr must be a finite number > 0"):
        SteerConfig(policy=policy_path, lr=float("nan"))
    with pytest.raises(ConfigError, match="net_arch"):
        SteerConfig(policy=policy_path, net_arch=())
    with pytest.raises(ConfigError, match="add --finite-horizon"):
        SteerConfig(policy=policy_path, reward="penalty")
    with pytest.raises(ConfigError, match="steps counts the transitions of all 2 envs: make it a multiple"):
        SteerConfig(policy=policy_path, steps=9, collection=SteeringCollection(envs=2))
    with pytest.raises(ConfigError, match="n_steps counts the transitions"):
        SteerConfig(policy=policy_path, collection=SteeringCollection(envs=3), steps=9, checkpoint_every=9,
                    algorithm=PpoSettings())
    with pytest.raises(ConfigError, match="--base-warmup fills SAC's warm-up steps"):
        SteerConfig(policy=policy_path, initial_std=0.1, collection=SteeringCollection(base_warmup=True))
    with pytest.raises(ConfigError, match="--privileged-critic"):
        SteerConfig(policy=policy_path, algorithm=PpoSettings(),
                    observation=SteeringObservation(privileged_critic=True))
    with pytest.raises(ConfigError, match="envs must be >= 1"):
        SteeringCollection(envs=0)
    with pytest.raises(ConfigError, match="latent_dim must be >= 1"):
        LatentSettings(0)
    with pytest.raises(ConfigError, match=r"--latent-dim: latent_dim must be in \[1, 28\]"):
        finetune_env_factory(SteerConfig(policy=policy_path, latent=LatentSettings(29)), load_policy(policy_path))
    with pytest.raises(ConfigError, match="unknown device 'tpu'"):
        ResidualConfig(policy=policy_path, runtime=RuntimeSettings(device="tpu"))
    with pytest.raises(ConfigError, match="no_such_task"):
        finetune(SteerConfig(policy=policy_path, out=tmp_path, task="no_such_task", runtime=QUIET))
    busy = tmp_path / "busy"
    busy.mkdir()
    with folder_lock(busy), pytest.raises(FolderLockedError, match=f"pid {os.getpid()}"):  # as a run holds it
        finetune(SteerConfig(policy=policy_path, out=busy, steps=8, runtime=QUIET))
    assert [p.name for p in busy.iterdir()] == [".lock"]


def test_a_finished_ppo_run_resumes_to_a_larger_budget_and_sac_refuses(policy_path, tmp_path):
    config = ResidualConfig(policy=policy_path, out=tmp_path / "ppo", algorithm=PpoSettings(n_steps=8), steps=8,
                            batch_size=4, net_arch=(16,), eval_episodes=1, max_steps=EPISODE_STEPS,
                            checkpoint_every=8, runtime=QUIET)
    first = finetune(config)
    saved = Checkpoint.manifest(CheckpointRotation(config.out / "checkpoints", keep_last=2).latest())["metadata"]
    began = time.perf_counter()
    report = finetune(dataclasses.replace(config, steps=16, resume=True))
    resumed_wall = time.perf_counter() - began
    # the first process's seconds count too (saved with its checkpoint), not only the resumed one's
    assert report["train_seconds"] > first["train_seconds"]
    assert 0 < saved["train_seconds"] <= first["train_seconds"]
    assert saved["train_seconds"] < report["train_seconds"] < saved["train_seconds"] + resumed_wall
    env = finetune_env_factory(config, load_policy(policy_path))[0]()
    state = SB3LearningState(build_agent(config, env))
    restore(Checkpoint(agent=state, rng=RunRNGState()), CheckpointRotation(config.out / "checkpoints", keep_last=2))
    env.close()
    assert state.agent.num_timesteps == 16 and report["steps"] == 16
    sac = dataclasses.replace(config, out=tmp_path / "sac", algorithm=SacSettings(learning_starts=4))
    finetune(sac)
    with pytest.raises(ConfigError, match=r"other settings \(steps\)"):
        finetune(dataclasses.replace(sac, steps=16, resume=True))


@pytest.mark.parametrize("design", ["default", "dsrl"])
def test_resume_after_kill_loses_and_repeats_no_step(policy_path, tmp_path, design):
    settings = {"steps": 120, "checkpoint_every": 8, "batch_size": 4, "net_arch": (16,), "eval_episodes": 1,
                "max_steps": EPISODE_STEPS}
    dsrl = design == "dsrl"
    reference = SteerConfig(policy=policy_path, out=tmp_path / "ref", runtime=QUIET,
                            algorithm=SacSettings(learning_starts=4, updates_per_step=2 if dsrl else 1),
                            **settings, **(DSRL if dsrl else {}))
    finetune(reference)
    out = tmp_path / "killed"
    args = ["finetune", "steer", "--policy", str(policy_path), "--out", str(out), "--runtime.no-progress",
            "--runtime.threads", "1"]
    for key, value in settings.items():
        args += [f"--{key.replace('_', '-')}", *map(str, value if isinstance(value, tuple) else (value,))]
    args += [*(DSRL_FLAGS if dsrl else []), "sac", "--learning-starts", "4",
             *(["--updates-per-step", "2"] if dsrl else [])]
    kill_after_first_checkpoint(args, out)
    assert not (out / "rl_agent.pt").exists()

    with pytest.raises(FileExistsError, match="--resume"):
        finetune(dataclasses.replace(reference, out=out))
    finetune(dataclasses.replace(reference, out=out, resume=True))
    states = {}
    for name in ("ref", "killed"):
        env = finetune_env_factory(reference, load_policy(policy_path))[0]()
        state = SB3LearningState(build_agent(reference, env))
        rotation = CheckpointRotation(tmp_path / name / "checkpoints", keep_last=2)
        restore(Checkpoint(agent=state, rng=RunRNGState()), rotation)
        states[name] = state.agent
        env.close()
    envs = reference.collection.envs
    for agent in states.values():
        assert agent.num_timesteps == 120 and agent.replay_buffer.pos == 120 // envs % agent.replay_buffer.buffer_size
        assert agent.replay_buffer.full  # 120 transitions in a buffer of 120: none lost, none twice
    first = 8 // envs  # the transitions before the first checkpoint are the same in both runs
    ref, got = states["ref"].replay_buffer, states["killed"].replay_buffer
    assert np.array_equal(ref.actions[:first], got.actions[:first])
    assert np.array_equal(ref.rewards[:first], got.rewards[:first])


def test_self_imitation_rolls_out_the_policy_on_fresh_seeds(policy_path, demo_dir, tmp_path):
    config = SelfImitationConfig(policy=policy_path, out=tmp_path / "ft", rollout_successes=1, max_steps=EPISODE_STEPS,
                                 curve_episodes=1, runtime=QUIET)
    with pytest.raises(ConfigError, match="pass --demos"):  # the policy file names no training dataset
        finetune(config)
    # An untrained policy never succeeds: the first round's collection gives up, its rollouts kept on disk.
    with pytest.raises(SuccessesOutOfReachError, match="press_button policy succeeded in only 0 of .* the policy"):
        finetune(dataclasses.replace(config, out=tmp_path / "ft2", demos=demo_dir))
    records = scan_episodes(tmp_path / "ft2" / "round-1" / "rollouts")["press_button"]
    tried = MAX_SEEDS_PER_EPISODE["policy"] * config.rollout_successes + 10
    assert sorted(records) == list(range(config.rollout_seed, config.rollout_seed + tried))
    assert all(r.length == EPISODE_STEPS and not r.success and not r.kept for r in records.values())
    # More rounds resume the run (the same collection goes on); other changed settings do not.
    with pytest.raises(SuccessesOutOfReachError, match=f"succeeded in only 0 of {tried + 1} "):
        finetune(dataclasses.replace(config, out=tmp_path / "ft2", demos=demo_dir, rounds=2, resume=True))
    with pytest.raises(ConfigError, match="started with other settings \\(rollout_successes\\)"):
        finetune(dataclasses.replace(config, out=tmp_path / "ft2", demos=demo_dir, rollout_successes=2, resume=True))
    # DAgger (the expert's labels taught): the failed rollouts are kept too, with their rows.
    dagger = dataclasses.replace(config, out=tmp_path / "ft3", demos=demo_dir,
                                 train=dataclasses.replace(config.train, data=dataclasses.replace(config.train.data,
                                                                                   extra_action_key="expert_action")))
    with pytest.raises(SuccessesOutOfReachError, match="succeeded in only 0 of"):
        finetune(dagger)
    kept = scan_episodes(tmp_path / "ft3" / "round-1" / "rollouts")["press_button"].values()
    assert len(kept) == tried and all(r.kept for r in kept)
    base_point = json.loads((tmp_path / "ft2" / "curve" / "round-0" / "report.json").read_text())
    assert base_point["seeds"] == [config.curve_seed, config.curve_seed] and base_point["policy"] == str(policy_path)


def test_the_control_is_the_base_fine_tuned_as_long_on_its_demonstrations_alone(policy_path, demo_dir, tmp_path):
    config = SelfImitationConfig(policy=policy_path, out=tmp_path / "ft", demos=demo_dir, rounds=2, seed=3,
                            train=RoundTraining(optim=OptimSettings(steps=2, lr=1e-4, batch_size=4),
                                                logging=LoggingSettings(log_every=1)),
                            eval_episodes=1, max_steps=EPISODE_STEPS, runtime=QUIET)
    name, row = control_row(config)
    assert name == "demonstrations alone (4 steps, the control)"  # two rounds of two steps
    trained = json.loads((tmp_path / "ft" / "control" / "steps-4" / "config.json").read_text())["config"]
    assert (trained["optim"]["steps"], trained["init_policy"], trained["data"]["extra_dataset"]) == (
        4, str(policy_path), None)
    assert trained["seed"] == 3  # the run's --seed: the rounds' own is not offered
    assert trained["dataset"] == str(demo_dir)
    assert row["episodes"] == 1 and row["seeds"] == [config.eval_seed]
    assert control_row(config) == (name, row)  # cached: read back, not trained or evaluated again


def test_a_rounds_time_adds_up_over_resumed_invocations(tmp_path):
    assert _add_seconds(tmp_path, 100.0) == 100.0  # the invocation that collected and trained
    assert _add_seconds(tmp_path, 0.5) == 100.5  # a resume that read the cached stages back
    assert json.loads((tmp_path / ROUND_SECONDS).read_text()) == {"seconds": 100.5}


@pytest.fixture(scope="module")
def sac_run(policy_path, tmp_path_factory) -> SteerConfig:
    """A finished SAC steering run of 8 steps, checkpointed at 4 and 8 (tests that change it put it back)."""
    config = SteerConfig(policy=policy_path, out=tmp_path_factory.mktemp("sac") / "ft", steps=8, checkpoint_every=4,
                         algorithm=SacSettings(learning_starts=2), batch_size=4, net_arch=(16,), eval_episodes=1,
                         max_steps=EPISODE_STEPS, runtime=QUIET)
    finetune(config)
    return config


def _tampered_agent(run: SteerConfig, path: pathlib.Path, edit) -> pathlib.Path:
    """The run's ``rl_agent.pt`` with ``edit`` applied to its entries, saved at ``path``."""
    payload = torch.load(run.out / "rl_agent.pt", weights_only=True)
    edit(payload)
    torch.save(payload, path)
    return path


def _nan_weights(payload: dict) -> None:
    for value in payload["state_dict"].values():
        value.fill_(float("nan"))


TAMPERED_AGENTS = {
    "settings-a-string": (lambda d: d.update(config="x"), "the fine-tuning settings do not read back (TypeError: the "
                                                          "fine-tuning settings are 'x', not an object of settings)"),
    "noise-bound-1e30": (lambda d: d["config"].update(noise_bound=1e30),
                         "the fine-tuning settings do not read back (ConfigError: noise_bound must be at most 10.0"),
    "nan-weights": (_nan_weights, "the RL agent does not load (ValueError: NaN or infinity in ['actor."),
}


@pytest.mark.parametrize("case", TAMPERED_AGENTS)
def test_eval_of_a_tampered_rl_agent_file_ends_in_one_line_naming_it(sac_run, tmp_path, case):
    from test_cli_errors import error_of

    edit, problem = TAMPERED_AGENTS[case]
    agent = _tampered_agent(sac_run, tmp_path / "rl_agent.pt", edit)
    assert f"{agent}: {problem}" in error_of(["eval", "--policy", str(agent), "--out", str(tmp_path / "eval"),
                                             "--episodes", "1", "--runtime.no-progress"])


def _forge(checkpoint: pathlib.Path, entry: str, value: object) -> None:
    """Set the agent component's state ``entry`` (``replay_buffer/pos``) to the JSON ``value``, or fill the tensor there
    with NaN (``value`` None), then write the digests anew, as a forger would."""
    from test_train import _record_digests

    component = next((checkpoint / "components").glob("*-agent"))
    state = json.loads((component / "state.json").read_text())
    node = state
    for name in entry.split("/"):
        node = next(v for k, v in node["items"] if k.get("value") == name)
    if value is None:
        memmap = component / "state" / f"{node['key']}.memmap"
        np.full(memmap.stat().st_size // 4, np.nan, np.float32).tofile(memmap)
    else:
        node["value"] = value
    (component / "state.json").write_text(json.dumps(state))
    _record_digests(checkpoint)


FORGED = {  # the first checkpoint holds 4 steps of 1 env in a buffer of 8 rows
    "pos-1e9": ("replay_buffer/pos", 10**9, r"the saved replay buffer \(pos 1000000000, full False, 4 rows\) is not "
                                            r"what 4 steps of 1 env\(s\) fill in a buffer of 8 rows"),
    "full-but-half-empty": ("replay_buffer/full", True, r"\(pos 4, full True, 4 rows\) is not what 4 steps"),
    "negative-step": ("counters/num_timesteps", -100, r"counters/num_timesteps is -100, not a count >= 0"),
    "step-past-the-run": ("counters/num_timesteps", 10**12, r"num_timesteps is 1000000000000, past the run's 8 steps"),
    "nan-rewards": ("replay_buffer/rewards", None, r"NaN or infinity in \['rewards'\]"),
}


@pytest.mark.parametrize("case", FORGED)
def test_a_forged_replay_buffer_or_step_counter_is_refused_on_resume(sac_run, tmp_path, case):
    """The digests are the writer's own, so a forger writes them anew; what a checkpoint restores is checked itself."""
    entry, value, problem = FORGED[case]
    checkpoints = sac_run.out / "checkpoints"
    kept = shutil.copytree(checkpoints, tmp_path / "kept")
    agent_file = (sac_run.out / RL_AGENT_FILE).read_bytes()
    try:
        first, last = sorted(checkpoints.iterdir())
        shutil.rmtree(last)  # resume from the first
        _forge(first, entry, value)
        with pytest.raises(CheckpointError, match=rf"{first.name}: cannot resume from this checkpoint .*{problem}"):
            finetune(dataclasses.replace(sac_run, resume=True))
    finally:
        shutil.rmtree(checkpoints)
        shutil.move(kept, checkpoints)
    assert (sac_run.out / RL_AGENT_FILE).read_bytes() == agent_file


def test_diverging_rl_training_stops_before_non_finite_weights_act_or_are_saved(policy_path, tmp_path):
    config = SteerConfig(policy=policy_path, out=tmp_path / "ft", steps=16, checkpoint_every=8, lr=1e30,
                         algorithm=SacSettings(learning_starts=8), batch_size=4, net_arch=(16,), eval_episodes=1,
                         max_steps=EPISODE_STEPS, runtime=QUIET)
    with pytest.raises(NonFiniteLossError, match=r"training diverged at step 9: NaN or infinity in the RL agent's "
                                                 r"weights .*no rl_agent\.pt was written and the newest checkpoint, "
                                                 r"checkpoint-000000000008, is intact; lower --lr"):
        finetune(config)  # the first update (after step 8's checkpoint) makes the weights infinite
    assert not (config.out / RL_AGENT_FILE).exists()
    (state,) = (config.out / "checkpoints").glob("checkpoint-*/components/*-agent/state")
    tensors = TensorDict.load_memmap(state).values(include_nested=True, leaves_only=True)
    assert all(torch.isfinite(t).all() for t in tensors if t.is_floating_point())


def test_a_pickle_grafted_into_a_finetune_checkpoint_never_runs_on_resume(policy_path, tmp_path):
    config = ResidualConfig(policy=policy_path, out=tmp_path / "ppo", algorithm=PpoSettings(n_steps=8), steps=8,
                            batch_size=4, net_arch=(16,), eval_episodes=1, max_steps=EPISODE_STEPS,
                            checkpoint_every=8, runtime=QUIET)
    finetune(config)
    agent_file = (config.out / "rl_agent.pt").read_bytes()
    latest = CheckpointRotation(config.out / "checkpoints", keep_last=2).latest()
    marker = tmp_path / "code-ran"
    CRAFTS["entry"](next((latest / "components").glob("*-agent")) / "state", marker)
    with pytest.raises(CheckpointError, match=r"cannot resume from this checkpoint .*evil/other\.pickle.*refused"):
        finetune(dataclasses.replace(config, resume=True))
    assert not marker.exists()
    assert (config.out / "rl_agent.pt").read_bytes() == agent_file


def test_a_full_disk_at_a_checkpoint_ends_fine_tuning_in_one_line(policy_path, tmp_path, monkeypatch):
    real = shutil.disk_usage
    monkeypatch.setattr(shutil, "disk_usage", lambda path: real(path)._replace(free=0))
    config = ResidualConfig(policy=policy_path, out=tmp_path / "ppo", algorithm=PpoSettings(n_steps=8), steps=8,
                            batch_size=4, net_arch=(16,), eval_episodes=1, max_steps=EPISODE_STEPS,
                            checkpoint_every=8, runtime=QUIET)
    with pytest.raises(NoSpaceError, match=f"no space left on device while fine-tuning into {config.out} "):
        finetune(config)
    assert not list((config.out / "checkpoints").glob(".*"))  # no half-written checkpoint left


def test_a_logger_whose_package_is_missing_is_refused_before_anything_is_written(policy_path, tmp_path, capsys):
    from dust_rl.cli import main

    out = tmp_path / "ft"
    with pytest.raises(SystemExit, match=r"^dust-rl: error: --loggers wandb needs the wandb package: pip install "
                                         r"wandb$"):
        main(["finetune", "residual", "--policy", str(policy_path), "--out", str(out), "--loggers", "csv", "wandb"])
    assert not out.exists()
    with pytest.raises(ConfigError, match="unknown loggers"):
        SteerConfig(policy=policy_path, loggers=("csv", "stdout"))


def test_each_method_is_a_subcommand_with_only_its_own_settings(capsys):
    from dust_rl.cli import main

    def help_of(*words: str) -> str:
        with pytest.raises(SystemExit):
            main(["finetune", *words, "--help"])
        return capsys.readouterr().out

    assert all(method in help_of() for method in ("steer", "residual", "self-imitation"))
    steer, sac, ppo = help_of("steer"), help_of("steer", "sac"), help_of("steer", "ppo")
    assert "--noise-bound" in steer and "--residual-scale" not in steer
    dsrl = ("--latent-dim", "--no-instruction", "--privileged-critic", "--envs", "--base-warmup")
    assert all(flag in steer for flag in dsrl) and not any(flag in help_of("residual") for flag in dsrl)
    assert "--updates-per-step" in sac and "--n-steps" not in sac
    assert "--n-steps" in ppo and "--updates-per-step" not in ppo
    rounds = help_of("self-imitation")
    assert "--train.optim.steps" in rounds and "--train.policy" not in rounds and "--train.init-policy" not in rounds
    # The rounds run under the run's own --runtime.* (one group, not a second one of the rounds').
    assert "--runtime.threads" in rounds and "--train.runtime" not in rounds


def test_an_sb3_run_config_reads_back_also_from_before_the_algorithm_had_its_own_settings():
    old = {"method": "residual", "policy": "p.pt", "out": "runs/ft", "algorithm": "ppo", "n_steps": 512,
           "n_epochs": 3, "gradient_steps": 1, "net_arch": [16], "world_model_obs": True, "learning_rate": 1e-3}
    config = rl_config_from_json(old, device="cpu")
    assert isinstance(config, ResidualConfig) and config.world_model_obs and config.runtime.device == "cpu"
    assert config.lr == 1e-3  # the learning rate's earlier name
    assert config.algorithm == PpoSettings(n_steps=512, n_epochs=3) and config.net_arch == (16,)
    new = SteerConfig(policy=pathlib.Path("p.pt"), algorithm=SacSettings(initial_alpha=0.5))
    assert rl_config_from_json(json.loads(json.dumps(dataclasses.asdict(new), default=str))) == new
    steer = {"method": "steer", "policy": "p.pt", "out": "runs/ft", "algorithm": {"name": "sac", "gradient_steps": 5}}
    read = rl_config_from_json(steer)  # SAC's update-to-data ratio by its earlier name; the steering groups default
    assert read.algorithm.updates_per_step == 5 and read.collection == SteeringCollection()


def test_a_run_config_from_before_the_runtime_group_reads_its_threads_device_and_progress_into_it():
    """Runs stored before every command's runtime settings were one group kept `threads`, `device` and `progress`
    beside the other settings (`--threads 2`); they read back as `runtime`, where today's run keeps them."""
    runtime = RuntimeSettings(threads=2, device="cpu", progress=False)
    today = config_json(SteerConfig(policy=pathlib.Path("p.pt"), runtime=runtime))
    flat = {"threads": 2, "device": "cpu", "progress": False}
    before = {**{k: v for k, v in today.items() if k != "runtime"}, **flat}
    assert as_this_version(before)["runtime"] == flat and not set(flat) & set(as_this_version(before))
    read = rl_config_from_json(before)
    assert read.runtime == runtime and read == rl_config_from_json(today)
    # an agent fine-tuned on a GPU loads on a machine without one when told where to run
    on_gpu = {**before, "device": "cuda"}
    assert rl_config_from_json(on_gpu, device="cpu").runtime == runtime
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="sees no CUDA device"):
            rl_config_from_json(on_gpu)
    rounds = SelfImitationConfig(policy=pathlib.Path("p.pt"), runtime=runtime)  # as a resumed run reads it back
    stored = {**{k: v for k, v in config_json(rounds).items() if k != "runtime"}, **flat}
    assert config_from_json(SelfImitationConfig, as_this_version(stored)) == rounds


@pytest.mark.parametrize("algorithm,name,value,other", [(SacSettings(), "q_bounds", None, [0.0, 1.0]),
                                                        (PpoSettings(), "target_kl", None, 0.01),
                                                        (PpoSettings(), "critic_warmup", 0, 1024)])
def test_a_retired_sb3_setting_reads_back_at_the_value_every_run_now_has_only(algorithm, name, value, other,
                                                                             policy_path, tmp_path):
    config = ResidualConfig(policy=policy_path, out=tmp_path / "ft", algorithm=algorithm, runtime=QUIET)
    today = config_json(config)

    def stored(setting: object) -> dict:  # as an rl_agent.pt or config.json of before holds the run's settings
        return {**today, "algorithm": {**today["algorithm"], name: setting}}

    assert rl_config_from_json(stored(value)) == config
    with pytest.raises(ValueError, match=rf"^algorithm\.{name} = .*: a setting this version removed .* 74cb2e1\)$"):
        rl_config_from_json(stored(other))
    flat = {**today, "algorithm": algorithm.name, name: other}  # from before the algorithm had its own settings
    with pytest.raises(ValueError, match=rf"^{name} = "):
        rl_config_from_json(flat)
    config.out.mkdir()
    (config.out / "config.json").write_text(json.dumps({"config": stored(other)}))
    with pytest.raises(ConfigError, match=rf"started with algorithm\.{name} = .* 74cb2e1\); it cannot resume"):
        finetune(dataclasses.replace(config, resume=True))


def test_a_self_imitation_run_from_before_the_settings_groups_reads_as_todays():
    today = config_json(SelfImitationConfig(policy=pathlib.Path("policy.pt"), train=RoundTraining(
        optim=OptimSettings(steps=7), data=RoundData(extra_action_key="expert_action"))))
    before = {**today, "train": as_before_the_groups(today["train"])}
    assert before["train"]["steps"] == 7 and "optim" not in before["train"]
    assert as_this_version(before) == today
    assert as_this_version({"method": "steer"}) == {"method": "steer"}


def test_bench_steer_speed_times_collection_and_updates_for_each_env_count(policy_path, capsys):
    from dust_rl.cli import main

    main(["bench", "steer-speed", "--policy", str(policy_path), "--envs", "1", "2", "--rl-steps", "2", "--updates", "2",
          "--batch-size", "4", "--net-arch", "16", "--max-steps", str(EPISODE_STEPS), "--runtime.device", "cpu"])
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("| envs | RL steps | env steps/s") and len(lines) == 4
    rows = [line.split("|")[1:-1] for line in lines[2:]]
    assert [(int(r[0]), int(r[1])) for r in rows] == [(1, 2), (2, 2)]  # 2 RL steps: 2 of 1 env, 1 of 2 envs
    assert all(float(value) > 0 for r in rows for value in r[2:])
