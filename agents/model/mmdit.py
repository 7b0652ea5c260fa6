"""Transformer blocks of the DUST trunk, with separate weights per stream.

Streams are stacked on a leading axis: tokens are [S, B, N, d] (streams padded
to a common N) and every weight is [S, ...], slice ``s`` belonging to stream
``s`` alone (AdaLN modulation, QKV, output projection, MLP). All streams then
go through each layer in one batched matmul: at batch 1 the trunk is bound by
the number of ops, and this halves it for two streams (measured ~1.7x faster
than one module per stream).

A :class:`Block` is one attention plus an MLP; its attention kind is

- ``"joint"``: the streams' tokens are concatenated inside ONE self-attention
  (MMDiT); this is the only place where streams meet.
- ``"self"``: self-attention within each stream (per-stream DiT block; with a
  single stream, a plain DiT block).
- ``"cross"``: each stream's tokens attend to the backbone condition tokens,
  through that stream's own K/V projection.

Self and cross attention alternate block by block, as in GR00T-N1.5's action
head which DUST extends (cross in even blocks, self in odd blocks). We chose
the alternation over "self then cross in every block" because it keeps the
paper's GR00T layout and gives one attention per block, which matters at
batch 1 where latency is set by the number of ops, not by FLOPs.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .adaln import modulate
from .stream_linear import StreamLinear

AttentionKind = Literal["joint", "self", "cross"]
KV = tuple[Tensor, Tensor]


def split_heads(x: Tensor, n_parts: int, n_heads: int) -> tuple[Tensor, ...]:
    """[S, B, N, n_parts * d] -> ``n_parts`` tensors [S, B, n_heads, N, d / n_heads]."""
    s, b, n, _ = x.shape
    return x.view(s, b, n, n_parts, n_heads, -1).permute(3, 0, 1, 4, 2, 5).unbind(0)


# CUDA's attention kernels fail from a batch of 65,536 on (cuDNN: "mha_graph.execute ... is_good()", the others:
# "invalid argument"; measured on an H200, torch 2.11, bf16; 65,535 runs): larger batches go in slices.
MAX_ATTENTION_BATCH = 65535


def attention(q: Tensor, k: Tensor, v: Tensor, mask: Tensor | None) -> Tensor:
    """``scaled_dot_product_attention`` over [B, h, N, e], in batch slices every CUDA kernel accepts."""
    if q.shape[0] <= MAX_ATTENTION_BATCH:
        return F.scaled_dot_product_attention(q, k, v, attn_mask=mask)
    rows = [slice(start, start + MAX_ATTENTION_BATCH) for start in range(0, q.shape[0], MAX_ATTENTION_BATCH)]
    return torch.cat([F.scaled_dot_product_attention(q[r], k[r], v[r], attn_mask=mask if mask is None or
                                                     mask.shape[0] == 1 else mask[r]) for r in rows])


def attend(q: Tensor, k: Tensor, v: Tensor, mask: Tensor | None) -> Tensor:
    """Attention per stream: q [S, B, h, N, e], k/v [S, B, h, M, e], mask broadcastable to [S, B, 1, 1, M].

    Returns [S, B, N, h * e].
    """
    s, b, h, n, e = q.shape
    flat_mask = None if mask is None else mask.expand(s, b, 1, 1, -1).flatten(0, 1)
    out = attention(q.flatten(0, 1), k.flatten(0, 1), v.flatten(0, 1), flat_mask)
    return out.view(s, b, h, n, e).transpose(2, 3).reshape(s, b, n, h * e)


def attend_jointly(q: Tensor, k: Tensor, v: Tensor, key_valid: Tensor | None) -> Tensor:
    """One attention over the tokens of all streams: q/k/v [S, B, h, N, e], key_valid bool [S, N].

    Returns [S, B, N, h * e].
    """
    s, b, h, n, e = q.shape

    def concat(t: Tensor) -> Tensor:  # [S, B, h, N, e] -> [B, h, S * N, e]
        return t.permute(1, 2, 0, 3, 4).reshape(b, h, s * n, e)

    mask = None if key_valid is None else key_valid.view(1, 1, 1, s * n)
    out = attention(concat(q), concat(k), concat(v), mask)
    return out.view(b, h, s, n, e).permute(2, 0, 3, 1, 4).reshape(s, b, n, h * e)


class Block(nn.Module):
    """One trunk block: an attention of the given kind plus an MLP, weights per stream.

    Args:
        kind: ``"joint"``, ``"self"`` or ``"cross"`` (see module doc).
        n_streams: number of streams with separate weights.
        d_model: token width (condition tokens are projected to it beforehand).
        n_heads: attention heads.
        mlp_ratio: MLP hidden width over d_model.
    """

    def __init__(self, kind: AttentionKind, n_streams: int, d_model: int, n_heads: int, mlp_ratio: float) -> None:
        super().__init__()
        self.kind = kind
        self.n_heads = n_heads
        hidden = int(d_model * mlp_ratio)
        # Fused projection: q only for cross-attention (k, v come from the condition), else q|k|v.
        self.qkv = StreamLinear(n_streams, d_model, d_model if kind == "cross" else 3 * d_model)
        self.kv = StreamLinear(n_streams, d_model, 2 * d_model) if kind == "cross" else None
        self.out = StreamLinear(n_streams, d_model, d_model)
        self.fc1 = StreamLinear(n_streams, d_model, hidden)
        self.fc2 = StreamLinear(n_streams, hidden, d_model)

    def condition_kv(self, cond: Tensor) -> KV | None:
        """Per-stream K/V [S, B, h, Nc, e] of the projected condition tokens [B, Nc, d]; None unless cross.

        They depend neither on the noisy tokens nor on tau, so a sampler
        computes them once per chunk instead of once per denoising step.
        """
        if self.kv is None:
            return None
        n_streams = self.kv.weight.shape[0]
        k, v = split_heads(self.kv(cond.expand(n_streams, *cond.shape)), 2, self.n_heads)
        return k, v

    def forward(
        self,
        x: Tensor,
        mod: Sequence[Tensor],
        cond_kv: KV | None = None,
        cond_mask: Tensor | None = None,
        key_valid: Tensor | None = None,
        streams: slice = slice(None),
    ) -> Tensor:
        """Update the tokens of the given streams.

        Args:
            x: tokens [S', B, N, d] of the selected streams.
            mod: the 6 AdaLN vectors of this block (shift, scale, gate for attention,
                then for the MLP), each [S', B, 1 or N, d].
            cond_kv: output of :meth:`condition_kv` (cross blocks only).
            cond_mask: bool [B, Nc], True where a condition token is valid.
            key_valid: bool [S, N], False on padding tokens of a stream; None without padding.
            streams: which streams x holds; a joint block needs all of them. Streams are
                independent outside joint blocks, so a caller may drop one whose output it
                does not need.
        """
        if self.kind == "joint" and x.shape[0] != self.qkv.weight.shape[0]:
            raise ValueError("a joint block needs every stream")
        h = self.qkv(modulate(x, mod[0], mod[1]), streams)
        if self.kind == "joint":
            attended = attend_jointly(*split_heads(h, 3, self.n_heads), key_valid)
        elif self.kind == "self":
            mask = None if key_valid is None else key_valid[streams, None, None, None, :]
            attended = attend(*split_heads(h, 3, self.n_heads), mask)
        else:
            mask = None if cond_mask is None else cond_mask[None, :, None, None, :]
            k, v = cond_kv
            attended = attend(split_heads(h, 1, self.n_heads)[0], k[streams], v[streams], mask)
        x = torch.addcmul(x, mod[2], self.out(attended, streams))
        hidden = F.gelu(self.fc1(modulate(x, mod[3], mod[4]), streams))
        return torch.addcmul(x, mod[5], self.fc2(hidden, streams))
