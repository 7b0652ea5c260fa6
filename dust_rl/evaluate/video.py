"""Rollout videos of a policy: what the cameras see beside what the policy predicts it will see.

Every video frame is one row of panels under a 12-pixel label strip:

    | <camera 1> | <camera 2> | ... | <future camera> +H predicted | <future camera> +H real |

The camera panels are the observation at step ``t``, in the policy's camera
order; the next panel is the frame the policy predicted, at its most recent
re-plan (step ``t0 <= t``), for its ``future_camera`` at ``t0 + H``: the
predicted future tokens decoded by the image encoder (or, for an encoder without a
decoder, a token decoder fitted for the policy: ``dust-rl encoder fit-decoder``) and resized to the
camera size; the last panel is what that camera really showed at ``t0 + H``
(the episode's last frame when it ended earlier). The two prediction panels
are missing when the policy cannot show a prediction (no vision stream, the
action-only sampler, or no decoder for its tokens). A video has one
frame per observation, the last one included.

A video is drawn from the evaluated episode itself: the collector's
trajectory holds every observation, the executor's step counter (which step
of the chunk ran, so when the policy last re-planned) and the future the
policy predicted at that re-plan (``("dust", "future_tokens")``, cached with
the chunk by :class:`~dust_rl.agents.ChunkExecutor`). Nothing is run again.
"""

from __future__ import annotations

import pathlib
from collections.abc import Callable

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image, ImageDraw
from tensordict import TensorDictBase
from torch import Tensor

from dust_rl.agents import DustPolicy
from dust_rl.agents.encoders.token_decoder import TOKEN_DECODER_FILE, TokenDecoder, load_token_decoder
from dust_rl.data.video import write_mp4
from dust_rl.keys import IMAGE_KEY, PREDICTED_FUTURE_KEY

LABEL_HEIGHT = 12
Decoder = Callable[[Tensor], Tensor]


def future_decoder(policy: DustPolicy, token_decoder: TokenDecoder | None = None,
                   source: str | pathlib.Path = "the token decoder") -> Decoder | None:
    """Predicted future tokens [B, N_o, Dv] -> images [B, 3, h, w] in [0, 1], if this policy can show them.

    The image encoder's own ``decode`` where its latent grid is the policy's future-token grid (the conv
    autoencoder), else ``token_decoder`` (fitted for this policy's tokens: ``dust-rl encoder fit-decoder``). None
    for the action-only variant or sampler (no prediction), and without either.

    Raises:
        CheckpointError: ``token_decoder`` (read from ``source``) reads other tokens than this policy predicts.
    """
    if not policy.config.has_vision or policy.config.sampler_name == "action_only":
        return None
    encoder = policy.backbone.image
    grid = getattr(getattr(encoder, "config", None), "latent_grid", None)
    if hasattr(encoder, "decode") and policy.config.vision_grid == (grid, grid):
        return lambda tokens: encoder.decode(tokens.to(policy.weights_device)).cpu()
    if token_decoder is None:
        return None
    token_decoder.check_reads(encoder.reference(), policy.config.vision_grid, policy.config.vision_dim, source)
    return lambda tokens: token_decoder(tokens.cpu())


def decoder_for(policy: DustPolicy, policy_file: pathlib.Path,
                decoder_file: pathlib.Path | None = None) -> tuple[Decoder | None, pathlib.Path | None]:
    """:func:`future_decoder` with the token decoder in ``decoder_file`` or, when None, the one beside
    ``policy_file`` (:data:`TOKEN_DECODER_FILE`) if there is one; and the token decoder file it uses (None: none).

    Raises:
        CheckpointError: ``decoder_file`` (or the file beside the policy) does not load or does not fit the policy.
    """
    own = future_decoder(policy)
    path = decoder_file or policy_file.parent / TOKEN_DECODER_FILE
    if own is not None or not (decoder_file is not None or path.is_file()):
        return own, None
    decoder = future_decoder(policy, load_token_decoder(path), path)
    return decoder, None if decoder is None else path


def image_panel(image: Tensor, size: int) -> np.ndarray:
    """A float image [3, h, w] in [0, 1] as a ``size`` x ``size`` uint8 panel [size, size, 3]."""
    image = F.interpolate(image[None].float(), size=(size, size), mode="bilinear", align_corners=False)[0]
    return (image.clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()


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
        image = image_panel(predicted, views[0].shape[-1])
        label = f"{policy.future_camera} +{policy.config.future_steps}"
        real = real_future.get((*IMAGE_KEY, policy.future_camera)).permute(1, 2, 0).numpy()
        panels += [(f"{label} predicted", image), (f"{label} real", real)]
    return labelled_row(panels)


def episode_frames(trajectory: TensorDictBase, policy: DustPolicy, decoder: Decoder | None) -> list[np.ndarray]:
    """The video frames of one evaluated episode (a collector trajectory ``[T]``): T + 1, the last observation
    included; ``decoder``: :func:`future_decoder`'s, None to show no prediction."""
    last, ahead = trajectory.shape[0], policy.config.future_steps
    observations = [trajectory[t] for t in range(last)] + [trajectory[last - 1].get("next")]
    counters = trajectory.get("counter").reshape(-1).tolist()
    frames, decoded = [], {}
    for t, obs in enumerate(observations):
        step = min(t, last - 1)  # the final observation shows the last plan's prediction
        planned_at = step - (counters[step] - 1)
        if decoder is not None and planned_at not in decoded:
            with torch.no_grad():
                decoded[planned_at] = decoder(trajectory[step].get(PREDICTED_FUTURE_KEY)[None])[0]
        frames.append(video_frame(obs, policy, decoded.get(planned_at),
                                  observations[min(planned_at + ahead, last)]))
    return frames


def write_episode_video(trajectory: TensorDictBase, policy: DustPolicy, decoder: Decoder | None, path: pathlib.Path,
                        fps: int) -> pathlib.Path:
    """``path``: the MP4 of one evaluated episode (:func:`episode_frames`)."""
    write_mp4(path, episode_frames(trajectory, policy, decoder), fps, pad_odd=True)
    return path
