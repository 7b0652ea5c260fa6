"""The world-model target's variance on press_button before and after standardising it after pooling
(docs/results/2026-11-28-world-model-target.md): t+H targets of 512 training windows, the clamped ones left out."""

import torch

from dust_rl.agents import load_policy
from dust_rl.data import DemoDataset, DemoWindows
from dust_rl.data.features import FeatureCache

torch.manual_seed(0)
policy = load_policy("runs/train/pb_dust_plain/policy.pt")  # the plain recipe, target standardised before pooling
dataset = DemoDataset("runs/data/press_button")
features = FeatureCache(dataset, policy, progress=False, store=True)
batch = features.batch(DemoWindows(dataset, horizon=16, images=False, batch_size=512).sample())
valid = ~batch["future_is_clamped"]
for when in ("before", "after"):
    if when == "after":  # fit the statistics as training now does
        policy.normalizer.set_future_stats(policy.future_targets(policy.normalizer.normalize_vision(rows))
                                           for rows in features.image_tokens.split(1024))
    target = policy._model_batch(batch)["future_tokens"][valid].flatten(0, 1)
    var = target.var(0)
    print(when, f"per element {target.square().mean():.2f}, per channel {var.min():.2f}-{var.max():.2f}")
