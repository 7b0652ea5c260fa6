"""A learned judge of DUST's predicted futures, for choosing among joint samples (``wm_select``).

DUST samples the action chunk jointly with the frozen embedding of the frame
after it. Drawing K joint samples and executing the one whose predicted
future looks most like success uses the world model at test time without
touching the policy's weights: the scorer is a small MLP over the
(normalised) predicted future tokens, trained afterwards on the policy's own
rollouts labelled by their outcome (:mod:`dust_rl.rl.wm_select`). With one
candidate the policy acts exactly as without a scorer.

==================  ===================  ==========================================
tensor              shape                meaning
==================  ===================  ==========================================
future tokens       [B, N_o, Dv] float   a predicted future, normalised as the trunk's targets
score               [B] float            logit of "this chunk leads to success"
==================  ===================  ==========================================
"""

from __future__ import annotations

from torch import Tensor, nn


class FutureScorer(nn.Module):
    """Predicted future tokens to a success logit.

    Args:
        n_tokens: N_o.
        dim: Dv.
        hidden: width of the hidden layer.
    """

    def __init__(self, n_tokens: int, dim: int, hidden: int) -> None:
        super().__init__()
        self.mlp = nn.Sequential(nn.Flatten(), nn.LayerNorm(n_tokens * dim), nn.Linear(n_tokens * dim, hidden),
                                 nn.GELU(), nn.Linear(hidden, 1))

    def forward(self, future_tokens: Tensor) -> Tensor:
        return self.mlp(future_tokens).squeeze(-1)
