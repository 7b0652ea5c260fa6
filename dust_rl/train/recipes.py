"""Named training recipes: measured settings of :class:`~dust_rl.train.imitation.TrainSettings`, each with its result
in the README."""

from __future__ import annotations

from dust_rl.agents.config import PolicyConfig
from dust_rl.train.imitation import TrainSettings


def vision_recipe() -> TrainSettings:
    """The quickstart's training: a task that needs vision (press_button: three coloured buttons, the
    instruction names one) solved in minutes. Frozen EfficientNet-Lite0 tokens at stride 8 (16x16 per camera,
    pooled to 8x8 for the trunk), text fused into them, a token read-out of the objects' state fitted first on
    8,000 rendered frames and fed to the trunk, three quarters of each batch from an episode's first 4 rows
    (docs/franka_results.md, "The token read-out"). 2,000 steps: 96% / 84% on 50 validation / held-out seeds and
    14.3 minutes in all on 2 idle cores, where 3,000 steps gave 90% / 86% in 18.0 minutes (README). lr 3e-4, higher than
    the paper's 1e-4: a small model trained for minutes."""
    return TrainSettings(policy=PolicyConfig(image_encoder="efficientnet-lite0-s8", cond_grid=(8, 8), text_fusion=True,
                                             readout="tokens", readout_grid=(16, 16), lambda_aux=1.0,
                                             aux_state_input=True),
                         steps=2000, lr=3e-4, start_rows=4, start_fraction=0.75, aux_frames=8000, readout_warmup=4000,
                         readout_demos=False)
