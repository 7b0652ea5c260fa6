"""A warmed-up read-out cached in the dataset folder: runs that would fit the same one load it instead.

``--readout.warmup-steps`` fits the state read-out alone on aux frames before the policy trains
(:mod:`dust_rl.train.readout.warmup`), and nothing in that fit reads the policy's trunk. So every run that starts the
read-out from the same weights and fits it on the same frames, with the same settings and random draws, ends with
the same read-out whatever its variant or trunk: ``dust-rl bench suite``'s dust and action_only cells of one
training seed, a rerun with another learning rate or step count. Two things make that hold: the policy builds its
read-out before the trunk (so the initial weights depend on the seed only), and training runs the warm-up on the
global generator seeded afresh with the run's seed, restoring the outer state afterwards (so the training steps
draw the same numbers whether the warm-up ran or was loaded). The warm-up was a third of a variant-comparison
cell's training time (pick_place, 100 demonstrations, the quickstart's recipe: 4,000 warm-up steps in ~25 minutes,
then 2,000 policy steps in ~45, beside two other jobs), and the variants now share one read-out, so a comparison
no longer mixes the trunk's effect with the read-out's.

The key hashes the read-out's initial weights, the normalisation its inputs pass through, the dataset's frozen
features and every setting the fit reads (:data:`WARMUP_SETTINGS`); a hit loads the fitted weights and replays the
warm-up's logged scalars into the new run's logs. A file that does not load (corrupt, another format) is fitted
again and replaced; one whose bytes changed since it was written is refused (:mod:`dust_rl.storage.cache_files`).
"""

from __future__ import annotations

import hashlib
import json
import pathlib
from collections.abc import Callable

import torch
from torch import nn

from dust_rl.agents import DustPolicy
from dust_rl.data.features import hash_weights
from dust_rl.errors import CheckpointError
from dust_rl.storage.cache_files import cached, record_cache
from dust_rl.storage.checkpoint_files import load_checkpoint, save_checkpoint
from dust_rl.train.readout.aux_frame_cache import FORMAT as AUX_FRAMES_FORMAT
from dust_rl.train.settings import RETIRED_FIELDS, setting

READOUT_KIND = "dust-rl/readout-warmup"
# What the warm-up reads from the training settings (dust_rl.train.settings.TrainSettings, by the top-level names
# they had before the settings were grouped, so fits cached then are still found) and the policy config.
WARMUP_SETTINGS = ("seed", "batch_size", "aux_frames", "readout.close_up_fraction", "readout_warmup", "readout_lr")
READOUT_POLICY_SETTINGS = ("readout", "readout_grid", "readout_heads", "readout_proprio", "readout_text", "keypoints",
                           "keypoint_source")

Logged = list[tuple[int, dict[str, float]]]  # (step, scalars) as the warm-up logged them


def readout_cache_path(folder: pathlib.Path, policy: DustPolicy, settings: object, features: str) -> pathlib.Path:
    """Where the fit of ``policy``'s read-out is cached, ``settings`` being the run's training config (its
    :data:`WARMUP_SETTINGS`) and ``features`` the key of the dataset's frozen features
    (:func:`dust_rl.data.features.feature_key`: rows, encoder weights, cameras, token grid)."""
    digest = hashlib.sha256()
    # The retired settings stay in the key at the value every run now has, so fits cached before are still found.
    retired = {name.partition(".")[::2]: value for name, value in RETIRED_FIELDS.items()}
    described = {"settings": {k: setting(settings, k) for k in WARMUP_SETTINGS}
                 | {name: value for (name, rest), value in retired.items() if not rest},
                 "features": features,
                 "policy": {k: getattr(policy.config, k) for k in READOUT_POLICY_SETTINGS}
                 | {rest: value for (group, rest), value in retired.items() if group == "policy"},
                 "frames": AUX_FRAMES_FORMAT, "cameras": policy.cameras, "device": policy.weights_device.type,
                 "torch": torch.__version__}
    digest.update(json.dumps(described, sort_keys=True, default=str).encode())
    hash_weights(digest, policy.readout.frame_modules())
    # The world-model target's statistics: the read-out never reads them, and fits cached before they existed
    # (or of an action-only policy, which has none) are found again.
    hash_weights(digest, policy.normalizer, exclude=policy.normalizer.FUTURE_STATS)
    return folder / f"{digest.hexdigest()[:24]}.pt"


def load_warmed_readout(path: pathlib.Path, modules: nn.Module) -> Logged | None:
    """Load a cached fit into ``modules``; returns its logged scalars, or None when there is none to load."""
    if not cached(path):
        return None
    try:
        payload = load_checkpoint(path, READOUT_KIND)
        modules.load_state_dict(payload["state_dict"])
    except (CheckpointError, KeyError, RuntimeError):
        return None
    return [(int(step), dict(scalars)) for step, scalars in payload["logged"]]


def warm_up_or_load(path: pathlib.Path | None, modules: nn.Module, seed: int,
                    warm_up: Callable[[Callable[[dict[str, float], int], None]], None],
                    log: Callable[[dict[str, float], int], None]) -> bool:
    """Load the fit cached at ``path`` into ``modules``, or run ``warm_up(log)`` on the global generator seeded
    with ``seed`` (the outer state restored afterwards) and cache its result; None: never cached.

    Returns:
        Whether the fit came from the cache.
    """
    if path is not None and (logged := load_warmed_readout(path, modules)) is not None:
        for step, scalars in logged:
            log(scalars, step)
        return True
    logged: Logged = []

    def log_and_keep(scalars: dict[str, float], step: int) -> None:
        logged.append((step, scalars))
        log(scalars, step)

    with torch.random.fork_rng():
        torch.manual_seed(seed)
        warm_up(log_and_keep)
    if path is not None:
        path.unlink(missing_ok=True)  # a cache that did not load (damaged, of other weights) is replaced
        save_checkpoint({"state_dict": modules.state_dict(), "logged": logged}, path, READOUT_KIND)
        record_cache(path)
    return False
