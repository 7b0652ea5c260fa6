"""Wiring between demonstration datasets and the DUST policy: cached frozen features, training batches.

The backbone is frozen, so its output for a dataset row never changes: the
image tokens of every row (all cameras) and the tokens of every instruction
are computed once (:class:`FeatureCache`), and a training batch is assembled
from a :class:`~dust_rl.data.DemoWindows` batch by indexing: condition tokens
from the window's row, the world-model target from its t+H row, state and
action chunk normalised with the policy's statistics.

The features depend only on the dataset rows and the backbone, so they are
also kept on disk (``<dataset>/features/<key>.pt``, written atomically), keyed
by a hash of the backbone's weights, the cameras and the token grid: a second
training run, or a resumed one, on the same data loads them instead of
re-encoding every frame.
"""

from __future__ import annotations

import hashlib
import json

import torch
from tensordict import TensorDict, TensorDictBase
from tqdm.auto import tqdm

from dust_rl.agents import DustPolicy
from dust_rl.agents.checkpoint_io import load_checkpoint, save_checkpoint
from dust_rl.data import DatasetError, DemoDataset
from dust_rl.data.stats import stat_name
from dust_rl.data.windows import CHUNK_KEY, FUTURE_KEY, PAD_KEY
from dust_rl.envs.expert_wrapper import EXPERT_ACTION_KEY

STATE_KEY = ("observation", "state")
FEATURES_KIND = "dust-rl-features"


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
        store: keep the features in ``<dataset>/features/`` and reuse them from there.

    Attributes:
        image_tokens: [rows, C, N, Dv] tokens of each of the policy's cameras.
        text_tokens: [instructions, L, Dt]; ``text_mask`` [instructions, L].
        path: the file the image tokens were read from or written to (None unless ``store``).
    """

    def __init__(self, dataset: DemoDataset, policy: DustPolicy, batch_size: int = 128, progress: bool = True,
                 store: bool = False) -> None:
        absent = [cam for cam in policy.cameras if cam not in dataset.cameras]
        if absent:
            raise DatasetError(f"{dataset.root} has no camera {absent} (it has {dataset.cameras})")
        self.policy = policy
        self.path = dataset.root / "features" / f"{feature_key(dataset, policy)}.pt" if store else None
        if self.path is not None and self.path.is_file():
            self.image_tokens = load_checkpoint(self.path, FEATURES_KIND)["image_tokens"]
        else:
            starts = range(0, len(dataset), batch_size)
            self.image_tokens = torch.cat([policy.image_features(dataset.data[s:s + batch_size])
                                           for s in tqdm(starts, desc="encoding frames", disable=not progress)])
            if self.path is not None:
                save_checkpoint({"image_tokens": self.image_tokens}, self.path, FEATURES_KIND)
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


def feature_key(dataset: DemoDataset, policy: DustPolicy) -> str:
    """Hash of what a dataset's image features depend on: rows, image encoder weights, cameras, token grid."""
    digest = hashlib.sha256(json.dumps({
        "data": dataset.meta["data"], "rows": len(dataset), "cameras": policy.cameras,
        "grid": list(policy.config.vision_grid), "encoder": policy.backbone.reference()["image"],
    }, sort_keys=True).encode())
    for name, tensor in sorted(policy.backbone.image.state_dict().items()):
        digest.update(name.encode())
        digest.update(tensor.detach().contiguous().numpy().tobytes())
    return digest.hexdigest()[:16]

