"""RL fine-tuning of a trained DUST policy: ``dust-rl finetune steer|residual|self-imitation``.

Read top to bottom, CleanRL style: arguments, the frozen policy and its env,
the fine-tuning env (noise steering or residual, :mod:`dust_rl.rl.steering`,
:mod:`dust_rl.rl.residual`), the SB3 agent and its training, then a closed-loop
comparison with the base policy on the same held-out seeds. Steering with ``--envs N`` steps N envs together, one
plan call for all (:mod:`dust_rl.rl.vector`); ``--privileged-critic`` gives SAC's critic the true object state, never
its actor (:mod:`dust_rl.rl.asymmetric`); ``--base-warmup`` fills SAC's warm-up with the base policy's own latents.

The imitation policy's weights never change (except with ``self_imitation``,
which writes new policy files beside it), so the base policy stays one
flag away. The RL agent's weights are saved as a plain state dict rather than SB3's zip, whose loader unpickles
objects, in one file with the frozen policy (``rl_agent.pt``, read with ``weights_only=True``), which ``dust-rl
eval`` runs as it runs a policy (:mod:`dust_rl.rl.fine_tuned_policy`).

SB3 trains on the gymnasium envs, but every closed-loop episode of the report (the learning curve's points, the
base, noise-centre and fine-tuned rows) runs through ``dust-rl eval``'s one runner
(:func:`dust_rl.evaluate.closed_loop.evaluate_task`: a torchrl collector, the seeded chunk executor, the same
episode records), so an evaluation here and there cannot drift apart. The base row is the policy as ``dust-rl
eval`` runs it, so its episodes are ``dust-rl eval``'s, digest for digest (tested); the agent acts through the
env's :meth:`~dust_rl.rl.frozen_policy_env.FrozenPolicyEnv.closed_loop_actor` (steering: a
:class:`~dust_rl.rl.steering.SteeredPolicy` picks each chunk's noise; residual: a
:class:`~dust_rl.rl.residual.ResidualCorrection` after the executor), seeing what the env shows it in training.

Every ``checkpoint_every`` RL steps the whole learning state (networks,
optimisers, replay buffer, counters, RNG; :mod:`dust_rl.rl.checkpoint`) goes
to a torchrl ``Checkpoint``; ``--resume`` continues from the newest one. The agent's scalars go through
torchrl's loggers (``--loggers``, :mod:`dust_rl.rl.sb3_logger`), as training's do.

``self-imitation`` trains no RL agent: it fine-tunes the policy's own weights on its
successful rollouts (:mod:`dust_rl.rl.self_imitation`). torchrl's SAC front-end is :mod:`dust_rl.rl.torchrl_sac`.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import time
from collections.abc import Callable

import numpy as np
from stable_baselines3 import PPO, SAC
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.policies import BasePolicy
from tensordict.nn import TensorDictModuleBase
from torchrl.checkpoint import Checkpoint, CheckpointRotation

from dust_rl.agents import DustPolicy, load_policy
from dust_rl.agents.factory import policy_entries
from dust_rl.envs.factory import check_tasks, make_env
from dust_rl.errors import ConfigError
from dust_rl.evaluate.closed_loop import EvalConfig, eval_setup, evaluate_task, summary_row
from dust_rl.evaluate.records import Episode
from dust_rl.evaluate.report import plot_learning_curve
from dust_rl.rl.asymmetric import AsymmetricSACPolicy
from dust_rl.rl.checkpoint import SB3LearningState
from dust_rl.rl.config import (
    PPO_RESUMABLE_FIELDS,
    RESUMABLE_FIELDS,
    RETIRED_RL_SETTINGS,
    RL_AGENT_FILE,
    RL_AGENT_KIND,
    FinetuneCommand,
    FinetuneConfig,
    RLConfig,
    SacSettings,
    SelfImitationConfig,
    SteerConfig,
    as_this_version,
    is_dagger,
)
from dust_rl.rl.critic_limits import LayerNormReLU
from dust_rl.rl.frozen_policy_env import Act, FrozenPolicyEnv
from dust_rl.rl.report_rows import BASE_ROW, rows_against_base
from dust_rl.rl.residual import ResidualEnv
from dust_rl.rl.sb3_logger import sb3_logger
from dust_rl.rl.self_imitation import self_imitation
from dust_rl.rl.start_at_base import BaseWarmupSAC, WarmStartSAC, start_at_base
from dust_rl.rl.steering import NoiseSteeringEnv, latent_map
from dust_rl.rl.vector import SB3SteeringVecEnv
from dust_rl.runtime.device import resolve_device
from dust_rl.runtime.episode_collector import torch_threads
from dust_rl.storage.atomic_files import write_json_atomic, write_text_atomic
from dust_rl.storage.checkpoint_dirs import run_out_of_space, save_checkpoint_dir
from dust_rl.storage.checkpoint_files import non_finite, save_checkpoint
from dust_rl.storage.config_json import config_json
from dust_rl.storage.run_folder import RunRNGState, check_run_folder, locked_run_folder, restore
from dust_rl.train.imitation import diverged

ALGORITHMS: dict[str, type[BaseAlgorithm]] = {"sac": SAC, "ppo": PPO}
FineTuningEnv = FrozenPolicyEnv | SB3SteeringVecEnv
"""What SB3 trains on: one fine-tuning env, or several steering envs stepped together."""


def finetune(config: FinetuneConfig, command: str | None = None) -> dict:
    """Fine-tune, save the result, compare with the base policy; returns the report."""
    is_ppo = not isinstance(config, SelfImitationConfig) and config.algorithm.name == "ppo"
    resumable = PPO_RESUMABLE_FIELDS if is_ppo else RESUMABLE_FIELDS
    with torch_threads(config.runtime.thread_count):
        check_run_folder(config, resumable, RETIRED_RL_SETTINGS, as_this_version)
        policy = load_policy(config.policy)
        env_id, env_kwargs, task = policy_env(config, policy)
        if isinstance(config, SelfImitationConfig):
            demos = config.demos or pathlib.Path(policy.info.get("dataset") or "")
            if not (demos / "meta.json").is_file():
                raise ConfigError(f"self-imitation trains on the policy's demonstrations too; {demos} is not a "
                                  "dataset: pass --demos")
            config = dataclasses.replace(config, demos=demos)
        with (run_out_of_space(f"fine-tuning into {config.out}"),
              locked_run_folder(config, resumable, command, RETIRED_RL_SETTINGS, as_this_version)):
            return _finetune_in_folder(config, command, policy, env_id, env_kwargs, task)


def _finetune_in_folder(config: FinetuneConfig, command: str | None, policy: DustPolicy, env_id: str,
                        env_kwargs: dict, task: str) -> dict:
    """The fine-tuning and its report, once the run folder is this run's."""
    if isinstance(config, SelfImitationConfig):
        result = self_imitation(config, task, env_id, env_kwargs)
        episodes = {name: [Episode.from_json(e) for e in row["per_episode"]] for name, row in result["rows"].items()}
        extra = {k: v for k, v in result.items() if k not in ("rows", "train_seconds")}
        trained_s = result["train_seconds"]
    else:
        policy.to(resolve_device(config.runtime.device))  # its precision and compilation: eval_runner's eval_setup
        make, task = finetune_env_factory(config, policy)
        episodes, trained_s = train_rl(config, policy, make, eval_runner(config, policy, task))
        extra = {"algorithm": config.algorithm.name, "steps": config.steps,
                 "rl_agent": str(config.out / RL_AGENT_FILE)}
    report = {
        "policy": str(config.policy), "method": config.method, "task": task, "command": command,
        "config": config_json(config),
        "seeds": [config.eval_seed, config.eval_seed + config.eval_episodes - 1], "train_seconds": trained_s,
        "rows": rows_against_base(episodes),
        "per_episode": {name: [e.to_json() for e in rows] for name, rows in episodes.items()}, **extra,
    }
    write_json_atomic(config.out / "report.json", report, indent=2)
    write_text_atomic(config.out / "report.md", _markdown(report))
    return report


