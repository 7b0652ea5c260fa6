"""Feature batches of a second dataset, to mix into every training batch beside the demonstrations.

A policy's own successful rollouts on fresh layouts (``dust-rl collect --policy``) teach it with its
executed actions (self-imitation: ``action_key="action"``); the same rollouts with the scripted expert's
label at every state they visit teach it to recover (DAgger: ``"expert_action"``). Action-free video
(:mod:`dust_rl.train.action_free`) drops the actions altogether. Either way the episodes must come from the
policy's robot and cameras; their frames are encoded once by the policy's frozen backbone and cached in
their dataset folder.
"""

from __future__ import annotations

from tensordict import TensorDict

from dust_rl.agents import DustPolicy
from dust_rl.data import DatasetError, DemoDataset, DemoWindows
from dust_rl.data.features import FeatureCache
from dust_rl.keys import EXPERT_ACTION_KEY


class DatasetBatches:
    """Feature batches of a dataset's windows, as :meth:`FeatureCache.batch` gives them for the demonstrations.

    Args:
        dataset: the episodes (same robot state and action sizes as the policy).
        policy: the policy in training (its backbone encodes the frames once, cached in the dataset folder).
        batch_size: windows per batch.
        action_key: the per-row action the chunks hold: the executed ``"action"`` or the ``"expert_action"``.
        start_rows, start_fraction: as :class:`~dust_rl.data.DemoWindows` (the demonstrations' emphasis).
        progress: show the encoding progress bar.

    Raises:
        DatasetError: another robot's state or action size.
    """

    def __init__(self, dataset: DemoDataset, policy: DustPolicy, batch_size: int,
                 action_key: str = EXPERT_ACTION_KEY, start_rows: int = 0, start_fraction: float = 0.0,
                 progress: bool = True) -> None:
        spec, config = dataset.meta["spec"], policy.config
        if (spec["state_dim"], spec["action_dim"]) != (config.state_dim, config.action_dim):
            raise DatasetError(f"{dataset.root}: its robot state and action have {spec['state_dim']} and "
                               f"{spec['action_dim']} numbers, the policy's {config.state_dim} and "
                               f"{config.action_dim}; episodes mixed into training must come from the same robot")
        self.features = FeatureCache(dataset, policy, progress=progress, store=True)
        self.windows = DemoWindows(dataset, horizon=config.horizon, future_offset=config.future_steps,
                                   batch_size=batch_size, action_key=action_key, images=False, start_rows=start_rows,
                                   start_fraction=start_fraction)

    def sample(self) -> TensorDict:
        """A feature batch of ``batch_size`` windows."""
        return self.features.batch(self.windows.sample())
