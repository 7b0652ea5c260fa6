"""SAC from torchrl's own parts on the fine-tuning envs: the same training for users of torchrl rather than SB3.

The steering and residual envs (:mod:`dust_rl.rl.steering`, :mod:`dust_rl.rl.residual`) are gymnasium envs, and
several steering envs stepped together are a gymnasium ``VectorEnv`` (:class:`~dust_rl.rl.vector.GymSteeringVectorEnv`),
so torchrl's ``GymWrapper`` takes them as they are (a vector of N as a batched env [N], resetting the finished ones
itself); their observation entries are concatenated into one ``observation`` vector, all but the critic's
``object_state``. The rest is torchrl: a ``ProbabilisticActor`` with a ``TanhNormal`` head inside the action box,
reading ``observation``; two Q networks (``ValueOperator``) reading it, ``object_state`` when the env observes it
(an asymmetric critic: :mod:`dust_rl.rl.asymmetric`) and the action; ``SACLoss`` with a learned temperature,
``SoftUpdate`` target networks, a ``Collector`` that takes uniformly random actions for the first
``learning_starts`` frames, and a ``ReplayBuffer`` on ``LazyTensorStorage``; ``updates_per_step`` updates after
each step of all envs (the update-to-data ratio). Read top to bottom, CleanRL style.

``initial_std`` starts the actor at the base policy, as :mod:`dust_rl.rl.start_at_base` does for SB3 (why: there):
the mean is 0 for every observation (the output layer zeroed), the pre-tanh standard deviation is fixed at
``initial_std``, the warm-up frames act with that actor instead of uniformly, and the entropy bonus is (all but) off.
``base_warmup`` (steering) makes the warm-up frames act with the base policy's own latents instead
(:func:`~dust_rl.rl.steering.prior_latents`), as SB3's ``BaseWarmupSAC`` does.
"""

from __future__ import annotations

from collections.abc import Callable

import gymnasium as gym
import torch
from gymnasium.vector import VectorEnv
from tensordict import TensorDictBase
from tensordict.nn import NormalParamExtractor, TensorDictModule, TensorDictModuleBase
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import CatTensors, GymWrapper, TransformedEnv
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import SACLoss, SoftUpdate
from tqdm.auto import tqdm

from dust_rl.rl.critic_limits import LayerNormReLU
from dust_rl.rl.frozen_policy_env import OBJECT_STATE
from dust_rl.rl.start_at_base import check_initial_std
from dust_rl.rl.steering import Steering, prior_latents

FIXED_STD_ALPHA = 1e-6
"""Entropy coefficient, kept fixed, when the std is fixed (``initial_std``): SB3's ``ent_coef=0`` as near as torchrl's
``SACLoss`` allows (it stores log alpha); why none: :mod:`dust_rl.rl.start_at_base`."""


def torchrl_env(env: gym.Env | VectorEnv) -> TransformedEnv:
    """A fine-tuning env (or a vector of steering envs) as a torchrl env with one ``observation`` vector: every entry
    of its observation (the residual env's ``base_action`` too) but ``object_state``, in the alphabetical order
    ``CatTensors`` sorts them to."""
    space = env.single_observation_space if isinstance(env, VectorEnv) else env.observation_space
    entries = [name for name in space.spaces if name != OBJECT_STATE]
    return TransformedEnv(GymWrapper(env), CatTensors(entries, "observation", del_keys=False))


