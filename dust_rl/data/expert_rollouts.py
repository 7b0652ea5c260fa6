"""Scripted-expert rollouts: success tables and demo videos.

The experts are the environment's own (``DustEnv.make_expert``); this
module only runs them, so the same code measures the per-task success
table and produces the demo video.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from tqdm import tqdm

from dust_rl.envs import DustEnv
from dust_rl.envs.factory import check_tasks, make_env
from dust_rl.errors import ConfigError

from .episodes import EpisodeRecord


def run_expert_episode(env: DustEnv, seed: int, with_frames: bool = False) -> tuple[EpisodeRecord, list[np.ndarray]]:
    """One episode of the task's scripted expert from ``reset(seed=seed)``: its record (not stored in a dataset) and,
    with ``with_frames``, every camera strip (:func:`camera_strip`) from the reset on."""
    obs, info = env.reset(seed=seed)
    expert = env.make_expert()
    frames = [camera_strip(obs)] if with_frames else []
    for step in range(1, env.max_episode_steps + 1):  # noqa: B007 (the count is read after the loop)
        obs, _, terminated, truncated, info = env.step(expert.act())
        if with_frames:
            frames.append(camera_strip(obs))
        if terminated or truncated:
            break
    return EpisodeRecord(env.task.name, seed, bool(info["is_success"]), step, info["language_instruction"],
                         kept=False), frames


def camera_strip(obs: dict) -> np.ndarray:
    """All camera images of an observation side by side."""
    return np.concatenate([v for k, v in obs.items() if k.startswith("observation.image.")], axis=1)


def expert_success_table(env_id: str, tasks: Iterable[str], seeds: int) -> list[dict]:
    """Per-task expert success over seeds ``0..seeds-1`` (state mode: no rendering needed).

    Raises:
        ConfigError: ``seeds < 1``, an unknown env id or task.
    """
    if seeds < 1:
        raise ConfigError(f"seeds must be >= 1, got {seeds}")
    tasks = list(tasks)
    check_tasks(env_id, {}, tasks)
    rows = []
    for task in tasks:
        env = make_env(env_id, {"task": task, "obs_mode": "state"}).unwrapped
        results = [run_expert_episode(env, seed)[0] for seed in tqdm(range(seeds), desc=task, leave=False)]
        env.close()
        successes = [r.success for r in results]
        rows.append({"task": task, "category": env.task.category, "episodes": seeds,
                     "success_rate": float(np.mean(successes)),
                     "mean_length": float(np.mean([r.length for r in results])),
                     "failed_seeds": [r.seed for r in results if not r.success]})
    return rows


def format_table(rows: list[dict]) -> str:
    """Markdown table of :func:`expert_success_table` rows."""
    lines = ["| task | category | episodes | expert success | mean length (steps) |",
             "|---|---|---|---|---|"]
    lines += [f"| {r['task']} | {r['category']} | {r['episodes']} | {100 * r['success_rate']:.0f}% | "
              f"{r['mean_length']:.0f} |" for r in rows]
    return "\n".join(lines)
