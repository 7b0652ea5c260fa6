"""Wiring between demonstration datasets and the DUST policy: cached frozen features, training batches.

The backbone is frozen, so its output for a dataset row never changes: the
image tokens of every row (all cameras) and the tokens of every instruction
are computed once (:class:`FeatureCache`), and a training batch is assembled
from a :class:`~dust_rl.data.DemoWindows` batch by indexing: condition tokens
from the window's row, the world-model target from its t+H row, state and
action chunk normalised with the policy's statistics.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from tqdm.auto import tqdm

from dust_rl.agents import DustPolicy
from dust_rl.data import DatasetError, DemoDataset
from dust_rl.data.stats import stat_name
from dust_rl.data.windows import CHUNK_KEY, FUTURE_KEY, PAD_KEY
from dust_rl.envs.expert_wrapper import EXPERT_ACTION_KEY

STATE_KEY = ("observation", "state")


def dataset_policy_kwargs(dataset: DemoDataset, action_key: str = EXPERT_ACTION_KEY) -> dict:
    """``make_policy`` arguments that a dataset fixes: sizes, cameras and normalisation statistics.

    Args:
        dataset: the training data.
        action_key: the per-row action that training chunks (as in :class:`~dust_rl.data.DemoWindows`).
    """
    spec, stats = dataset.meta["spec"], dataset.meta["stats"]
    return {"action_dim": spec["action_dim"], "state_dim": spec["state_dim"], "cameras": list(spec["cameras"]),
            "stats": {"state": stats[stat_name(STATE_KEY)], "action": stats[stat_name(action_key)]}}


class FeatureCache:
    """Frozen-backbone features of every row and instruction of a dataset.

    Args:
        dataset: the dataset.
        policy: supplies the backbone, cameras, token grid and normalisation statistics.
        batch_size: rows encoded at once.
        progress: show a progress bar.

    Attributes:
        image_tokens: [rows, C, N, Dv] tokens of each of the policy's cameras.
        text_tokens: [instructions, L, Dt]; ``text_mask`` [instructions, L].
    """

    def __init__(self, dataset: DemoDataset, policy: DustPolicy, batch_size: int = 128, progress: bool = True) -> None:
        absent = [cam for cam in policy.cameras if cam not in dataset.cameras]
        if absent:
            raise DatasetError(f"{dataset.root} has no camera {absent} (it has {dataset.cameras})")
        self.policy = policy
        starts = range(0, len(dataset), batch_size)
        self.image_tokens = torch.cat([policy.image_features(dataset.data[s:s + batch_size])
                                       for s in tqdm(starts, desc="encoding frames", disable=not progress)])
        self.text_tokens, self.text_mask = policy.backbone.text_tokens(dataset.instructions)
        self.future_camera = policy.cameras.index(policy.future_camera)

    def batch(self, windows: TensorDictBase) -> TensorDict:
        """The policy's feature batch (see :mod:`dust_rl.agents.policy`) for a ``DemoWindows`` batch."""
        rows, instructions = windows.get("index"), windows.get("instruction_index")
        normalizer = self.policy.normalizer
        return TensorDict({
            "image_tokens": self.image_tokens[rows],
            "text_tokens": self.text_tokens[instructions],
            "text_mask": self.text_mask[instructions],
            "state": normalizer.normalize_state(windows.get(STATE_KEY)),
            "action_chunk": normalizer.normalize_action(windows.get(CHUNK_KEY)),
            "action_is_pad": windows.get(PAD_KEY),
            "future_tokens": self.image_tokens[windows.get((FUTURE_KEY, "index")), self.future_camera],
        }, batch_size=windows.batch_size)
