"""STAGE's Hierarchical Temporal Feature Transfer (HTFT, STAGE [2506.13138v1] sec. 4B) and its streaming buffer.

While frame T is denoised at step t, the intermediate features ``f_t^T`` of chosen layers attend to
the features that the same layers produced at the same denoising step for selected past frames:

    F_s = FIFO({f_t^{T-1}, ..., f_t^{T-N}})          (N = 10)
    F_e = U_{x in S} F_s[x]                          (S = {-1, -5, -10})
    g_t^T = Linear(GroupNorm(f_t^T))
    H_t^T = CrossAttn(g_t^T, F_e)
    F_fused = Dropout(f_t^T) + Linear(H_t^T)

:class:`HTFT` is the fusion; :func:`buffer_init`, :func:`buffer_push` and :func:`buffer_select`
are the FIFO as pure functions over a preallocated ring (a slot index, never growing): one ring
per fused layer holding every denoising step's features, ``[steps, B, N, S, V, D]``, which the
streaming generator (:mod:`jaxdrive.generate.streaming`) reads at step i and writes once a frame
is done. N and S are arguments (configuration, ``stream.buffer`` / ``stream.taps``), the paper's
values the defaults.

Choices where STAGE is not specific: the last Linear is zero-initialised, so that adding HTFT to a
trained model (STAGE's stage 2 trains only the HTFT parameters) starts from the model's own
output; GroupNorm statistics are taken per frame over all its tokens (STAGE's U-Net features are
per frame); the cross-attention has its own q/k/v/out projections.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.attention import attention
from jaxdrive.models.layers import AttnProj, Dense, GroupNorm
from jaxdrive.models.params import ZEROS
from jaxdrive.models.tokens import from_sequence, merge, to_sequence
from jaxdrive.parallel.rules import constrain, reshard_like
from jaxdrive.validate import check_positive_int, check_shape

BUFFER_SIZE = 10
SELECT = (-1, -5, -10)
_SFV = (2, 1, 3)  # merged sequences: spatial patches (the sharded axis) major


class HTFT(nn.Module):
    """``F_fused = Dropout(f) + Linear(CrossAttn(Linear(GroupNorm(f)), past))`` (STAGE [2506.13138v1] sec. 4B).

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
            GroupNorm(self.groups, keep=2, name_="embed", name="norm")(f)
        )
        proj = AttnProj(self.heads, self.head_dim, self.width, dtype=self.dtype, name="attn")
        q, (k, v) = proj.q(g), proj.kv(past)
        mask = None
        if past_mask is not None:
            check_shape("past_mask", past_mask, [past.shape[0], past.shape[1]])
            b, kk, s, nv = past.shape[:4]
            m = jnp.broadcast_to(jnp.asarray(past_mask, bool)[:, None, :, None], (b, s, kk, nv))
            mask = merge(merge(m, 1), 1)
        o = attention(to_sequence(q, _SFV), to_sequence(k, _SFV), to_sequence(v, _SFV), impl=self.impl, kv_mask=mask)
        h = proj.out(
            constrain(from_sequence(o, q.shape, _SFV), ("batch", "frames", "tokens", "views", "heads", "head_dim"))
        )
        out = Dense(self.width, ("embed", None), dtype=self.dtype, kernel_init=ZEROS, name="linear_out")(h)
        return nn.Dropout(self.dropout)(f, deterministic=deterministic) + out


def check_taps(taps: Sequence[int], size: int, name: str = "taps") -> tuple[int, ...]:
    """``taps`` (past-frame offsets, -1 = the previous frame) checked against a buffer of ``size``
    frames: ``ValueError`` naming ``name`` for an offset outside ``[-size, -1]`` or a repeat."""
    taps = tuple(taps)
    for o in taps:
        if isinstance(o, bool) or not isinstance(o, (int, np.integer)) or not -size <= o <= -1:
            raise ValueError(f"{name}: expected offsets in [-{size}, -1] for a buffer of {size} frames, got {o!r}")
    if len(set(taps)) != len(taps):
        raise ValueError(f"{name}: expected distinct offsets, got {taps}")
    return taps


def write_slot(data, update, index, axis: int):
    """``data`` with ``update`` (``data`` without ``axis``) written at ``index`` of ``axis``; under an
    Explicit mesh the update first takes ``data``'s sharding (the model's features come sharded
    over ``seq``, a preallocated buffer however it was made)."""
    update = jnp.expand_dims(update.astype(data.dtype), axis)
    return jax.lax.dynamic_update_slice_in_dim(data, reshard_like(update, data), index, axis=axis)


def buffer_init(frame_shapes, size: int = BUFFER_SIZE, *, steps: int = 1, dtype=jnp.float32) -> dict:
    """An empty ring buffer of ``size`` frames of features at ``steps`` denoising steps each:
    ``frame_shapes`` is one frame's shape ``(B, S, V, D)`` or a mapping ``{layer: shape}``;
    ``{"data": [steps, B, size, S, V, D] (per layer), "head": the slot the next frame goes to,
    "count": frames pushed so far}``. Preallocated: pushing never grows it."""
    check_positive_int("size", size)
    check_positive_int("steps", steps)

    def empty(shape):
        b, *rest = shape
        return jnp.zeros((steps, b, size, *rest), dtype)

    data = {k: empty(v) for k, v in frame_shapes.items()} if isinstance(frame_shapes, Mapping) else empty(frame_shapes)
    return {"data": data, "head": jnp.zeros((), jnp.int32), "count": jnp.zeros((), jnp.int32)}


def buffer_push(buf: dict, frame) -> dict:
    """Write one frame's features (``[steps, B, S, V, D]`` per layer, like ``buf["data"]``
    without the slot axis) into the slot at ``head``, the oldest frame's once the ring is full."""
    size = jax.tree_util.tree_leaves(buf["data"])[0].shape[2]

    def write(data, f):
        check_shape("frame", f, [data.shape[0], data.shape[1], *data.shape[3:]])
        return write_slot(data, f, buf["head"], 2)

    return {
        "data": jax.tree_util.tree_map(write, buf["data"], frame),
        "head": (buf["head"] + 1) % size,
        "count": jnp.minimum(buf["count"] + 1, size),
    }


def buffer_select(buf: dict, offsets: Sequence[int] = SELECT):
    """The frames at ``offsets`` (-1 = the previous frame, -10 = ten frames back):
    ``(past, mask)``: ``past [steps, B, K, S, V, D]`` (per layer, like ``buf["data"]``) and
    ``mask [B, K]``, False where that frame does not exist yet (its slot is not attended to)."""
    leaf = jax.tree_util.tree_leaves(buf["data"])[0]
    size = leaf.shape[2]
    offsets = check_taps(offsets, size, "offsets")
    off = jnp.asarray(offsets, jnp.int32)
    idx = (buf["head"] + off) % size
    past = jax.tree_util.tree_map(lambda d: jnp.take(d, idx, axis=2), buf["data"])
    mask = jnp.broadcast_to(buf["count"] >= -off, (leaf.shape[1], len(offsets)))
    return past, mask
