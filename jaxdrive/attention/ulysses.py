"""All-to-all ("Ulysses") sequence-parallel attention over the ``seq`` mesh axis.

DeepSpeed-Ulysses (Jacobs et al. 2023), the sequence parallelism MagicDrive-V2 uses: the ``n``
devices of the ``seq`` axis each hold a sequence chunk ``[B, L / n, H, D]`` of q, k and v.
``lax.all_to_all`` trades the sequence split for a head split, giving every device the *whole*
sequence for ``H / n`` of its heads ``[B, L, H / n, D]``; a single-device kernel attends over it,
and a second all-to-all restores the sequence split. The price is that the heads on one
``tensor`` shard must divide by ``n``.

By default only the query side crosses whole: keys and values cross in *pieces* of one key tile
(piece p of every device's chunk, exchanged together), and each piece is attended by all query
tiles and merged into the running ``(o, lse)`` in place
(:func:`jaxdrive.attention.blockwise.tiled_attend`). The backward is a ``custom_vjp`` whose
residuals are q, k, v, the output and the row log-sum-exp: it exchanges q and the output
cotangent, sends the K/V pieces again, and returns each piece's dK/dV to its owners as soon as the
piece is done; the output and dQ return to the sequence split one query tile at a time. A device
so holds head-split copies of q, dO and dQ but never of K, V, dK or dV, and exchanges no whole K/V,
output or dQ chunk at once (each whole-chunk all-to-all needs about two chunks of transient
buffers). The price is communication: q, k and v cross again in the backward, 11 chunk exchanges
per call instead of 8.

``local=`` swaps in any single-device kernel ``local(q, k, v, *, scale, kv_mask, causal_block)``
(a fused GPU/TPU kernel, for instance): q, k, v cross whole, ``kv_mask`` is gathered with
``lax.all_gather``, and gradients flow by autodiff through the collectives (the transpose of an
all-to-all is the inverse all-to-all), with the local kernel's own backward.

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


def _to_heads(x, axis):
    """``[B, L / n, h, D] -> [B, L, h / n, D]`` (sequence split -> head split)."""
    return jax.lax.all_to_all(x, axis, split_axis=2, concat_axis=1, tiled=True)


def _to_seq(x, axis):
    """``[B, L, h / n, D] -> [B, L / n, h, D]`` (head split -> sequence split)."""
    return jax.lax.all_to_all(x, axis, split_axis=1, concat_axis=2, tiled=True)


def _seq_in_tiles(x, axis, n, tile, dtype):
    """:func:`_to_seq` of ``x [B, n c, h / n, D]`` in ``dtype``, ``tile`` rows of every device's
    block at a time, so the exchange's transient buffers are tile-sized, not chunk-sized."""
    if n == 1:
        return x.astype(dtype)
    b, c = x.shape[0], x.shape[1] // n
    blocks = x.reshape(b, n, c, *x.shape[2:])

    def part(p):
        y = jax.lax.dynamic_slice_in_dim(blocks, p * tile, tile, axis=2)
        return _to_seq(y.reshape(b, n * tile, *x.shape[2:]).astype(dtype), axis)

    step = lambda p, out: jax.lax.dynamic_update_slice_in_dim(out, part(p), p * tile, axis=1)
    # The result starts as the padded first tile, not as zeros: XLA copies a zero constant into
    # the loop's buffer at program start, holding a chunk-sized buffer through the forward.
    first = part(0)
    first = jnp.pad(first, [(0, 0), (0, c - tile)] + [(0, 0)] * (first.ndim - 2))
    return jax.lax.fori_loop(1, c // tile, step, first)


@functools.cache
def _ulysses_kernel(scale: float, causal_block, axis: str, n: int, has_mask: bool, bq: int, bk: int):
    """Per-device custom-VJP all-to-all attention (runs inside ``shard_map``), K/V in pieces.

    Key piece p gathers key tile p of every device's chunk: its tile j is device j's, global
    start ``j * chunk + p * bk`` (``k_step = chunk`` for the tile loops)."""
    tiles = dict(scale=scale, causal_block=causal_block, bq=bq, bk=bk)
    piece = lambda x, p: jax.lax.dynamic_slice_in_dim(x, p * bk, bk, axis=1)

    def gathered(k, v, mask, p):
        """Key piece p of every device for this device's heads, ``[B, n * bk, h / n, D]``."""
        mp = jax.lax.all_gather(piece(mask, p), axis, axis=1, tiled=True) if has_mask else None
        return _to_heads(piece(k, p), axis), _to_heads(piece(v, p), axis), mp

    def key_pieces(k, body, state):
        return jax.lax.fori_loop(0, k.shape[1] // bk, body, state)

    def forward(q, k, v, mask):
        qh = _to_heads(q, axis)

        def one_piece(p, acc):
            kp, vp, mp = gathered(k, v, mask, p)
            return tiled_attend(qh, kp, vp, mp, k_start=p * bk, k_step=k.shape[1], acc=acc, **tiles)

        o, lse = key_pieces(k, one_piece, sb.empty(qh))
        return _seq_in_tiles(o, axis, n, bq, q.dtype), lse

    @jax.custom_vjp
    def kernel(q, k, v, mask):
        return forward(q, k, v, mask)[0]

    def kernel_fwd(q, k, v, mask):
        o, lse = forward(q, k, v, mask)
        return o, (q, k, v, mask, o, lse)

    def kernel_bwd(res, do):
        q, k, v, mask, o, lse = res
        # delta per (head, row) in the sequence split, then to the head split like lse
        delta = jax.lax.all_to_all(sb.delta(o, do), axis, split_axis=1, concat_axis=2, tiled=True)
        qh, doh = _to_heads(q, axis), _to_heads(do, axis)

        def one_piece(p, grads):
            dqh, dk, dv = grads
            kp, vp, mp = gathered(k, v, mask, p)
            zeros = lambda x: jnp.zeros(x.shape, jnp.float32)
            dqh, dkp, dvp = tiled_grads(
                qh,
                kp,
                vp,
                mp,
                lse,
                delta,
                doh,
                k_start=p * bk,
                k_step=k.shape[1],
                acc=(dqh, zeros(kp), zeros(vp)),
                **tiles,
            )
            # piece p is complete: back to its owners, in k's dtype
            put = lambda x, g: jax.lax.dynamic_update_slice_in_dim(x, _to_seq(g.astype(x.dtype), axis), p * bk, axis=1)
            return dqh, put(dk, dkp), put(dv, dvp)

        like = lambda x: jnp.zeros(x.shape, x.dtype)
        dqh, dk, dv = key_pieces(k, one_piece, (jnp.zeros(qh.shape, jnp.float32), like(k), like(v)))
        return _seq_in_tiles(dqh, axis, n, bq, q.dtype), dk, dv, None

    kernel.defvjp(kernel_fwd, kernel_bwd)
    return kernel


def _whole(local, scale, causal_block, axis, has_mask):
    """Per-device all-to-all around an arbitrary single-device kernel (q, k, v cross whole)."""

    def per_device(q, k, v, mask):
        qh, kh, vh = (_to_heads(x, axis) for x in (q, k, v))
        full_mask = jax.lax.all_gather(mask, axis, axis=1, tiled=True) if has_mask else None
        o = local(qh, kh, vh, scale=scale, kv_mask=full_mask, causal_block=causal_block)
        return _to_seq(o.astype(q.dtype), axis)

    return per_device


def ulysses_attention(
    q, k, v, *, mesh, scale, kv_mask=None, causal_block=None, seq_axis="seq", block: int = 512, local=None
):
    """Softmax attention of ``q [B, Lq, H, D]`` over ``k, v [B, Lk, H, D]`` by all-to-all over ``seq``.

    ``kv_mask [B, Lk]`` bool (True = attend) and ``causal_block`` follow
    :mod:`jaxdrive.attention.softmax_blocks`; rows with no allowed key give 0. ``mesh`` must have
    the axis ``seq_axis``; batch is split over ``data``/``fsdp`` and heads over ``tensor`` where
    those axes exist, and the heads of one ``tensor`` shard must divide by the ``seq`` size.
    Tiles (and K/V pieces) are at most ``block`` tokens, shorter for short sequences
    (:func:`jaxdrive.attention.seq_shard.tile_size`). ``local(q, k, v, *, scale, kv_mask,
    causal_block) -> [B, Lq, H', D]``, when given, is a single-device kernel run over the whole
    sequence instead (see the module docstring). Sequence lengths that ``seq`` does not divide are
    padded (padded keys masked, padded query rows dropped). Returns ``[B, Lq, H, D]`` in
    ``q.dtype``.
    """
    lay = seq_shard.layout(q, k, v, kv_mask, causal_block, mesh, seq_axis)
    if lay.heads_per_shard % lay.n:
        raise ValueError(
            f"q: expected a number of heads per {seq_shard.HEAD_AXIS!r} shard divisible "
            f"by the size {lay.n} of mesh axis {seq_axis!r}, got {q.shape[2]} heads "
            f"({lay.heads_per_shard} per shard)"
        )
    lq, q_type = q.shape[1], jax.typeof(q)
    if local is None:  # a device holds all query rows of its heads: they set the tile
        tile = seq_shard.tile_size(lay.n * seq_shard.chunk(lq, lay.n), q.shape[3], block)
        q, k, v, kv_mask, bq, bk, has_mask = seq_shard.pad_to_tiles(q, k, v, kv_mask, lay.n, tile)
        kernel = _ulysses_kernel(float(scale), causal_block, seq_axis, lay.n, has_mask, bq, bk)
    else:
        q, k, v, kv_mask, _, _, has_mask = seq_shard.pad_to_tiles(q, k, v, kv_mask, lay.n, None)
        kernel = _whole(local, scale, causal_block, seq_axis, has_mask)
    return seq_shard.run(kernel, mesh, lay, q, k, v, kv_mask, lq, q_type)
