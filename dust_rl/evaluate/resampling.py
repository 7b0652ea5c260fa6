"""How a command that runs a trained policy picks its sampler: as the file says, or ``resample`` with other settings.

``dust-rl eval`` and ``dust-rl diagnose world-model`` take the same choice, so a sampler measured in closed loop
(e.g. N_o = 16 vision steps) is the one the diagnosis scores open loop.
"""

from __future__ import annotations

import dataclasses
import pathlib
from typing import Annotated

import tyro

from dust_rl.agents import DustPolicy, SamplerConfig
from dust_rl.errors import ConfigError
from dust_rl.storage.config_json import config_json

Resampling = (Annotated[SamplerConfig, tyro.conf.subcommand("resample")]
              | Annotated[None, tyro.conf.subcommand("as-saved")])


def apply_sampling(policy: DustPolicy, sampling: SamplerConfig | None, source: pathlib.Path) -> None:
    """Set ``sampling`` on ``policy`` (loaded from ``source``); None keeps the file's.

    Raises:
        ConfigError: the sampler does not apply to the policy's variant (e.g. async sampling of one shared timestep).
    """
    if sampling is None:
        return
    try:
        policy.set_sampler(sampling)
    except ValueError as err:
        raise ConfigError(f"{source}: sampling {config_json(sampling)} does not apply: {err}") from err


def resolved_sampler(policy: DustPolicy) -> SamplerConfig:
    """The policy's sampler settings with its name set (None in a file means the variant's natural sampler)."""
    return dataclasses.replace(policy.config.sampler_settings, sampler=policy.config.sampler_name)


def describe_sampler(sampler: SamplerConfig) -> dict:
    """Name, N_A, N_o (vision Euler steps: q * N_A async, N_A sync, none action-only) and the initial noise's scale
    of a resolved sampler (:func:`resolved_sampler`)."""
    vision = {"async": sampler.n_action_steps * sampler.vision_step_ratio, "sync": sampler.n_action_steps}
    return {"name": sampler.sampler, "n_action_steps": sampler.n_action_steps,
            "vision_steps": vision.get(sampler.sampler, 0), "noise_scale": sampler.noise_scale}