Run = Callable[[range, TensorDictModuleBase | None], list[Episode]]
"""Closed-loop episodes on seeds, of an actor (None: the base policy)."""


def eval_runner(config: RLConfig, policy: DustPolicy, task: str) -> Run:
    """Episodes of ``task`` through ``dust-rl eval``'s runner (:func:`~dust_rl.evaluate.closed_loop.evaluate_task`,
    one worker in this process): of ``policy`` as ``dust-rl eval`` runs it, or of an actor built around it."""
    settings = EvalConfig(policy=config.policy, out=config.out, tasks=(task,), workers=1, videos=0,
                          max_steps=config.max_steps, runtime=config.runtime)
    setup = eval_setup(settings, policy)

    def run(seeds: range, actor: TensorDictModuleBase | None) -> list[Episode]:
        on_seeds = dataclasses.replace(settings, seed=seeds.start, episodes=len(seeds))
        return evaluate_task(setup, task, policy, on_seeds, actor)[0]

    return run


def train_rl(config: RLConfig, policy: DustPolicy, make: Callable[[], FineTuningEnv],
             run: Run) -> tuple[dict[str, list[Episode]], float]:
    """Train the SB3 agent on the fine-tuning env of the frozen ``policy`` (resuming from the newest checkpoint),
    save it with the policy as one file (:mod:`dust_rl.rl.fine_tuned_policy`), and run the base and the fine-tuned
    policy on the evaluation seeds through ``run`` (:func:`eval_runner`); returns their episodes by row name and the
    training seconds."""
    began = time.perf_counter()
    env = make()
    agent = build_agent(config, env)
    agent.set_logger(sb3_logger(config.loggers, config.out / "logs"))
    checkpoint = Checkpoint(agent=SB3LearningState(agent, config.steps), rng=RunRNGState())
    rotation = CheckpointRotation(config.out / "checkpoints", keep_last=2)
    restored = restore(checkpoint, rotation)
    env.env_steps = int(restored.get("env_steps", 0))
    seconds_before = float(restored.get("train_seconds", 0.0))  # earlier processes' share of a resumed run

    def trained_seconds() -> float:
        return seconds_before + time.perf_counter() - began

    curve_path = config.out / "learning_curve.json"
    curve = [p for p in _read_curve(curve_path) if p["rl_steps"] <= agent.num_timesteps]  # none past the checkpoint
    curve_seeds = range(config.curve_seed, config.curve_seed + config.curve_episodes)
    if config.eval_every and not curve:  # the curve starts at the base policy (the RL agent's "off" action)
        curve.append({"rl_steps": 0, "env_steps": 0, **summary_row(BASE_ROW, run(curve_seeds, None))})
    sitting = min(config.checkpoint_every, config.eval_every or config.checkpoint_every)
    callbacks = [DivergenceCheck(rotation)]
    while agent.num_timesteps < config.steps:  # in sittings of checkpoint_every (or eval_every) steps
        agent.learn(total_timesteps=min(sitting, config.steps - agent.num_timesteps), reset_num_timesteps=False,
                    progress_bar=config.runtime.progress, callback=callbacks)
        last_eval = curve[-1]["rl_steps"] if curve else 0
        if config.eval_every and (agent.num_timesteps >= last_eval + config.eval_every
                                  or agent.num_timesteps >= config.steps):
            episodes = run(curve_seeds, env.closed_loop_actor(deterministic(agent)))
            curve.append({"rl_steps": agent.num_timesteps, "env_steps": env.env_steps,
                          **summary_row("fine-tuned", episodes)})
            agent.logger.record("eval/curve_success_rate", curve[-1]["success_rate"])
            write_json_atomic(curve_path, curve, indent=2)
            title = f"{config.method} + {config.algorithm.name}, seeds {curve_seeds.start}..{curve_seeds.stop - 1}"
            plot_learning_curve(curve, config.out / "learning_curve.png", title)
        save_checkpoint_dir(checkpoint, rotation, agent.num_timesteps,
                            {"step": agent.num_timesteps, "env_steps": env.env_steps,
                             "train_seconds": trained_seconds()})
    trained_s = trained_seconds()
    save_checkpoint({"config": config_json(config), "state_dict": agent.policy.state_dict(),
                     "policy": policy_entries(policy)}, config.out / RL_AGENT_FILE, RL_AGENT_KIND)

    # The base policy and the fine-tuned one on the same held-out seeds; when steering, also the base policy with
    # the centre of its noise (the RL action 0), which a deterministic steering agent starts from.
    seeds = range(config.eval_seed, config.eval_seed + config.eval_episodes)
    actors: dict[str, TensorDictModuleBase | None] = {"base": None}
    if isinstance(config, SteerConfig):
        centre = np.zeros(env.action_space.shape, np.float32)
        actors["centre"] = env.closed_loop_actor(lambda obs: centre)
    actors["fine_tuned"] = env.closed_loop_actor(deterministic(agent))
    env.close()
    names = {"base": BASE_ROW, "centre": f"{BASE_ROW}, noise at its centre",
             "fine_tuned": f"fine-tuned ({config.method}, {config.algorithm.name})"}
    rows = {}
    for key, actor in actors.items():
        rows[names[key]] = episodes = run(seeds, actor)
        agent.logger.record(f"eval/success_rate_{key}", summary_row(key, episodes)["success_rate"])
    agent.logger.dump(agent.num_timesteps)
    return rows, trained_s


