"""Ring attention: exact softmax attention with the sequence sharded over the ``seq`` mesh axis.

Each of the ``n`` devices of the ``seq`` axis holds one chunk of the queries and one chunk of the
keys/values (Liu et al. 2023, "Ring Attention with Blockwise Transformers"). Keys and values (and
their ``kv_mask``) travel around the ring by ``lax.ppermute`` in *pieces* of one key tile: piece p
of every chunk goes once round the ring (``n`` steps) and is home again before piece p + 1 leaves.
Each step attends all local query tiles to the visiting piece and merges the result into the
running ``(o, lse)`` in place (:func:`jaxdrive.attention.blockwise.tiled_attend`); tiles that
causal masking hides are skipped. The backward is a ``custom_vjp`` that keeps only q, k, v, the
output and the row log-sum-exp; each piece travels again *together with* its dK/dV accumulators
and lands, complete, on the device that owns it.

Memory per device: the chunk-sized inputs, outputs and running accumulators, plus tile-sized
rotation buffers (a ``ppermute`` output cannot reuse its input, so each travelling array is held
twice, but only one tile long) and a few score tiles. Tiles shrink with short chunks
(:func:`jaxdrive.attention.seq_shard.tile_size`), so nothing in it stays constant as ``n`` grows.

Batch is sharded over ``data``/``fsdp`` and heads over ``tensor`` (those present in the mesh) at
the same time; padding follows :mod:`jaxdrive.attention.seq_shard`.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from jaxdrive.attention import seq_shard
from jaxdrive.attention import softmax_blocks as sb
from jaxdrive.attention.blockwise import tiled_attend, tiled_grads


@functools.cache
def _ring_kernel(scale: float, causal_block, axis: str, n: int, has_mask: bool, bq: int, bk: int):
    """Per-device custom-VJP ring attention (runs inside ``shard_map``) for fixed static settings.

    K/V travel in pieces of one ``bk`` key tile: piece p of every chunk goes once round the ring
    (``n`` steps) and comes home before piece p + 1 leaves, so the rotation buffers are tile-sized.
    Each step attends all local query tiles to the visiting piece
    (:func:`jaxdrive.attention.blockwise.tiled_attend`), merging into the running ``(o, lse)`` in
    place; in the backward the piece's dK/dV accumulators travel with it and land in dK/dV at home.
    """
    tiles = dict(scale=scale, causal_block=causal_block, bq=bq, bk=bk)
    shift = [(i, (i + 1) % n) for i in range(n)]  # piece on device i moves to device i + 1
    piece = lambda x, p: None if x is None else jax.lax.dynamic_slice_in_dim(x, p * bk, bk, axis=1)

    def round_trips(k, start, visit, land, state):
        """For each piece p: ``start(p)`` builds what travels, ``visit(p, t, state, travelling)``
        runs at ring step t (returning both), and after ``n`` rotations ``land(p, state,
        travelling)`` receives it back home. One loop body for all steps: a peeled or shortened
        last step would be a second copy of the tile loops with buffers of its own."""

        def one_piece(p, state):
            def step(t, carry):
                state, travelling = visit(p, t, *carry)
                return state, jax.lax.ppermute(travelling, axis, shift)

            return land(p, *jax.lax.fori_loop(0, n, step, (state, start(p))))

        return jax.lax.fori_loop(0, k.shape[1] // bk, one_piece, state)

    def positions(q, k, p, t):
        """Global start of the local queries and of piece p visiting at step t."""
        idx = jax.lax.axis_index(axis)
        return idx * q.shape[1], ((idx - t) % n) * k.shape[1] + p * bk

    def forward(q, k, v, mask):
        mask = mask if has_mask else None

        def visit(p, t, acc, travelling):
            kp, vp, mp = travelling
            q_start, k_start = positions(q, k, p, t)
            return tiled_attend(q, kp, vp, mp, q_start=q_start, k_start=k_start, acc=acc, **tiles), travelling

        start = lambda p: (piece(k, p), piece(v, p), piece(mask, p))
        return round_trips(k, start, visit, lambda p, acc, _: acc, sb.empty(q))

    @jax.custom_vjp
    def kernel(q, k, v, mask):
        return forward(q, k, v, mask)[0].astype(q.dtype)

    def kernel_fwd(q, k, v, mask):
        o, lse = forward(q, k, v, mask)
        o = o.astype(q.dtype)  # the output doubles as the residual (only delta needs it)
        return o, (q, k, v, mask, o, lse)

    def kernel_bwd(res, do):
        q, k, v, mask, o, lse = res
        mask = mask if has_mask else None
        delta = sb.delta(o, do)
        zeros = lambda x: jnp.zeros(x.shape, jnp.float32)

        def start(p):
            kp, vp = piece(k, p), piece(v, p)
            return kp, vp, piece(mask, p), zeros(kp), zeros(vp)

        def visit(p, t, grads, travelling):
            kp, vp, mp, dkp, dvp = travelling
            q_start, k_start = positions(q, k, p, t)
            dq, dkp, dvp = tiled_grads(
                q, kp, vp, mp, lse, delta, do, q_start=q_start, k_start=k_start, acc=(grads[0], dkp, dvp), **tiles
            )
            return (dq, *grads[1:]), (kp, vp, mp, dkp, dvp)

        def land(p, grads, travelling):  # piece p is home, its dK/dV complete: store in k's dtype
            dq, dk, dv = grads
            put = lambda x, g: jax.lax.dynamic_update_slice_in_dim(x, g.astype(x.dtype), p * bk, axis=1)
            return dq, put(dk, travelling[3]), put(dv, travelling[4])

        like = lambda x: jnp.zeros(x.shape, x.dtype)
        dq, dk, dv = round_trips(k, start, visit, land, (zeros(q), like(k), like(v)))
        return dq.astype(q.dtype), dk, dv, None

    kernel.defvjp(kernel_fwd, kernel_bwd)
    return kernel


def ring_attention(q, k, v, *, mesh, scale, kv_mask=None, causal_block=None, seq_axis="seq", block: int = 512):
    """Softmax attention of ``q [B, Lq, H, D]`` over ``k, v [B, Lk, H, D]`` as a ring over ``seq``.

    ``kv_mask [B, Lk]`` bool (True = attend) and ``causal_block`` follow
    :mod:`jaxdrive.attention.softmax_blocks`; rows with no allowed key give 0. ``mesh`` must have
    the axis ``seq_axis``; batch is split over ``data``/``fsdp`` and heads over ``tensor`` where
    those axes exist, so ``B`` and ``H`` must divide accordingly. Sequence lengths that ``seq``
    does not divide are padded (padded keys masked, padded query rows dropped). Returns
    ``[B, Lq, H, D]`` in ``q.dtype``; differentiable in q, k and v (custom ring backward).
    Chunks are processed in square tiles of at most ``block`` tokens, shorter for short chunks
    (:func:`jaxdrive.attention.seq_shard.tile_size`); K/V rotate one tile at a time.
    """
    lay = seq_shard.layout(q, k, v, kv_mask, causal_block, mesh, seq_axis)
    lq, q_type = q.shape[1], jax.typeof(q)
    tile = seq_shard.tile_size(seq_shard.chunk(lq, lay.n), q.shape[3], block)
    q, k, v, kv_mask, bq, bk, has_mask = seq_shard.pad_to_tiles(q, k, v, kv_mask, lay.n, tile)
    kernel = _ring_kernel(float(scale), causal_block, seq_axis, lay.n, has_mask, bq, bk)
    return seq_shard.run(kernel, mesh, lay, q, k, v, kv_mask, lq, q_type)
