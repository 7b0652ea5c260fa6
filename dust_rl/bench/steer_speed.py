"""Noise-steering speed: env steps/s and SAC updates/s with 1 and N steering envs stepped together.

Each row builds the fine-tuning envs as ``dust-rl finetune steer --envs N`` does (the policy's task, its
time limit or ``--max-steps``), always as :class:`~dust_rl.rl.vector.SB3SteeringVecEnv` (N = 1 included, so every
row times the same path), and an SB3 SAC agent as the run would (``--net-arch``, ``--layer-norm``,
``--batch-size``). After one untimed RL step (the resets, the agent's setup), it times ``rl_steps`` RL steps of
collection (``agent.learn`` with the warm-up covering them, so no update runs: the envs, the policy's plan and
encoders, the agent's action and the replay buffer) and ``updates`` SAC updates on the transitions collected
(``agent.train``). Env steps count the executed actions of every env (``execute_steps`` per RL step until an
episode ends).

    dust-rl bench steer-speed --policy runs/train/policy.pt [--envs 1 4] [--rl-steps 64] [--updates 200]
"""

from __future__ import annotations

import pathlib
import time
from dataclasses import dataclass, replace

from stable_baselines3.common.logger import configure

from dust_rl.agents import load_policy
from dust_rl.errors import ConfigError, check_at_least
from dust_rl.rl.config import LatentSettings, SacSettings, SteerConfig, SteeringCollection
from dust_rl.rl.finetune import build_agent, finetune_env_factory
from dust_rl.rl.vector import SB3SteeringVecEnv
from dust_rl.runtime.device import resolve_device
from dust_rl.runtime.episode_collector import torch_threads
from dust_rl.runtime.settings import RuntimeSettings, runtime_field


@dataclass
class SteerSpeedConfig:
    """Time noise steering's collection and SAC updates with 1 and N envs (`dust-rl bench steer-speed`)."""

    policy: pathlib.Path
    """Policy file written by `dust-rl train`."""
    task: str | None = None
    """Task; default: the policy's first training task."""
    max_steps: int | None = None
    """Time limit per episode in env steps; default: the task's."""
    envs: tuple[int, ...] = (1, 4)
    """Env counts to time, one row each."""
    rl_steps: int = 64
    """RL steps (chunks) of collection timed per row, of all envs together (rounded up to a multiple of the
    envs)."""
    updates: int = 200
    """SAC updates timed per row."""
    batch_size: int = 256
    """SAC's minibatch size."""
    net_arch: tuple[int, ...] = (256, 256)
    """Hidden layers of the actor and critic."""
    layer_norm: bool = False
    """Hidden layers normalised before their ReLU."""
    latent_dim: int | None = None
    """The RL action's size (`--latent-dim`); default: the whole noise."""
    runtime: RuntimeSettings = runtime_field(threads=1)
    """Where the policy and the agent run, torch threads, the policy's precision (`--runtime.*`)."""
    seed: int = 0
    """Seed of the agent and the first episodes."""

    def __post_init__(self) -> None:
        check_at_least(self, 1, "rl_steps", "updates", "batch_size", "max_steps")
        if not self.envs or min(self.envs) < 1:
            raise ConfigError(f"envs must list positive env counts, got {self.envs}")


def steer_speed(config: SteerSpeedConfig) -> list[dict]:
    """One row per env count: RL steps/s and env steps/s of collection, SAC updates/s."""
    rows = []
    with torch_threads(config.runtime.thread_count):
        policy = load_policy(config.policy).to(resolve_device(config.runtime.device))
        policy.set_runtime(config.runtime.precision, config.runtime.compile)
        for envs in config.envs:
            steps = -(-config.rl_steps // envs) * envs
            steer = SteerConfig(policy=config.policy, task=config.task, max_steps=config.max_steps, seed=config.seed,
                                steps=steps + envs, checkpoint_every=steps + envs, batch_size=config.batch_size,
                                net_arch=config.net_arch, layer_norm=config.layer_norm,
                                runtime=replace(config.runtime, progress=False),
                                latent=LatentSettings(config.latent_dim),
                                collection=SteeringCollection(envs=envs),
                                algorithm=SacSettings(learning_starts=steps + envs))
            made = finetune_env_factory(steer, policy)[0]()
            env = made if isinstance(made, SB3SteeringVecEnv) else SB3SteeringVecEnv([made])
            agent = build_agent(steer, env)
            agent.set_logger(configure(None, []))
            agent.learn(total_timesteps=envs)  # the resets and the agent's setup, untimed
            before = env.env_steps
            began = time.perf_counter()
            agent.learn(total_timesteps=steps, reset_num_timesteps=False)
            collected = time.perf_counter() - began
            env_steps = env.env_steps - before
            began = time.perf_counter()
            agent.train(gradient_steps=config.updates, batch_size=config.batch_size)
            updated = time.perf_counter() - began
            env.close()
            rows.append({"envs": envs, "rl_steps": steps, "env_steps": env_steps,
                         "rl_steps_per_s": steps / collected, "env_steps_per_s": env_steps / collected,
                         "updates": config.updates, "updates_per_s": config.updates / updated})
    return rows


def table(rows: list[dict]) -> str:
    """The rows as a markdown table."""
    lines = ["| envs | RL steps | env steps/s | RL steps/s | SAC updates/s |", "|---|---|---|---|---|"]
    lines += [f"| {r['envs']} | {r['rl_steps']} | {r['env_steps_per_s']:.1f} | {r['rl_steps_per_s']:.2f} | "
              f"{r['updates_per_s']:.1f} |" for r in rows]
    return "\n".join(lines)


def steer_speed_command(config: SteerSpeedConfig, command: str | None = None) -> list[dict]:
    """``dust-rl bench steer-speed``: time and print the table."""
    rows = steer_speed(config)
    print(table(rows))
    return rows
