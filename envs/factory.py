"""Registered envs built from ``(env_id, env_kwargs)``, as datasets and policy files record them.

``gym.make(env_id, max_episode_steps=N, **kwargs)`` keeps ``max_episode_steps`` for its own
``TimeLimit`` wrapper and never passes it to the env, whose own time limit (the task's
default) then ends the episode first. :func:`make_env` passes every recorded kwarg to
the env constructor, so a stored ``max_episode_steps`` is the limit actually used.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import gymnasium as gym

from dust_rl.envs import list_tasks, make_task
from dust_rl.envs.registration import ENV_IDS
from dust_rl.errors import ConfigError


def env_spec_of(env_id: str) -> gym.envs.registration.EnvSpec:
    """The registered spec of ``env_id``; raises :class:`ConfigError` for an id dust-rl does not register (another
    gymnasium env has none of the tasks, cameras and metadata datasets and policies record)."""
    if env_id not in ENV_IDS:
        raise ConfigError(f"unknown env id {env_id!r}; dust-rl registers {list(ENV_IDS)}")
    try:
        return gym.spec(env_id)
    except gym.error.Error as err:
        raise ConfigError(f"unknown env id {env_id!r} ({err}); dust-rl registers {list(ENV_IDS)}") from err


DEFAULT_ENV_ID = "DustFranka-v0"


def robot_of(env_id: str, env_kwargs: dict | None = None) -> str:
    """The robot whose suite an env runs: it follows from the env id (or an explicit ``robot`` kwarg)."""
    return {**env_spec_of(env_id).kwargs, **(env_kwargs or {})}.get("robot", "franka")


def env_tasks(env_id: str, task: str) -> list[str]:
    """A command's ``--task``: ``all`` (the suite of the env's robot), one name or comma-separated names,
    each checked (:class:`ConfigError` listing the suite otherwise)."""
    tasks = list_tasks(robot_of(env_id)) if task == "all" else [name.strip() for name in task.split(",")]
    check_tasks(env_id, {}, tasks)
    return tasks


def make_env(env_id: str, env_kwargs: dict) -> gym.Env:
    """``gym.make(env_id)`` with every entry of ``env_kwargs`` passed to the env constructor.

    Raises:
        ConfigError: unknown env id, or kwargs the env refuses (its message names the argument).
    """
    spec = env_spec_of(env_id)
    try:
        return gym.make(dataclasses.replace(spec, kwargs={**spec.kwargs, **env_kwargs}))
    except (ValueError, TypeError) as err:  # the env's documented answer to a bad argument
        raise ConfigError(f"{env_id} with {env_kwargs}: {err}") from err


def check_tasks(env_id: str, env_kwargs: dict, tasks: Sequence[str]) -> None:
    """Raise :class:`ConfigError` (listing the suite) unless every task exists, once, without building envs (a task
    named twice would count its seeds twice in every pooled rate and interval)."""
    if not tasks:
        raise ConfigError("no tasks given")
    if repeated := sorted({task for task in tasks if list(tasks).count(task) > 1}):
        raise ConfigError(f"task(s) {', '.join(repeated)} given more than once; name each task once")
    robot = robot_of(env_id, env_kwargs)
    for task in tasks:
        try:
            make_task(task, robot)
        except ValueError as err:
            raise ConfigError(str(err)) from err