class FixedScale(nn.Module):
    """Maps a mean to (mean, ``std``): a Gaussian head whose standard deviation is not learnt."""

    def __init__(self, std: float) -> None:
        super().__init__()
        self.register_buffer("std", torch.tensor(float(std)))

    def forward(self, loc: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return loc, self.std.expand_as(loc)


def _activation(layer_norm: bool) -> type[nn.Module]:
    """The hidden layers' activation: torchrl's default, or normalised before a ReLU (``dust-rl finetune
    --layer-norm``, :mod:`dust_rl.rl.critic_limits`)."""
    return LayerNormReLU if layer_norm else nn.Tanh


def sac_actor(env: TransformedEnv, net_arch: tuple[int, ...], initial_std: float | None = None,
              layer_norm: bool = False) -> ProbabilisticActor:
    """A tanh-squashed Gaussian policy over ``env``'s action box; with ``initial_std``, started at the base policy."""
    spec = env.action_spec_unbatched
    action_dim = spec.shape[-1]
    if initial_std is None:
        net = nn.Sequential(MLP(out_features=2 * action_dim, num_cells=list(net_arch),
                                activation_class=_activation(layer_norm)), NormalParamExtractor())
    else:
        mean = MLP(in_features=env.observation_spec["observation"].shape[-1], out_features=action_dim,
                   num_cells=list(net_arch), activation_class=_activation(layer_norm))
        with torch.no_grad():
            mean[-1].weight.zero_()
            mean[-1].bias.zero_()
        net = nn.Sequential(mean, FixedScale(initial_std))
    module = TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"])
    return ProbabilisticActor(module, in_keys=["loc", "scale"], spec=spec, distribution_class=TanhNormal,
                              distribution_kwargs={"low": spec.space.low, "high": spec.space.high},
                              return_log_prob=False)


def sac_critic(env: TransformedEnv, net_arch: tuple[int, ...], layer_norm: bool = False) -> ValueOperator:
    """A Q network of ``env``'s ``observation``, its ``object_state`` when the env observes it (an asymmetric critic),
    and the action; its lazy layers are sized on the first call."""
    privileged = [OBJECT_STATE] if OBJECT_STATE in env.observation_spec.keys() else []
    return ValueOperator(MLP(out_features=1, num_cells=list(net_arch), activation_class=_activation(layer_norm)),
                         in_keys=["observation", *privileged, "action"])


class BaseWarmup(TensorDictModuleBase):
    """The actor, or while :attr:`warming` the base policy's own latents
    (:func:`~dust_rl.rl.steering.prior_latents`) as the action."""

    def __init__(self, actor: ProbabilisticActor, steering: Steering) -> None:
        super().__init__()
        self.actor, self.steering, self.warming = actor, steering, True
        self.in_keys, self.out_keys = list(actor.in_keys), ["action"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if not self.warming:
            return self.actor(tensordict)
        latents = prior_latents(tensordict.numel(), self.steering.action_dim, self.steering.noise_bound)
        return tensordict.set("action", latents.reshape(*tensordict.shape, -1))


def train_sac(make_env: Callable[[], gym.Env | VectorEnv], steps: int, *, learning_starts: int = 1000,
              batch_size: int = 256, net_arch: tuple[int, ...] = (256, 256), layer_norm: bool = False,
              updates_per_step: int = 1, lr: float = 3e-4, gamma: float = 0.99, tau: float = 0.005, seed: int = 0,
              initial_std: float | None = None, base_warmup: bool = False, progress: bool = True,
              log: Callable[[dict[str, float], int], None] | None = None) -> ProbabilisticActor:
    """Train SAC for ``steps`` frames of ``make_env()``; returns the actor (its mean is the greedy policy).

    Args:
        make_env: builds a fine-tuning env (gymnasium), or a vector of steering envs.
        steps: frames to collect (one per RL step of each env; a multiple of the envs).
        learning_starts: frames of warm-up actions (uniformly random) before the first update.
        batch_size, net_arch, lr, gamma, tau: SAC's minibatch size, hidden layers, Adam rate, discount, and
            target-network rate.
        layer_norm: normalise each hidden layer of the actor and critics before a ReLU.
        updates_per_step: updates after each step of all envs once learning starts.
        seed: seeds torch and the env.
        initial_std: start at the base policy (zero mean, this fixed pre-tanh std, no uniform warm-up, no entropy
            bonus to speak of).
        base_warmup: the warm-up acts with the base policy's own latents (a steering env; module doc).
        progress: show a progress bar.
        log: receives the losses and temperature after each update, with the frame count.

    Raises:
        ValueError: ``initial_std`` not a finite number > 0, both ``initial_std`` and ``base_warmup``, or ``steps``
            not a multiple of the envs.
    """
    fixed_std = initial_std is not None
    if fixed_std:
        check_initial_std(initial_std)
        if base_warmup:
            raise ValueError("initial_std warms up with the actor, base_warmup with the base policy's latents: "
                             "pick one")
    torch.manual_seed(seed)
    raw = make_env()
    env = torchrl_env(raw)
    envs = env.batch_size.numel()
    if steps % envs:
        raise ValueError(f"steps must be a multiple of the {envs} envs, got {steps}")
    env.set_seed(seed)
    actor = sac_actor(env, net_arch, initial_std, layer_norm)
    qvalue = sac_critic(env, net_arch, layer_norm)
    with torch.no_grad():  # materialise the lazy layers on one real step
        qvalue(actor(env.reset()))
    loss = SACLoss(actor, qvalue, num_qvalue_nets=2, action_spec=env.action_spec_unbatched, fixed_alpha=fixed_std,
                   alpha_init=FIXED_STD_ALPHA if fixed_std else 1.0)
    loss.make_value_estimator(gamma=gamma)
    target_update = SoftUpdate(loss, tau=tau)
    optimizer = torch.optim.Adam(loss.parameters(), lr=lr)
    buffer = ReplayBuffer(storage=LazyTensorStorage(steps), batch_size=batch_size)
    acting = BaseWarmup(actor, raw.steering) if base_warmup else actor
    collector = Collector(env, acting, frames_per_batch=envs, total_frames=steps,
                          init_random_frames=0 if fixed_std or base_warmup else learning_starts,
                          auto_register_policy_transforms=False)  # the actor needs no InitTracker

    frames = 0
    for data in tqdm(collector, total=steps // envs, desc="SAC (torchrl)", disable=not progress):
        buffer.extend(data.reshape(-1).exclude("loc", "scale"))  # the actor's outputs: SACLoss recomputes them
        frames += data.numel()
        if isinstance(acting, BaseWarmup):
            acting.warming = frames < learning_starts
        if frames < learning_starts or len(buffer) < batch_size:
            continue
        for _ in range(updates_per_step):
            losses = loss(buffer.sample())
            total = losses["loss_actor"] + losses["loss_qvalue"] + losses["loss_alpha"]
            optimizer.zero_grad()
            total.backward()
            optimizer.step()
            target_update.step()
            if log is not None:
                log({k: losses[k].item() for k in ("loss_actor", "loss_qvalue", "loss_alpha", "alpha")}, frames)
    collector.shutdown()
    env.close()
    return actor
