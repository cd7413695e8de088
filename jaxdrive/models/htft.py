"""STAGE's Hierarchical Temporal Feature Transfer (HTFT, STAGE sec. 4B) and its streaming buffer.

While frame T is denoised at step t, the intermediate features ``f_t^T`` of chosen layers attend to
the features that the same layers produced at the same denoising step for selected past frames:

    F_s = FIFO({f_t^{T-1}, ..., f_t^{T-N}})          (N = 10)
    F_e = U_{x in S} F_s[x]                          (S = {-1, -5, -10})
    g_t^T = Linear(GroupNorm(f_t^T))
    H_t^T = CrossAttn(g_t^T, F_e)
    F_fused = Dropout(f_t^T) + Linear(H_t^T)

:class:`HTFT` is the fusion; :func:`buffer_init`, :func:`buffer_push` and :func:`buffer_select`
are the FIFO as pure functions (the streaming generator keeps one buffer per fused layer and
denoising step). N and S are arguments (configuration), the paper's values the defaults.

Choices where STAGE is not specific: the last Linear is zero-initialised, so that adding HTFT to a
trained model (STAGE's stage 2 trains only the HTFT parameters) starts from the model's own
output; GroupNorm statistics are taken per frame over all its tokens (STAGE's U-Net features are
per frame); the cross-attention has its own q/k/v/out projections.
"""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax.numpy as jnp

from jaxdrive.attention import attention
from jaxdrive.models.layers import AttnProj, Dense, GroupNorm
from jaxdrive.models.params import ZEROS
from jaxdrive.models.tokens import from_sequence, merge, to_sequence
from jaxdrive.parallel.rules import constrain
from jaxdrive.validate import check_positive_int, check_shape

BUFFER_SIZE = 10
SELECT = (-1, -5, -10)
_SFV = (2, 1, 3)   # merged sequences: spatial patches (the sharded axis) major


class HTFT(nn.Module):
    """``F_fused = Dropout(f) + Linear(CrossAttn(Linear(GroupNorm(f)), past))`` (STAGE sec. 4B).

    ``f [B, F, S, V, D]``: the current features (all frames of the current clip); ``past
    [B, K, S, V, D]``: the selected past frames' features at the same layer and step;
    ``past_mask [B, K]`` (False = that buffer slot is empty, not attended to). The attention runs
    sequence-sharded (queries and keys are both split over ``seq``)."""

    width: int
    heads: int
    head_dim: int
    groups: int = 8
    dropout: float = 0.0
    impl: str = "auto"
    dtype: jnp.dtype = jnp.float32

    @nn.compact
    def __call__(self, f, past, past_mask=None, deterministic: bool = True):
        check_shape("past", past, [f.shape[0], None, *f.shape[2:]])
        g = Dense(self.width, ("embed", None), dtype=self.dtype, name="linear_in")(
            GroupNorm(self.groups, keep=2, name_="embed", name="norm")(f))
        proj = AttnProj(self.heads, self.head_dim, self.width, dtype=self.dtype, name="attn")
        q, (k, v) = proj.q(g), proj.kv(past)
        mask = None
        if past_mask is not None:
            check_shape("past_mask", past_mask, [past.shape[0], past.shape[1]])
            b, kk, s, nv = past.shape[:4]
            m = jnp.broadcast_to(jnp.asarray(past_mask, bool)[:, None, :, None], (b, s, kk, nv))
            mask = merge(merge(m, 1), 1)
        o = attention(to_sequence(q, _SFV), to_sequence(k, _SFV), to_sequence(v, _SFV), impl=self.impl,
                      kv_mask=mask)
        h = proj.out(constrain(from_sequence(o, q.shape, _SFV), ("batch", "frames", "tokens", "views", "heads", "head_dim")))
        out = Dense(self.width, ("embed", None), dtype=self.dtype, kernel_init=ZEROS,
                    name="linear_out")(h)
        return nn.Dropout(self.dropout)(f, deterministic=deterministic) + out


def buffer_init(frame_shape: Sequence[int], size: int = BUFFER_SIZE, dtype=jnp.float32) -> dict:
    """An empty FIFO of ``size`` frames of features ``frame_shape = (B, S, V, D)``:
    ``{"data": [B, size, S, V, D], "filled": [B, size] bool}``, slot 0 the most recent frame."""
    check_positive_int("size", size)
    b, *rest = frame_shape
    return {"data": jnp.zeros((b, size, *rest), dtype), "filled": jnp.zeros((b, size), bool)}


def buffer_push(buf: dict, frame) -> dict:
    """Push one frame's features ``[B, S, V, D]`` into the FIFO (the oldest falls out)."""
    data, filled = buf["data"], buf["filled"]
    check_shape("frame", frame, [data.shape[0], *data.shape[2:]])
    data = jnp.concatenate([frame[:, None].astype(data.dtype), data[:, :-1]], axis=1)
    filled = jnp.concatenate([jnp.ones_like(filled[:, :1]), filled[:, :-1]], axis=1)
    return {"data": data, "filled": filled}


def buffer_select(buf: dict, offsets: Sequence[int] = SELECT):
    """The frames at ``offsets`` (-1 = the previous frame, -10 = ten frames back):
    ``(past [B, K, S, V, D], mask [B, K])``, mask False where the slot is still empty."""
    size = buf["data"].shape[1]
    for o in offsets:
        if not -size <= o <= -1:
            raise ValueError(f"offsets: expected values in [-{size}, -1] for a buffer of {size} frames, got {o}")
    idx = jnp.asarray([-o - 1 for o in offsets])
    return jnp.take(buf["data"], idx, axis=1), jnp.take(buf["filled"], idx, axis=1)
