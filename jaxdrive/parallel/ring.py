"""Ring attention: exact softmax attention with the sequence sharded over the ``seq`` mesh axis.

Each of the ``n`` devices of the ``seq`` axis holds one chunk of the queries and one chunk of the
keys/values (Liu et al. 2023, "Ring Attention with Blockwise Transformers"). In ``n`` steps the
key/value chunks (and their ``kv_mask`` chunk) travel once around the ring by ``lax.ppermute``;
each step merges the partial result of the local queries against the visiting chunk
(:mod:`jaxdrive.parallel.softmax_blocks`) into the running ``(o, lse)``. Causal blocks that hide a
whole visiting chunk from every local query are skipped (``lax.cond``; devices take different
branches). The backward is a ``custom_vjp`` that keeps only q, k, v, the output and the row
log-sum-exp; it sends K/V around the ring again *together with* their dK/dV accumulators, so after
``n`` steps every accumulator is back on the device that owns the chunk. No score matrix survives a
step: memory per device is O(L / n) plus one ``(L / n) x (L / n)`` tile per head.

Batch is sharded over ``data``/``fsdp`` and heads over ``tensor`` (those present in the mesh) at
the same time. Lengths the seq axis cannot split are padded up to a multiple of ``n``: padded keys
are masked out through ``kv_mask`` and padded query rows are dropped from the output, so any
``Lq``/``Lk`` works (``Lq != Lk`` included: positions for ``causal_block`` are global indices
counted from 0 in each of q and k).

The input checks, padding and layout helpers live in :mod:`jaxdrive.parallel.seq_shard`.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from jaxdrive.parallel import softmax_blocks as sb
from jaxdrive.parallel.seq_shard import layout, pad_inputs, to_specs, unpad
from jaxdrive.parallel.blockwise import tiled_attend, tiled_grads

@functools.lru_cache(maxsize=None)
def _ring_kernel(scale: float, causal_block, axis: str, n: int, has_mask: bool, tile_q: int, tile_k: int):
    """Per-device custom-VJP ring attention (runs inside ``shard_map``) for fixed static settings.

    Each step attends the local queries to the visiting key chunk in ``tile_q x tile_k`` tiles
    (:func:`jaxdrive.parallel.blockwise.tiled_attend`), so a device never holds a chunk x chunk
    score matrix: memory is linear in the chunk length."""
    tiles = dict(scale=scale, causal_block=causal_block, bq=tile_q, bk=tile_k)
    shift = [(i, (i + 1) % n) for i in range(n)]      # chunk on device i moves to device i + 1

    rotate = lambda x: jax.lax.ppermute(x, axis, shift)
    rotate_mask = rotate if has_mask else (lambda m: m)   # a placeholder mask stays put

    def _starts(q, k):
        idx = jax.lax.axis_index(axis)
        return idx, idx * q.shape[1], k.shape[1]

    def forward(q, k, v, mask):
        idx, q_start, ck = _starts(q, k)

        def attend(t, carry, kc, vc, mc):
            src = (idx - t) % n                       # owner of the chunk visiting at step t

            def compute():
                o, lse = tiled_attend(q, kc, vc, mc if has_mask else None, q_start=q_start,
                                      k_start=src * ck, **tiles)
                return sb.merge(*carry, o, lse)
            if causal_block is None:
                return compute()
            return jax.lax.cond(sb.hidden(q_start, q.shape[1], src * ck, causal_block),
                                lambda: carry, compute)

        def step(t, state):
            carry, kc, vc, mc = state
            carry = attend(t, carry, kc, vc, mc)
            # One body for all n steps (a peeled first step would be a second copy of the tile
            # loops with buffers of its own); the last rotation is spent, K/V are back home.
            return (carry, *rotate((kc, vc)), rotate_mask(mc))

        carry, *_ = jax.lax.fori_loop(0, n, step, (sb.empty(q), k, v, mask))
        return carry

    @jax.custom_vjp
    def kernel(q, k, v, mask):
        return forward(q, k, v, mask)[0].astype(q.dtype)

    def kernel_fwd(q, k, v, mask):
        o, lse = forward(q, k, v, mask)
        return o.astype(q.dtype), (q, k, v, mask, o, lse)

    def kernel_bwd(res, do):
        q, k, v, mask, o, lse = res
        idx, q_start, ck = _starts(q, k)
        delta = sb.delta(o, do)

        def grads(t, kc, vc, mc):
            src = (idx - t) % n

            def compute():
                return tiled_grads(q, kc, vc, mc if has_mask else None, lse, delta, do,
                                   q_start=q_start, k_start=src * ck, **tiles)
            zeros = lambda: (jnp.zeros(q.shape, jnp.float32), jnp.zeros(kc.shape, jnp.float32),
                             jnp.zeros(vc.shape, jnp.float32))
            if causal_block is None:
                return compute()
            return jax.lax.cond(sb.hidden(q_start, q.shape[1], src * ck, causal_block), zeros, compute)

        def step(t, state):
            dq, kc, vc, mc, dk, dv = state
            gq, gk, gv = grads(t, kc, vc, mc)
            # K/V travel on with their accumulators; after n rotations dK/dV are back with the
            # owner of their chunk (one loop body, as in the forward).
            kc, vc, dk, dv = rotate((kc, vc, dk + gk, dv + gv))
            return dq + gq, kc, vc, rotate_mask(mc), dk, dv

        zero = lambda x: jnp.zeros(x.shape, jnp.float32)
        state = (zero(q), k, v, mask, zero(k), zero(v))
        dq, _, _, _, dk, dv = jax.lax.fori_loop(0, n, step, state)
        return dq.astype(q.dtype), dk.astype(k.dtype), dv.astype(v.dtype), None

    kernel.defvjp(kernel_fwd, kernel_bwd)
    return kernel


def ring_attention(q, k, v, *, mesh, scale, kv_mask=None, causal_block=None, seq_axis="seq",
                   block: int = 512):
    """Softmax attention of ``q [B, Lq, H, D]`` over ``k, v [B, Lk, H, D]`` as a ring over ``seq``.

    ``kv_mask [B, Lk]`` bool (True = attend) and ``causal_block`` follow
    :mod:`jaxdrive.parallel.softmax_blocks`; rows with no allowed key give 0. ``mesh`` must have
    the axis ``seq_axis``; batch is split over ``data``/``fsdp`` and heads over ``tensor`` where
    those axes exist, so ``B`` and ``H`` must divide accordingly. Sequence lengths that ``seq``
    does not divide are padded (padded keys masked, padded query rows dropped). Returns
    ``[B, Lq, H, D]`` in ``q.dtype``; differentiable in q, k and v (custom ring backward).
    Chunks longer than ``block`` are processed in ``block``-sized tiles (lengths padded to a
    multiple of ``n * block`` then), so per-device memory is linear in the chunk length.
    """
    lay = layout(q, k, v, kv_mask, causal_block, mesh, seq_axis)
    lq, q_type = q.shape[1], jax.typeof(q)

    def padded(length):  # chunks longer than a tile become whole tiles
        multiple = lay.n * block if -(-length // lay.n) > block else lay.n
        return -(-length // multiple) * multiple
    lk_pad = padded(k.shape[1])
    has_mask = kv_mask is not None or k.shape[1] != lk_pad
    q, k, v, kv_mask = pad_inputs(q, k, v, kv_mask, lay.n, lq=padded(lq), lk=lk_pad)
    if kv_mask is None:
        kv_mask = jnp.ones(k.shape[:2], bool)         # placeholder, ignored when has_mask is False
    tile = lambda length: min(length // lay.n, block)  # the chunk, or a block dividing it
    kernel = _ring_kernel(float(scale), causal_block, seq_axis, lay.n, has_mask,
                          tile(q.shape[1]), tile(k.shape[1]))
    fn = jax.shard_map(kernel, mesh=mesh, in_specs=(lay.qkv_spec,) * 3 + (lay.mask_spec,),
                       out_specs=lay.qkv_spec, check_vma=False)
    return unpad(fn(*to_specs(mesh, lay, q, k, v, kv_mask)), lq, mesh, lay, like=q_type)
