"""Wiring between demonstration datasets and the DUST policy: cached frozen features, training batches.

The backbone is frozen, so its output for a dataset row never changes: the
image tokens of every row (all cameras) and the tokens of every instruction
are computed once (:class:`FeatureCache`), and a training batch is assembled
from a :class:`~dust_rl.data.DemoWindows` batch by indexing: condition tokens
from the window's row, the world-model target from its t+H row, state and
action chunk normalised with the policy's statistics.

The features depend only on the dataset rows and the backbone, so they are
also kept on disk (``<dataset>/features/<key>.npy``, written atomically), keyed
by a hash of the backbone's weights, the cameras and the token grid: a second
training run, or a resumed one, on the same data reads them instead of
re-encoding every frame. Tokens are kept as float16 (half the memory and
disk; features of a 200-episode pick_place dataset at 2 x 8x8x112 tokens per
row take ~450 MB) and turned back into float32 per batch. A stored cache is
streamed to disk while encoding and read memory-mapped (:mod:`dust_rl.storage.token_store`),
so a dataset's features need not fit in memory.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Collection, Iterator

import torch
from tensordict import TensorDict, TensorDictBase
from tqdm.auto import tqdm

from dust_rl.agents import DustPolicy
from dust_rl.data import DatasetError, DemoDataset
from dust_rl.data.augment import JITTER, MAX_SHIFT, augment_frames, view_generator
from dust_rl.data.env_state_norm import EnvStateNorm
from dust_rl.keys import (
    ACTION_CHUNK_KEY,
    ACTION_IS_PAD_KEY,
    BATCH_ENV_STATE_KEY,
    ENV_STATE_KEY,
    EXPERT_ACTION_KEY,
    FUTURE_IS_CLAMPED_KEY,
    FUTURE_KEY,
    IMAGE_KEY,
    READOUT_ESTIMATE_KEY,
    STATE_KEY,
    flat_name,
)
from dust_rl.storage.cache_files import cached, record_cache
from dust_rl.storage.token_store import read_rows, write_rows


def dataset_policy_kwargs(dataset: DemoDataset, action_key: str = EXPERT_ACTION_KEY) -> dict:
    """``make_policy`` arguments that a dataset fixes: sizes, cameras and normalisation statistics.

    Args:
        dataset: the training data.
        action_key: the per-row action that training chunks (as in :class:`~dust_rl.data.DemoWindows`).
    """
    spec, stats = dataset.meta["spec"], dataset.meta["stats"]
    return {"action_dim": spec["action_dim"], "state_dim": spec["state_dim"], "cameras": list(spec["cameras"]),
            "stats": {"state": stats[flat_name(STATE_KEY)], "action": stats[flat_name(action_key)]}}


class FeatureCache:
    """Frozen-backbone features of every row and instruction of a dataset.

    Args:
        dataset: the dataset.
        policy: supplies the backbone, cameras, token grid and normalisation statistics.
        batch_size: rows encoded at once.
        progress: show a progress bar.
        store: keep the features in ``<dataset>/features/`` and reuse them from there.
        views: K, cached views per frame (1: no augmentation).

    Attributes:
        views: [K, rows, C, N, Dv] float16 condition tokens of each of the policy's cameras; view 0 is
            the frames themselves, views 1..K-1 augmented copies (``image_tokens`` is view 0).
        text_tokens: [instructions, L, Dt]; ``text_mask`` [instructions, L].
        path: the file the image tokens were read from or written to (None unless ``store``).
    """

    def __init__(self, dataset: DemoDataset, policy: DustPolicy, batch_size: int = 128, progress: bool = True,
                 store: bool = False, views: int = 1) -> None:
        absent = [cam for cam in policy.cameras if cam not in dataset.cameras]
        if absent:
            raise DatasetError(f"{dataset.root} has no camera {absent} (it has {dataset.cameras})")
        if views < 1:
            raise ValueError(f"views must be >= 1, got {views}")
        self.policy, self.dataset, self.batch_size = policy, dataset, batch_size
        key = feature_key(dataset, policy, views, batch_size)
        self.path = dataset.cache_root / "features" / f"{key}.npy" if store else None
        # Stored row-major, [rows, views, ...], so encoding appends batch after batch of rows.
        shape = (len(dataset), views, len(policy.cameras), policy.config.n_image_tokens,
                 policy.config.vision_dim)
        encoded = self._encoded_rows(views, progress)
        if self.path is None:
            rows = torch.cat(list(encoded))
        else:
            if not cached(self.path):
                write_rows(self.path, shape, encoded)
                record_cache(self.path)
            rows = read_rows(self.path, shape)
        self.views = rows.transpose(0, 1)
        self.text_tokens, self.text_mask = policy.backbone.text_tokens(dataset.instructions)
        self.env_state_norm = EnvStateNorm.of_dataset(dataset) if policy.config.aux_state_dim else None
        self.readout_estimates: torch.Tensor | None = None  # [rows, S], once the read-out is frozen

    def store_readout_estimates(self, chunk: int = 1024) -> None:
        """The frozen token read-out's estimate of every row, made once from its frames as they are (view 0), for
        :meth:`batch` to hand out: a training step then runs no read-out, and an augmented view of the frames no
        longer moves what the trunk is told about the objects. Call after the read-out's weights are frozen."""
        instruction = self.dataset.data.get("instruction_index").reshape(-1)
        device, estimates = self.policy.weights_device, []
        for start in range(0, len(self.dataset), chunk):
            rows = slice(start, start + chunk)
            text = instruction[rows]
            state = self.dataset.data.get(STATE_KEY)[rows].to(device)
            features = self.policy.feature_batch(self.image_tokens[rows].to(device).float(), self.text_tokens[text],
                                                 self.text_mask[text], state)
            estimates.append(self.policy.estimate_env_state(features))
        self.readout_estimates = torch.cat(estimates)

    @property
    def image_tokens(self) -> torch.Tensor:
        """[rows, C, N, Dv] float16 condition tokens of the frames themselves (view 0)."""
        return self.views[0]

    def _image_keys(self) -> list[tuple[str, ...]]:
        return [(*IMAGE_KEY, cam) for cam in self.policy.cameras]

    def _encoded_rows(self, views: int, progress: bool) -> Iterator[torch.Tensor]:
        """Tokens [rows, views, ...] of batch after batch of rows, encoded when asked for (a cache read from
        disk starts no progress bar)."""
        for start in tqdm(range(0, len(self.dataset), self.batch_size), desc="encoding frames", disable=not progress):
            yield self._encode(start, views).transpose(0, 1)

    def _encode(self, start: int, views: int) -> torch.Tensor:
        """Tokens [views, rows, ...] of the batch of rows from ``start``: as they are, then augmented copies.

        The frames are read once for all views (see :mod:`dust_rl.data.augment` for the augmentation).
        """
        keys = self._image_keys()
        rows = self.dataset.data.select(*keys)[start:start + self.batch_size]
        device = self.policy.weights_device
        encoded = [self.policy.image_features(rows.to(device)).half()]
        for view in range(1, views):  # augmented on the CPU, from a CPU generator: the same views on any device
            generator = view_generator(start, view)
            frames = {key: augment_frames(rows.get(key), generator) for key in keys}
            encoded.append(self.policy.image_features(TensorDict(frames, batch_size=rows.batch_size,
                                                                 device=device)).half())
        return torch.stack(encoded).cpu()

    def batch(self, windows: TensorDictBase) -> TensorDict:
        """The policy's feature batch (see :mod:`dust_rl.agents.policy`) for a ``DemoWindows`` batch."""
        rows, instructions = windows.get("index"), windows.get("instruction_index")
        views = self.views.shape[0]  # one cached view per window
        view = torch.randint(0, views, rows.shape) if views > 1 else torch.zeros_like(rows)
        labels = {ACTION_IS_PAD_KEY: windows.get(ACTION_IS_PAD_KEY),
                  FUTURE_IS_CLAMPED_KEY: windows.get((FUTURE_KEY, "is_clamped"))}
        if self.env_state_norm is not None:
            labels[BATCH_ENV_STATE_KEY] = self.env_state_norm.normalize(windows.get(ENV_STATE_KEY).float(),
                                                                        self.dataset.row_task_index[rows])
        if self.readout_estimates is not None:
            labels[READOUT_ESTIMATE_KEY] = self.readout_estimates[rows]
        frames = None
        if self.policy.reads_pixels:  # read from the dataset's memmap per batch (the OS caches the pages)
            frames = self.policy.frames(self.dataset.data.select(*self._image_keys())[rows])
        device = self.policy.weights_device
        return self.policy.feature_batch(
            self.views[view, rows].to(device).float(), self.text_tokens[instructions], self.text_mask[instructions],
            windows.get(STATE_KEY).to(device), None if frames is None else frames.to(device),
            action_chunk=windows.get(ACTION_CHUNK_KEY).to(device),
            future_image_tokens=self.image_tokens[windows.get((FUTURE_KEY, "index"))].to(device).float(),
            labels={key: value.to(device) for key, value in labels.items()})


