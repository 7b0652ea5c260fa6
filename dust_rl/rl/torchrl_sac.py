"""SAC from torchrl's own parts on the fine-tuning envs: the same training for users of torchrl rather than SB3.

The steering and residual envs (:mod:`dust_rl.rl.steering`, :mod:`dust_rl.rl.residual`) are gymnasium envs, so
torchrl's ``GymWrapper`` takes them as they are; their two observation entries are concatenated into one
``observation`` vector. The rest is torchrl: a ``ProbabilisticActor`` with a ``TanhNormal`` head inside the
action box, two Q networks (``ValueOperator``), ``SACLoss`` with a learned temperature, ``SoftUpdate`` target
networks, a ``Collector`` that takes uniformly random actions for the first ``learning_starts`` frames, and a
``ReplayBuffer`` on ``LazyTensorStorage``. Read top to bottom, CleanRL style.

``initial_std`` starts the actor at the base policy, as :mod:`dust_rl.rl.start_at_base` does for SB3 (why: there):
the mean is 0 for every observation (the output layer zeroed), the pre-tanh standard deviation is fixed at
``initial_std``, the warm-up frames act with that actor instead of uniformly, and the entropy bonus is (all but) off.
"""

from __future__ import annotations

from collections.abc import Callable

import gymnasium as gym
import torch
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import CatTensors, GymWrapper, TransformedEnv
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import SACLoss, SoftUpdate
from tqdm.auto import tqdm

from dust_rl.rl.start_at_base import check_initial_std

FIXED_STD_ALPHA = 1e-6
"""Entropy coefficient, kept fixed, when the std is fixed (``initial_std``): SB3's ``ent_coef=0`` as near as torchrl's
``SACLoss`` allows (it stores log alpha); why none: :mod:`dust_rl.rl.start_at_base`."""


def torchrl_env(env: gym.Env) -> TransformedEnv:
    """A fine-tuning env as a torchrl env with one ``observation`` vector: every entry of its observation (the
    residual env's ``base_action`` too) in the alphabetical order ``CatTensors`` sorts them to."""
    entries = list(env.observation_space.spaces)
    return TransformedEnv(GymWrapper(env), CatTensors(entries, "observation", del_keys=False))


class FixedScale(nn.Module):
    """Maps a mean to (mean, ``std``): a Gaussian head whose standard deviation is not learnt."""

    def __init__(self, std: float) -> None:
        super().__init__()
        self.register_buffer("std", torch.tensor(float(std)))

    def forward(self, loc: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return loc, self.std.expand_as(loc)


def sac_actor(env: TransformedEnv, net_arch: tuple[int, ...], initial_std: float | None = None) -> ProbabilisticActor:
    """A tanh-squashed Gaussian policy over ``env``'s action box; with ``initial_std``, started at the base policy."""
    action_dim = env.action_spec.shape[-1]
    if initial_std is None:
        net = nn.Sequential(MLP(out_features=2 * action_dim, num_cells=list(net_arch)), NormalParamExtractor())
    else:
        mean = MLP(in_features=env.observation_spec["observation"].shape[-1], out_features=action_dim,
                   num_cells=list(net_arch))
        with torch.no_grad():
            mean[-1].weight.zero_()
            mean[-1].bias.zero_()
        net = nn.Sequential(mean, FixedScale(initial_std))
    module = TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"])
    space = env.action_spec.space
    return ProbabilisticActor(module, in_keys=["loc", "scale"], spec=env.action_spec, distribution_class=TanhNormal,
                              distribution_kwargs={"low": space.low, "high": space.high}, return_log_prob=False)


def train_sac(make_env: Callable[[], gym.Env], steps: int, *, learning_starts: int = 1000, batch_size: int = 256,
              net_arch: tuple[int, ...] = (256, 256), lr: float = 3e-4, gamma: float = 0.99, tau: float = 0.005,
              seed: int = 0, initial_std: float | None = None, progress: bool = True,
              log: Callable[[dict[str, float], int], None] | None = None) -> ProbabilisticActor:
    """Train SAC for ``steps`` env steps of ``make_env()``; returns the actor (its mean is the greedy policy).

    Args:
        make_env: builds a fine-tuning env (gymnasium).
        steps: frames to collect (one per RL step).
        learning_starts: frames of uniformly random actions before the first update.
        batch_size, net_arch, lr, gamma, tau: SAC's minibatch size, hidden layers, Adam rate, discount, and
            target-network rate.
        seed: seeds torch and the env.
        initial_std: start at the base policy (zero mean, this fixed pre-tanh std, no uniform warm-up, no entropy
            bonus to speak of).
        progress: show a progress bar.
        log: receives the losses and temperature after each update, with the frame count.
    """
    fixed_std = initial_std is not None
    if fixed_std:
        check_initial_std(initial_std)
    torch.manual_seed(seed)
    env = torchrl_env(make_env())
    env.set_seed(seed)
    actor = sac_actor(env, net_arch, initial_std)
    qvalue = ValueOperator(MLP(out_features=1, num_cells=list(net_arch)), in_keys=["observation", "action"])
    with torch.no_grad():  # materialise the lazy layers on one real step
        qvalue(actor(env.reset()))
    loss = SACLoss(actor, qvalue, num_qvalue_nets=2, action_spec=env.action_spec, fixed_alpha=fixed_std,
                   alpha_init=FIXED_STD_ALPHA if fixed_std else 1.0)
    loss.make_value_estimator(gamma=gamma)
    target_update = SoftUpdate(loss, tau=tau)
    optimizer = torch.optim.Adam(loss.parameters(), lr=lr)
    buffer = ReplayBuffer(storage=LazyTensorStorage(steps), batch_size=batch_size)
    collector = Collector(env, actor, frames_per_batch=1, total_frames=steps,
                          init_random_frames=0 if fixed_std else learning_starts,
                          auto_register_policy_transforms=False)  # the actor needs no InitTracker

    frames = 0
    for data in tqdm(collector, total=steps, desc="SAC (torchrl)", disable=not progress):
        buffer.extend(data.reshape(-1))
        frames += data.numel()
        if frames < learning_starts or len(buffer) < batch_size:
            continue
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
