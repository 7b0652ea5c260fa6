"""stable-baselines3 from scratch on the state-mode env: the reference rows of the RL fine-tuning table.

Why: fine-tuning an imitation policy is worth its machinery only against what plain RL reaches in the same
env steps without one. The reference is generous to RL: the state mode (``obs_mode="state"``) hands the agent
the robot state and the objects' true state (``environment_state``, the named object first), no images, and
the task's staged dense reward (potential-based) by default. Success is counted as ``dust-rl finetune`` counts
it: the agent's deterministic action, the env's ``is_success``, on held-out seeds from 10,000 (validation seeds
from 5,000 for the learning curve). Not resumable: a run is minutes to an hour; rerun it whole.

    python -m dust_rl.bench.sb3_scratch --task press_button --algorithm sac --steps 100000 \
        --eval-every 20000 --out runs/bench/sb3_scratch/press_button_sac
"""

from __future__ import annotations

import argparse
import pathlib
import time
from collections.abc import Callable

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3 import PPO, SAC
from stable_baselines3.common.base_class import BaseAlgorithm

from dust_rl.data.seeding import HELDOUT_SEED, VALIDATION_SEED
from dust_rl.envs.env import FLAT_STATE_KEY, STATE_MODE_KEYS
from dust_rl.envs.factory import check_tasks, make_env
from dust_rl.errors import ConfigError
from dust_rl.evaluate.closed_loop import summary_row
from dust_rl.evaluate.records import Episode
from dust_rl.evaluate.report import plot_learning_curve
from dust_rl.runtime.episode_collector import torch_threads
from dust_rl.storage.atomic_files import write_json_atomic

ALGORITHMS: dict[str, type[BaseAlgorithm]] = {"sac": SAC, "ppo": PPO}


def state_env_factory(env_id: str, task: str, reward: str) -> Callable[[], gym.Env]:
    """Fresh state-mode envs of ``task`` (checked once, here: an unknown task raises ``ConfigError``)."""
    kwargs = {"obs_mode": "state", "reward_type": reward}
    check_tasks(env_id, kwargs, [task])
    return lambda: make_env(env_id, {**kwargs, "task": task})


def run_episodes(agent: BaseAlgorithm, make: Callable[[], gym.Env], seeds: range) -> list[Episode]:
    """The agent's deterministic episodes on ``seeds`` (equal digests: the same episode)."""
    env, episodes = make(), []
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        actions, done, info = [], False, {}
        while not done:
            action = agent.predict(obs, deterministic=True)[0]
            actions.append(action)
            obs, _, terminated, truncated, info = env.step(action)
            done = terminated or truncated
        episodes.append(Episode.of(seed, info.get("is_success", False), torch.from_numpy(np.stack(actions)),
                                   torch.from_numpy(obs[STATE_MODE_KEYS[FLAT_STATE_KEY]])))
    env.close()
    return episodes


def train_from_scratch(task: str, algorithm: str, steps: int, out: pathlib.Path, *, env_id: str = "DustFranka-v0",
                       reward: str = "dense", eval_every: int = 0, curve_episodes: int = 10, episodes: int = 50,
                       seed: int = 0, threads: int = 1, progress: bool = True) -> dict:
    """Train an SB3 agent on ``task`` from scratch for ``steps`` env steps and evaluate it on held-out seeds;
    writes ``out/results.json`` (and ``learning_curve.png`` with ``eval_every``) and returns the results.

    Raises:
        ConfigError: an unknown algorithm or task, or a non-positive count.
    """
    if algorithm not in ALGORITHMS:
        raise ConfigError(f"unknown algorithm {algorithm!r}; choose one of {sorted(ALGORITHMS)}")
    if min(steps, episodes, curve_episodes, threads) < 1 or eval_every < 0:
        raise ConfigError(f"steps, episodes, curve_episodes and threads must be >= 1 and eval_every >= 0, got "
                          f"{steps}, {episodes}, {curve_episodes}, {threads}, {eval_every}")
    make = state_env_factory(env_id, task, reward)
    out.mkdir(parents=True, exist_ok=True)
    with torch_threads(threads):
        env = make()
        kwargs = {"buffer_size": steps} if algorithm == "sac" else {"n_steps": min(2048, steps)}
        agent = ALGORITHMS[algorithm]("MultiInputPolicy", env, seed=seed, device="cpu", **kwargs)
        began, curve, interval = time.perf_counter(), [], eval_every or steps
        while agent.num_timesteps < steps:  # PPO rounds each call up to whole rollouts
            agent.learn(min(interval, steps - agent.num_timesteps), reset_num_timesteps=False, progress_bar=progress)
            if eval_every:
                points = run_episodes(agent, make, range(VALIDATION_SEED, VALIDATION_SEED + curve_episodes))
                curve.append({"env_steps": agent.num_timesteps, **summary_row("validation", points)})
                plot_learning_curve(curve, out / "learning_curve.png",
                                    f"{algorithm} from scratch, {task}, state, {reward} reward")
        trained_s = time.perf_counter() - began
        env.close()
        heldout = run_episodes(agent, make, range(HELDOUT_SEED, HELDOUT_SEED + episodes))
    results = {"task": task, "algorithm": algorithm, "reward": reward, "env_steps": agent.num_timesteps,
               "train_seconds": trained_s, "seed": seed, "curve": curve,
               "heldout": {**summary_row(f"{algorithm} from scratch", heldout),
                           "per_episode": [e.to_json() for e in heldout]}}
    write_json_atomic(out / "results.json", results, indent=2)
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="press_button")
    parser.add_argument("--env", default="DustFranka-v0")
    parser.add_argument("--algorithm", default="sac", choices=sorted(ALGORITHMS))
    parser.add_argument("--steps", type=int, default=100_000, help="env steps of training")
    parser.add_argument("--reward", default="dense", choices=("dense", "sparse"))
    parser.add_argument("--eval-every", type=int, default=0, help="env steps between validation evaluations")
    parser.add_argument("--curve-episodes", type=int, default=10)
    parser.add_argument("--episodes", type=int, default=50, help="held-out episodes (seeds 10000 on)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--no-progress", dest="progress", action="store_false")
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("runs/bench/sb3_scratch"))
    args = parser.parse_args()
    try:
        results = train_from_scratch(args.task, args.algorithm, args.steps, args.out, env_id=args.env,
                                     reward=args.reward, eval_every=args.eval_every,
                                     curve_episodes=args.curve_episodes, episodes=args.episodes, seed=args.seed,
                                     threads=args.threads, progress=args.progress)
    except ConfigError as err:
        raise SystemExit(f"sb3_scratch: error: {err}") from err
    row = results["heldout"]
    print("| task | agent | reward | env steps | held-out success | 95% CI | train time |")
    print("|---|---|---|---|---|---|---|")
    print(f"| {args.task} | {args.algorithm} from scratch (state) | {args.reward} | {results['env_steps']} | "
          f"{100 * row['success_rate']:.0f}% ({row['successes']}/{row['episodes']}) | "
          f"{100 * row['ci95_low']:.0f}-{100 * row['ci95_high']:.0f}% | {results['train_seconds']:.0f} s |")


if __name__ == "__main__":
    main()
