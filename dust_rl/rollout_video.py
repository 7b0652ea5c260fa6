"""Rollout videos of a policy: what the cameras see beside what the policy predicts it will see.

Every video frame is one row of panels under a 12-pixel label strip:

    | <camera 1> | <camera 2> | ... | <future camera> +H predicted | <future camera> +H real |

The camera panels are the observation at step ``t``, in the policy's camera
order; the next panel is the frame the policy predicted, at its most recent
re-plan (step ``t0 <= t``), for its ``future_camera`` at ``t0 + H``: the
predicted future tokens decoded by the image encoder and resized to the
camera size; the last panel is what that camera really showed at ``t0 + H``
(the episode's last frame when it ended earlier). The two prediction panels
are missing when the policy cannot show a prediction (no vision stream, the
action-only sampler, or an image encoder without a decoder). A video has one
frame per observation, the last one included.

A recorded episode is the evaluated episode of the same seed, bit for bit:
the env resets from the same seed schedule, the policy re-plans on the same
steps as torchrl's ``MultiStepActorWrapper`` (every ``execute_steps``), and its
sampling noise comes from :func:`episode_generator` in both places.
"""

from __future__ import annotations

import dataclasses
import hashlib
import pathlib
from collections.abc import Callable

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image, ImageDraw
from tensordict import TensorDictBase
from torch import Tensor
from torchrl.envs import EnvBase
from torchrl.envs.utils import step_mdp
from tqdm import tqdm

from dust_rl.agents import DustPolicy
from dust_rl.expert_rollouts import write_video
from dust_rl.keys import IMAGE_KEY, SEED_KEY, STATE_KEY, SUCCESS_KEY

LABEL_HEIGHT = 12
Decoder = Callable[[Tensor], Tensor]


def episode_generator(seed: int) -> torch.Generator:
    """The sampling-noise generator of the episode reset with ``seed``.

    Seeding the noise per episode (not per process) makes an episode's outcome depend on its seed
    only, whatever the number of env processes and the order they ran their episodes in.
    """
    return torch.Generator().manual_seed(int(seed))


def episode_digest(actions: Tensor, final_state: Tensor) -> str:
    """A fingerprint of an episode (its executed actions [T, Da] and last state): equal digests, same episode."""
    data = actions.detach().cpu().contiguous().numpy().tobytes() + final_state.detach().cpu().numpy().tobytes()
    return hashlib.sha256(data).hexdigest()[:16]


def future_decoder(policy: DustPolicy) -> Decoder | None:
    """Predicted future tokens [B, N_o, Dv] -> images [B, 3, h, w] in [0, 1], if this policy can show them.

    None for the action-only variant or sampler (no prediction), and for image encoders without a
    ``decode`` or whose latent grid is not the policy's future-token grid.
    """
    encoder = policy.backbone.image
    grid = getattr(getattr(encoder, "config", None), "latent_grid", None)
    if (not policy.config.has_vision or policy.config.sampler_name == "action_only"
            or not hasattr(encoder, "decode") or policy.config.vision_grid != (grid, grid)):
        return None
    return encoder.decode


def labelled_row(panels: list[tuple[str, np.ndarray]]) -> np.ndarray:
    """Images [H, W, 3] uint8 side by side under a strip naming each one."""
    row = np.concatenate([image for _, image in panels], axis=1)
    canvas = Image.new("RGB", (row.shape[1], row.shape[0] + LABEL_HEIGHT))
    canvas.paste(Image.fromarray(row), (0, LABEL_HEIGHT))
    draw = ImageDraw.Draw(canvas)
    x = 0
    for label, image in panels:
        draw.text((x + 2, 0), label, fill=(255, 255, 255))
        x += image.shape[1]
    return np.asarray(canvas)


def video_frame(td: TensorDictBase, policy: DustPolicy, predicted: Tensor | None,
                real_future: TensorDictBase) -> np.ndarray:
    """The frame of one observation: its cameras, then the decoded prediction [3, h, w] and the real future."""
    views = [td.get((*IMAGE_KEY, cam)) for cam in policy.cameras]
    panels = [(cam, view.permute(1, 2, 0).numpy()) for cam, view in zip(policy.cameras, views)]
    if predicted is not None:
        image = F.interpolate(predicted[None], size=views[0].shape[-2:], mode="bilinear", align_corners=False)[0]
        image = (image.clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
        label = f"{policy.future_camera} +{policy.config.horizon}"
        real = real_future.get((*IMAGE_KEY, policy.future_camera)).permute(1, 2, 0).numpy()
        panels += [(f"{label} predicted", image), (f"{label} real", real)]
    return labelled_row(panels)


@dataclasses.dataclass
class RecordedEpisode:
    """One recorded episode: its seed, outcome, :func:`episode_digest`, and frames (T + 1)."""

    seed: int
    success: bool
    length: int
    digest: str
    frames: list[np.ndarray] = dataclasses.field(repr=False)


@torch.no_grad()
def record_episode(env: EnvBase, policy: DustPolicy) -> RecordedEpisode:
    """Run one episode of ``env`` (its next seed) with receding-horizon re-planning, keeping every frame.

    ``env`` must report ``episode_seed`` and ``is_success`` (:class:`~dust_rl.data.seeding.EpisodeSeedWrapper`).
    """
    decoder = future_decoder(policy)
    td = env.reset()
    seed = int(td.get(SEED_KEY))
    generator = episode_generator(seed)
    observations, predictions, plan_steps, actions, t = [], [], [], [], 0
    while True:
        if t % policy.execute_steps == 0:  # when MultiStepActorWrapper re-plans; it plans on a batch of one
            plan = policy.plan(td.unsqueeze(0), generator)[0]
            predicted = decoder(plan.get("future_tokens")[None])[0] if decoder is not None else None
            planned_at = t
        observations.append(td.exclude("next"))
        predictions.append(predicted)
        plan_steps.append(planned_at)
        actions.append(plan.get("action_chunk")[t % policy.execute_steps])
        td = env.step(td.set("action", actions[-1]))
        if td.get(("next", "done")).any():
            observations.append(td.get("next"))
            predictions.append(predicted)
            plan_steps.append(planned_at)
            last, horizon = len(observations) - 1, policy.config.horizon
            frames = [video_frame(obs, policy, prediction, observations[min(t0 + horizon, last)])
                      for obs, prediction, t0 in zip(observations, predictions, plan_steps)]
            success = bool(td.get(("next", SUCCESS_KEY)).any())
            digest = episode_digest(torch.stack(actions), td.get(("next", *STATE_KEY)))
            return RecordedEpisode(seed, success, t + 1, digest, frames)
        td, t = step_mdp(td), t + 1


def record_videos(env: EnvBase, policy: DustPolicy, episodes: int, out_dir: pathlib.Path, prefix: str,
                  fps: int, progress: bool = True) -> list[dict]:
    """Record the next ``episodes`` episodes of ``env`` as ``<out_dir>/<prefix>_seed<seed>.mp4``.

    Returns:
        One ``{"seed", "success", "length", "digest", "path"}`` per episode.
    """
    rows = []
    for _ in tqdm(range(episodes), desc=f"videos {prefix}", disable=not progress, leave=False):
        episode = record_episode(env, policy)
        path = out_dir / f"{prefix}_seed{episode.seed}.mp4"
        write_video(path, episode.frames, fps)
        rows.append({"seed": episode.seed, "success": episode.success, "length": episode.length,
                     "digest": episode.digest, "path": str(path)})
    return rows