class DivergenceCheck(BaseCallback):
    """Stop RL training once an update leaves the agent's weights non-finite, before they act (the next rollout)
    or are saved (the sitting's checkpoint), as imitation training stops at a non-finite loss
    (:func:`~dust_rl.train.imitation.diverged`); without it the NaN action ends in a traceback from the env."""

    def __init__(self, checkpoints: CheckpointRotation) -> None:
        super().__init__()
        self.checkpoints = checkpoints

    def _on_step(self) -> bool:
        return True

    def _on_rollout_start(self) -> None:
        self._check()

    def _on_training_end(self) -> None:
        self._check()

    def _check(self) -> None:
        if bad := non_finite(self.model.policy.state_dict()):
            raise diverged(self.model.num_timesteps, f"NaN or infinity in the RL agent's weights {bad[:4]}",
                           RL_AGENT_FILE, self.checkpoints, "lower --lr or check the rewards for non-finite values")


def build_agent(config: RLConfig, env: FineTuningEnv) -> BaseAlgorithm:
    """The SB3 agent ``config`` asks for, on ``env`` (the same settings rebuild it to resume)."""
    settings = config.algorithm
    algorithm = ALGORITHMS[settings.name]
    kwargs: dict = {"gamma": config.gamma, "learning_rate": config.lr}
    target_entropy = None
    steer = isinstance(config, SteerConfig)
    if isinstance(settings, SacSettings):  # a replay buffer no larger than the run
        target_entropy = settings.target_entropy
        kwargs |= {"learning_starts": settings.learning_starts, "batch_size": config.batch_size,
                   "buffer_size": config.steps, "gradient_steps": settings.updates_per_step}
        if config.initial_std is not None and target_entropy is None:
            kwargs["ent_coef"] = 0.0  # the std is fixed: an entropy bonus would only swamp the reward (start_at_base)
        else:
            kwargs["ent_coef"] = f"auto_{settings.initial_alpha}"
            if target_entropy is not None:
                kwargs["target_entropy"] = target_entropy
        if config.initial_std is not None:
            algorithm = WarmStartSAC
        elif steer and config.collection.base_warmup:
            algorithm = BaseWarmupSAC
    else:  # a rollout no longer than the run (n_steps of all envs together), minibatches no larger than a rollout
        n_steps = min(settings.n_steps, config.steps)
        kwargs |= {"n_steps": n_steps // (config.collection.envs if steer else 1),
                   "batch_size": min(config.batch_size, n_steps), "n_epochs": settings.n_epochs}
    policy_class, policy_kwargs = policy_network(config)
    agent = algorithm(policy_class, env, seed=config.seed, device=resolve_device(config.runtime.device),
                      policy_kwargs=policy_kwargs, **kwargs)
    if isinstance(agent, BaseWarmupSAC):
        agent.noise_bound = config.noise_bound
    if config.initial_std is not None:
        start_at_base(agent, config.initial_std, learn_std=target_entropy is not None)
    return agent


