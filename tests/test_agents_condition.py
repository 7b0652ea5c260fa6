"""The condition projector's instruction fusion: image tokens that depend on the named object."""

from __future__ import annotations

import torch

from dust_rl.agents.condition import ConditionProjector

CAMERAS, GRID, DIM, TEXT_DIM, COND_DIM, WORDS = 2, (2, 3), 8, 6, 16, 5


def _condition(projector: ConditionProjector, text: torch.Tensor) -> torch.Tensor:
    torch.manual_seed(1)
    image = torch.randn(1, CAMERAS, GRID[0] * GRID[1], DIM).expand(text.shape[0], -1, -1, -1)
    tokens, _ = projector(image, text, torch.ones(text.shape[:2], dtype=torch.bool))
    return tokens


def test_fused_image_tokens_change_with_the_instruction_and_only_then():
    text = torch.randn(2, WORDS, TEXT_DIM)  # the same image under two instructions
    n_image = CAMERAS * GRID[0] * GRID[1]
    torch.manual_seed(0)
    plain = _condition(ConditionProjector(CAMERAS, GRID, DIM, TEXT_DIM, COND_DIM), text)
    assert torch.equal(plain[0, :n_image], plain[1, :n_image])
    torch.manual_seed(0)
    fused = _condition(ConditionProjector(CAMERAS, GRID, DIM, TEXT_DIM, COND_DIM, text_fusion=True), text)
    assert fused.shape == plain.shape  # the same tokens, no new ones
    assert not torch.allclose(fused[0, :n_image], fused[1, :n_image])
    torch.testing.assert_close(fused[:, n_image:], plain[:, n_image:])  # the text tokens are not touched


def test_fusion_reads_only_the_real_instruction_tokens():
    projector = ConditionProjector(CAMERAS, GRID, DIM, TEXT_DIM, COND_DIM, text_fusion=True)
    text = torch.randn(1, WORDS, TEXT_DIM)
    mask = torch.tensor([[True, True, True, False, False]])
    image = torch.randn(1, CAMERAS, GRID[0] * GRID[1], DIM)
    padded = text.clone()
    padded[0, 3:] = 100.0  # padding holds anything
    n_image = CAMERAS * GRID[0] * GRID[1]
    tokens, padded_tokens = projector(image, text, mask)[0], projector(image, padded, mask)[0]
    torch.testing.assert_close(tokens[:, :n_image], padded_tokens[:, :n_image])
