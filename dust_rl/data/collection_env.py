"""The env a demonstration collector steps: DustEnv + expert + seeds, with torchrl's VLA keys.

Built inside each collector worker from a picklable constructor, so the scripted
expert and the seed schedule live next to the simulator they read.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

from torchrl.envs import InitTracker, StepCounter, TransformedEnv

from dust_rl.envs.expert_wrapper import Expert, ExpertActionWrapper, scripted_expert
from dust_rl.envs.factory import make_env
from dust_rl.envs.torchrl_env import make_torchrl_env

from .seeding import EpisodeSeedWrapper, SeedSchedule


def make_collection_env(env_id: str, env_kwargs: dict, schedule: SeedSchedule,
                        make_expert: Callable[..., Expert] = scripted_expert) -> TransformedEnv:
    """A torchrl env of ``env_id`` with ``expert_action``, ``episode_seed``, ``is_success``, ``step_count`` and
    ``is_init`` (a trained policy's chunk executor restarts at every reset; not stored).

    Observations use the canonical VLA keys (``("observation", "image", cam)`` uint8 ``[C, H, W]``,
    ``("observation", "state")``, ``language_instruction``), like ``make_torchrl_env``. ``make_expert`` builds
    the expert whose actions ``expert_action`` holds (:class:`ExpertActionWrapper`).
    """
    env = make_torchrl_env(EpisodeSeedWrapper(ExpertActionWrapper(make_env(env_id, env_kwargs), make_expert),
                                              schedule))
    env.append_transform(StepCounter())
    env.append_transform(InitTracker())
    return env


def collection_env_fns(env_id: str, env_kwargs: dict, start_seed: int, known_seeds: frozenset[int],
                       num_workers: int, make_expert: Callable[..., Expert] = scripted_expert,
                       ) -> list[Callable[[], TransformedEnv]]:
    """One env constructor per worker, each with its share of the unknown seeds."""
    return [functools.partial(make_collection_env, env_id, env_kwargs,
                              SeedSchedule(start_seed, known_seeds, worker, num_workers), make_expert)
            for worker in range(num_workers)]