def policy_network(config: RLConfig) -> tuple[type[BasePolicy], dict]:
    """The SB3 policy class of ``config``'s agent and its keyword arguments (the agent's networks; the file of a
    fine-tuned agent rebuilds them without the agent, :mod:`dust_rl.rl.fine_tuned_policy`)."""
    privileged = isinstance(config, SteerConfig) and config.observation.privileged_critic
    policy_class = (AsymmetricSACPolicy if privileged
                    else ALGORITHMS[config.algorithm.name].policy_aliases["MultiInputPolicy"])
    kwargs = {"net_arch": list(config.net_arch)}
    if config.layer_norm:
        kwargs["activation_fn"] = LayerNormReLU
    return policy_class, kwargs


def finetune_command(command_config: FinetuneCommand, command: str | None = None) -> dict:
    """``dust-rl finetune METHOD``: fine-tune, print the comparison, say where the files are."""
    config = command_config.method
    report = finetune(config, command)
    for row in report["rows"]:
        print(f"{row['task']}: {row['successes']}/{row['episodes']} successful ({100 * row['success_rate']:.0f}%, "
              f"95% CI {100 * row['ci95_low']:.0f}-{100 * row['ci95_high']:.0f}%)")
    print(f"{'policy' if 'policy_file' in report else 'RL agent'}: "
          f"{report.get('policy_file', report.get('rl_agent'))}\nreport: {config.out / 'report.md'}")
    return report


def policy_env(config: FinetuneConfig, policy: DustPolicy) -> tuple[str, dict, str]:
    """The env id, env kwargs (the policy's, with ``max_steps``) and task to fine-tune on, checked."""
    env_id = policy.info.get("env_id")
    if env_id is None:
        raise ConfigError(f"{config.policy}: the policy does not name the env it was trained in (info['env_id'])")
    task = config.task or (policy.info.get("tasks") or [None])[0]
    if task is None:
        raise ConfigError(f"{config.policy}: no training task recorded; pass --task")
    env_kwargs = {k: v for k, v in policy.info.get("env_kwargs", {}).items() if k != "task"}
    if config.max_steps:
        env_kwargs["max_episode_steps"] = config.max_steps
    check_tasks(env_id, env_kwargs, [task])
    return env_id, env_kwargs, task


