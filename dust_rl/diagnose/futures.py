"""The futures a policy predicts, drawn beside the real ones: ``futures.png`` of ``dust-rl diagnose world-model``.

One row per episode, at a window drawn at random whose t+H lies inside the episode (a clamped future would show
its last frame):

    | now (t) | +H predicted | +H real, decoded | +H real |

"predicted" is the future of the policy's own joint sample, "real, decoded" the real future's tokens through the
same decoder: the prediction is read against it, since no decoder draws more than its tokens keep. The decoder is
the image encoder's own (conv autoencoder) or a token decoder fitted for the policy (``dust-rl encoder
fit-decoder``); without either there is no figure.
"""

from __future__ import annotations

import numpy as np
import torch
from PIL import Image

from dust_rl.agents import DustPolicy
from dust_rl.data import DemoWindows
from dust_rl.data.features import FeatureCache
from dust_rl.evaluate.video import Decoder, image_panel, labelled_row
from dust_rl.keys import FUTURE_KEY, IMAGE_KEY, STATE_KEY

FIGURE_ROWS = 6


@torch.no_grad()
def futures_figure(policy: DustPolicy, features: FeatureCache, decoder: Decoder, seed: int,
                   rows: int = FIGURE_ROWS) -> Image.Image:
    """Up to ``rows`` unclamped windows of ``features``' dataset, drawn with ``seed``, as the module doc lays them out
    (torch's global generator is left as it was)."""
    dataset = features.dataset
    windows = DemoWindows(dataset, horizon=policy.config.horizon, future_offset=policy.config.future_steps,
                          batch_size=min(8 * rows, len(dataset)), images=False)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        drawn = windows.sample()
    drawn = drawn[~drawn.get((FUTURE_KEY, "is_clamped"))]
    episode = (torch.searchsorted(dataset.episode_starts, drawn.get("index"), right=True) - 1).tolist()
    drawn = drawn[[episode.index(e) for e in dict.fromkeys(episode)][:rows]]  # one window per episode
    now, ahead, instruction = drawn.get("index"), drawn.get((FUTURE_KEY, "index")), drawn.get("instruction_index")
    device = policy.weights_device
    frames = None
    if policy.reads_pixels:
        frames = policy.frames(dataset.data.select(*[(*IMAGE_KEY, cam) for cam in policy.cameras])[now]).to(device)
    batch = policy.feature_batch(features.image_tokens[now].to(device).float(), features.text_tokens[instruction],
                                 features.text_mask[instruction], drawn.get(STATE_KEY).to(device), frames)
    predicted = policy.plan_features(batch, torch.Generator(device).manual_seed(seed)).get("future_tokens")
    real_tokens = policy.future_targets(features.image_tokens[ahead].float())
    camera = dataset.data.get((*IMAGE_KEY, policy.future_camera))
    size, label = camera.shape[-1], f"+{policy.config.future_steps}"
    lines = []
    for t, t_ahead, mine, real in zip(now, ahead, decoder(predicted), decoder(real_tokens)):
        lines.append(labelled_row([("now", camera[t].permute(1, 2, 0).numpy()),
                                   (f"{label} predicted", image_panel(mine, size)),
                                   (f"{label} real, decoded", image_panel(real, size)),
                                   (f"{label} real", camera[t_ahead].permute(1, 2, 0).numpy())]))
    return Image.fromarray(np.concatenate(lines))
