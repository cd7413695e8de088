"""All-to-all ("Ulysses") sequence-parallel attention over the ``seq`` mesh axis.

DeepSpeed-Ulysses (Jacobs et al. 2023), the sequence parallelism MagicDrive-V2 uses: the ``n``
devices of the ``seq`` axis each hold a sequence chunk ``[B, L / n, H, D]`` of q, k and v. One
``lax.all_to_all`` trades the sequence split for a head split, giving every device the *whole*
sequence for ``H / n`` of its heads ``[B, L, H / n, D]``; a single-device kernel (by default the
memory-efficient :func:`jaxdrive.parallel.blockwise.blockwise_attention`) attends over the full
sequence, and a second all-to-all restores the sequence split. ``kv_mask`` chunks are gathered to
full length with ``lax.all_gather``. Communication is two all-to-alls per call (four arrays),
independent of ``n``; the price is that the heads on one ``tensor`` shard must divide by ``n``.

Gradients flow by autodiff through the collectives (the transpose of an all-to-all is the inverse
all-to-all); the local kernel brings its own memory-efficient ``custom_vjp``.

Batch is sharded over ``data``/``fsdp`` and heads over ``tensor`` (those present in the mesh) at
the same time. Lengths the seq axis cannot split are padded to a multiple of ``n``: padded keys
are masked through ``kv_mask`` and padded query rows dropped (:mod:`jaxdrive.parallel.seq_shard`).
"""

from __future__ import annotations

import jax

from jaxdrive.parallel import seq_shard
from jaxdrive.parallel.blockwise import blockwise_attention


def _to_heads(x, axis):
    """``[B, L / n, h, D] -> [B, L, h / n, D]`` (sequence split -> head split)."""
    return jax.lax.all_to_all(x, axis, split_axis=2, concat_axis=1, tiled=True)


def _to_seq(x, axis):
    """``[B, L, h / n, D] -> [B, L / n, h, D]`` (head split -> sequence split)."""
    return jax.lax.all_to_all(x, axis, split_axis=1, concat_axis=2, tiled=True)


def ulysses_attention(q, k, v, *, mesh, scale, kv_mask=None, causal_block=None, seq_axis="seq",
                      local=blockwise_attention):
    """Softmax attention of ``q [B, Lq, H, D]`` over ``k, v [B, Lk, H, D]`` by all-to-all over ``seq``.

    ``kv_mask [B, Lk]`` bool (True = attend) and ``causal_block`` follow
    :mod:`jaxdrive.parallel.softmax_blocks`; rows with no allowed key give 0. ``mesh`` must have
    the axis ``seq_axis``; batch is split over ``data``/``fsdp`` and heads over ``tensor`` where
    those axes exist, and the heads of one ``tensor`` shard must divide by the ``seq`` size.
    ``local(q, k, v, *, scale, kv_mask, causal_block) -> [B, Lq, H', D]`` is the single-device
    kernel run over the full sequence. Sequence lengths that ``seq`` does not divide are padded
    (padded keys masked, padded query rows dropped). Returns ``[B, Lq, H, D]`` in ``q.dtype``.
    """
    lay = seq_shard.layout(q, k, v, kv_mask, causal_block, mesh, seq_axis)
    if lay.heads_per_shard % lay.n:
        raise ValueError(f"q: expected a number of heads per {seq_shard.HEAD_AXIS!r} shard divisible "
                         f"by the size {lay.n} of mesh axis {seq_axis!r}, got {q.shape[2]} heads "
                         f"({lay.heads_per_shard} per shard)")
    lq, q_type = q.shape[1], jax.typeof(q)
    q, k, v, kv_mask = seq_shard.pad_inputs(q, k, v, kv_mask, lay.n)
    has_mask = kv_mask is not None
    if not has_mask:
        kv_mask = jax.numpy.ones(k.shape[:2], bool)   # placeholder, never gathered nor used

    def per_device(q, k, v, mask):
        qh, kh, vh = (_to_heads(x, seq_axis) for x in (q, k, v))
        full_mask = jax.lax.all_gather(mask, seq_axis, axis=1, tiled=True) if has_mask else None
        o = local(qh, kh, vh, scale=scale, kv_mask=full_mask, causal_block=causal_block)
        return _to_seq(o.astype(q.dtype), seq_axis)

    fn = jax.shard_map(per_device, mesh=mesh, in_specs=(lay.qkv_spec,) * 3 + (lay.mask_spec,),
                       out_specs=lay.qkv_spec, check_vma=False)
    out = fn(*seq_shard.to_specs(mesh, lay, q, k, v, kv_mask))
    return seq_shard.unpad(out, lq, mesh, lay, like=q_type)
