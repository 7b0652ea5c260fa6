"""A fine-tuned RL agent as one file that ``dust-rl eval`` runs: ``rl_agent.pt``.

``dust-rl finetune steer|residual`` writes ``rl_agent.pt``: the run's config, the SB3 policy's weights (actor and
critics) and the frozen base policy itself (the entries of its own file,
:func:`~dust_rl.agents.factory.policy_entries`). The file alone rebuilds the closed-loop actor: the base policy, one
fine-tuning env of the run's settings (for its spaces and its actor's view of an observation, then closed), and the
SB3 policy network on those spaces (not the agent: SAC's replay buffer is sized by the run). It is read with
``weights_only=True``; the run's paths recorded in it (the base policy's file, the run folder) are never opened.

``dust-rl eval --policy <run>/rl_agent.pt`` evaluates the agent as it evaluates an imitation policy, on the
fine-tuning task and time limit unless ``--tasks`` (and, for an agent that does not observe the time left,
``--max-steps``) say otherwise, in one local worker (the actor lives in the evaluating process): its episodes are the
fine-tuning report's fine-tuned row's, seed for seed, on the device it was trained on (tested). What the agent was
trained with stays: ``--execute-steps``, ``resample``, ``--backend ray`` and, under ``--finite-horizon``, another
``--max-steps`` are refused.
"""

from __future__ import annotations

import dataclasses
import pathlib
from typing import NamedTuple

from tensordict.nn import TensorDictModuleBase

from dust_rl.agents import DustPolicy
from dust_rl.agents.factory import policy_from_entries
from dust_rl.errors import CheckpointError, ConfigError, one_line
from dust_rl.evaluate.closed_loop import NOISE_SEEDING, EvalConfig, evaluate_command
from dust_rl.rl.config import RL_AGENT_KIND, RLConfig, SteerConfig, rl_config_from_json
from dust_rl.rl.finetune import deterministic, finetune_env_factory, policy_network
from dust_rl.runtime.device import resolve_device
from dust_rl.storage.checkpoint_files import check_tensor_values, load_checkpoint

STEERED_NOISE = "the RL agent picks each plan's initial action noise (a vision stream starts from one fixed draw)"


class PolicyWithActor(NamedTuple):
    """The base policy with the agent's closed-loop actor built around it in this process, and what the report
    records of the agent (its ``noise_seeding``: how the actor's plans draw their noise)."""

    policy: DustPolicy
    actor: TensorDictModuleBase
    about: dict


def load_fine_tuned(path: pathlib.Path, device: str = "auto") -> tuple[RLConfig, PolicyWithActor]:
    """The fine-tuning config and the closed-loop actor (with its base policy, on ``device``) of an ``rl_agent.pt``;
    ``about`` names the fine-tuning task.

    Raises:
        CheckpointError: a missing, corrupt or foreign file, one written before it held its base policy, or
            settings or weights that do not rebuild the agent.
    """
    payload = load_checkpoint(path, RL_AGENT_KIND)
    if "policy" not in payload:
        raise CheckpointError(f"{path}: written before an RL agent's file held its base policy; run `dust-rl finetune "
                              "... --resume` in its run folder to write it again")
    try:
        config = rl_config_from_json(payload["config"], device=device)
    except (KeyError, TypeError, ValueError, ConfigError) as err:
        raise CheckpointError(f"{path}: the fine-tuning settings do not read back ({one_line(err)})") from err
    if isinstance(config, SteerConfig):  # one env builds the actor; the run's vector of them only sped training
        config = dataclasses.replace(config, collection=dataclasses.replace(config.collection, envs=1))
    where = resolve_device(device)
    policy = policy_from_entries(payload["policy"], path).to(where)
    try:
        make, task = finetune_env_factory(config, policy)
        env = make()
    except ConfigError as err:
        raise CheckpointError(f"{path}: the fine-tuning env does not rebuild ({one_line(err)})") from err
    try:
        policy_class, kwargs = policy_network(config)
        network = policy_class(env.observation_space, env.action_space, lambda _: config.lr, **kwargs)
        check_tensor_values(payload["state_dict"], network.state_dict())
        network.load_state_dict(payload["state_dict"])
        network.to(where).set_training_mode(False)
        actor = env.closed_loop_actor(deterministic(network))
    except (KeyError, TypeError, ValueError, RuntimeError) as err:
        raise CheckpointError(f"{path}: the RL agent does not load ({one_line(err)})") from err
    finally:
        env.close()
    noise = (STEERED_NOISE if isinstance(config, SteerConfig)
             else f"{NOISE_SEEDING}; the RL agent adds its correction to every action")
    about = {"method": config.method, "algorithm": config.algorithm.name, "steps": config.steps, "task": task,
             "parameters": sum(p.numel() for p in network.parameters()), "noise_seeding": noise}
    return config, PolicyWithActor(policy, actor, about)


def evaluate_agent_command(config: EvalConfig, command: str | None = None) -> dict:
    """``dust-rl eval`` of a fine-tuned RL agent's ``rl_agent.pt``: through its actor (module doc), as
    :func:`~dust_rl.evaluate.closed_loop.evaluate_command` runs a policy file.

    Raises:
        ConfigError: a setting the agent was not trained with (module doc).
    """
    refused = [flag for flag, given in (("--execute-steps", config.execute_steps is not None),
                                        ("resample", config.sampling is not None),
                                        ("--backend ray", config.backend != "local")) if given]
    if refused:
        raise ConfigError(f"{config.policy} is a fine-tuned RL agent: it runs as it was trained, in this process; "
                          f"drop {', '.join(refused)}")
    fine_tuning, agent = load_fine_tuned(config.policy, config.runtime.device)
    if fine_tuning.finite_horizon and config.max_steps not in (None, fine_tuning.max_steps):
        raise ConfigError(f"{config.policy}: the agent observes the time left of its {fine_tuning.max_steps}-step "
                          "episodes (--finite-horizon); drop --max-steps")
    config = dataclasses.replace(config, tasks=config.tasks or (agent.about["task"],),
                                 max_steps=config.max_steps or fine_tuning.max_steps, workers=1)
    return evaluate_command(config, command, agent.policy, agent.actor,
                            {"rl_agent": agent.about, "noise_seeding": agent.about["noise_seeding"]})