def env_state_width(dataset: DemoDataset) -> int:
    """Size of the dataset's privileged ``observation.environment_state`` (0 when it has none)."""
    return len(dataset.meta["stats"].get(flat_name(ENV_STATE_KEY), {}).get("mean", []))


def feature_key(dataset: DemoDataset, policy: DustPolicy, views: int = 1, batch_size: int = 128) -> str:
    """Hash of what a dataset's image features depend on: rows, encoder weights, cameras, token grid, views.

    ``batch_size`` seeds the augmented views (one generator per batch of rows), so it is part of the key.
    """
    augmentation = {"views": views, "augment": [MAX_SHIFT, JITTER, batch_size]} if views > 1 else {}
    digest = hashlib.sha256(json.dumps({
        "data": dataset.meta["data"], "rows": len(dataset), "cameras": policy.cameras, **augmentation,
        "grid": list(policy.config.token_grid), "dtype": "float16", "encoder": policy.backbone.reference()["image"],
    }, sort_keys=True).encode())
    hash_weights(digest, policy.backbone.image)
    return digest.hexdigest()[:16]


def hash_weights(digest: hashlib._Hash, module: torch.nn.Module, exclude: Collection[str] = ()) -> None:
    """Add every tensor of ``module``'s state but those named in ``exclude``, by name, to ``digest``: the key of a
    cache derived from those weights (any dtype, any device: the bytes are read on the CPU)."""
    for name, tensor in sorted(module.state_dict().items()):
        if name in exclude:
            continue
        digest.update(name.encode())
        digest.update(tensor.detach().cpu().contiguous().flatten().view(torch.uint8).numpy().tobytes())