def finetune_env_factory(config: RLConfig, policy: DustPolicy) -> tuple[Callable[[], FineTuningEnv], str]:
    """A factory of fresh fine-tuning envs for ``config``'s task (checked once, here), and the task: a steering or
    residual env, or with ``--envs N`` (N > 1) N steering envs stepped together (:mod:`dust_rl.rl.vector`)."""
    env_id, env_kwargs, task = policy_env(config, policy)
    steer = isinstance(config, SteerConfig)
    step_discount = config.gamma ** (1 / policy.execute_steps) if steer else config.gamma
    penalty = config.reward == "penalty"
    env_kwargs = {**env_kwargs, "task": task, "reward_type": "sparse" if penalty else config.reward,
                  "shaping_discount": step_discount}
    if steer:
        try:
            latent_map(config.latent.latent_dim, (policy.config.horizon, policy.config.action_dim))
        except ValueError as err:
            raise ConfigError(f"--latent-dim: {err}") from err

    def make_steering() -> NoiseSteeringEnv:
        return NoiseSteeringEnv(make_env(env_id, env_kwargs), policy, noise_bound=config.noise_bound,
                                step_discount=step_discount, finite_horizon=config.finite_horizon,
                                latent_dim=config.latent.latent_dim, instruction=config.observation.instruction,
                                object_state=config.observation.privileged_critic, reward_penalty=penalty)

    def make() -> FineTuningEnv:
        if steer:
            envs = config.collection.envs
            return make_steering() if envs == 1 else SB3SteeringVecEnv([make_steering() for _ in range(envs)])
        env = make_env(env_id, env_kwargs)
        half_width = (env.action_space.high - env.action_space.low) / 2
        return ResidualEnv(env, policy, residual_scale=config.residual_scale * half_width,
                           world_model=config.world_model_obs, finite_horizon=config.finite_horizon,
                           reward_penalty=penalty)

    return make, task


def deterministic(agent: BaseAlgorithm | BasePolicy) -> Act:
    """The RL agent's (or its policy network's) deterministic action for an observation."""
    return lambda obs: agent.predict(obs, deterministic=True)[0]


def _read_curve(path: pathlib.Path) -> list[dict]:
    """The learning curve written so far (a resumed run continues it); empty for a new run."""
    return json.loads(path.read_text()) if path.is_file() else []


def _versus_base(row: dict) -> str:
    paired = row.get("vs_base")
    return "" if paired is None else f"+{paired['gained']} / -{paired['lost']} (p = {paired['p_value']:.2f})"


def _markdown(report: dict) -> str:
    if report["method"] == "self_imitation":
        config = as_this_version(report["config"])
        taught = ("and the failures between them, taught the expert"
                  if is_dagger(config["train"]["data"]["extra_action_key"])
                  else "taught their actions")
        how = (f"{config['rounds']} round(s) of {config['rollout_successes']} successful rollouts {taught} "
               f"({', '.join(str(r['rollouts']) for r in report['rounds'])} episodes; {report['rollout_env_steps']} "
               f"env steps), each followed by {config['train']['optim']['steps']} fine-tuning steps "
               f"({report['train_seconds']:.0f} s in all)"
               + ("; the control: as many steps on the demonstrations alone" if config.get("control") else ""))
    else:
        how = (f"{report['algorithm']}, {report['steps']} RL steps ({report['train_seconds']:.0f} s), "
               f"{report['config']['reward']} reward")
    lines = [f"# RL fine-tuning: {report['policy']}", "",
             f"- task `{report['task']}`, method `{report['method']}`: {how}",
             f"- seeds {report['seeds'][0]}..{report['seeds'][1]}; the imitation policy "
             f"{'is fine-tuned' if report['method'] == 'self_imitation' else 'stays frozen'}", "",
             "| policy | episodes | success | 95% CI | episodes won / lost against the base (McNemar p) |",
             "|---|---|---|---|---|"]
    lines += [f"| {row['task']} | {row['episodes']} | {100 * row['success_rate']:.0f}% | "
              f"{100 * row['ci95_low']:.0f}-{100 * row['ci95_high']:.0f}% | {_versus_base(row)} |"
              for row in report["rows"]]
    lines += ["", "Reproduce:", "", f"    {report['command']}", ""]
    return "\n".join(lines)
