"""Memory-efficient attention on one device: O(L) memory forward and backward.

Queries are processed in blocks of ``block_q``; for each, a ``lax.scan`` over key blocks of
``block_k`` merges partial softmax results (:mod:`jaxdrive.parallel.softmax_blocks`), so at most
one ``block_q x block_k`` score tile per head is alive (Rabe & Staats 2021). The backward is a
``custom_vjp`` that stores only q, k, v, the output and the row log-sum-exp, and recomputes the
score tiles (the FlashAttention backward, Dao et al. 2022). Key blocks that causal masking hides
entirely from a query block are skipped.

Lengths that are not multiples of the block sizes are padded: padded keys are masked out and
padded query rows dropped, so any length works.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from jaxdrive.parallel import softmax_blocks as sb


def _pad(x, length, axis=1, value=0):
    extra = length - x.shape[axis]
    if extra == 0:
        return x
    widths = [(0, 0)] * x.ndim
    widths[axis] = (0, extra)
    return jnp.pad(x, widths, constant_values=value)


def _blocks(x, size):
    """``[B, L, ...] -> [L / size, B, size, ...]``."""
    b, length = x.shape[:2]
    return jnp.moveaxis(x.reshape((b, length // size, size) + x.shape[2:]), 1, 0)


def _unblocks(x):
    """``[n, B, size, ...] -> [B, n * size, ...]``."""
    x = jnp.moveaxis(x, 0, 1)
    return x.reshape((x.shape[0], x.shape[1] * x.shape[2]) + x.shape[3:])


def _hidden(i, j, bq, bk, causal_block, q_start=0, k_start=0):
    """True when causal masking hides key tile j from every query of query tile i."""
    if causal_block is None:
        return False
    return (k_start + j * bk) // causal_block > (q_start + (i + 1) * bq - 1) // causal_block


def _key_tiles(k, v, mask, bk):
    mb = None if mask is None else _blocks(mask, bk)
    return jnp.arange(k.shape[1] // bk), _blocks(k, bk), _blocks(v, bk), mb


def tiled_attend(q, k, v, mask, *, scale, causal_block, bq, bk, q_start=0, k_start=0):
    """``(o [B, Lq, H, D], lse [B, H, Lq])`` over tiles of ``bq x bk`` (lengths multiples of them).

    The building block of :func:`blockwise_attention` and of each ring step: at most one score
    tile per head is alive. ``q_start``/``k_start`` (may be traced) are the global positions of
    the first query and key, for causal masking; ``mask [B, Lk]`` or None.
    """
    idx, kb, vb, mb = _key_tiles(k, v, mask, bk)

    def one_query_tile(args):
        i, qi = args

        def step(acc, kv):
            j, kj, vj, mj = kv

            def attend():
                o, lse = sb.attend_block(qi, kj, vj, scale=scale, kv_mask=mj, causal_block=causal_block,
                                         q_start=q_start + i * bq, k_start=k_start + j * bk)
                return sb.merge(*acc, o, lse)
            if causal_block is None:
                return attend(), None
            return jax.lax.cond(_hidden(i, j, bq, bk, causal_block, q_start, k_start),
                                lambda: acc, attend), None

        return jax.lax.scan(step, sb.empty(qi), (idx, kb, vb, mb))[0]

    qb = _blocks(q, bq)
    o, lse = jax.lax.map(one_query_tile, (jnp.arange(qb.shape[0]), qb))
    lse = jnp.moveaxis(lse, 0, 2)                                         # [B, H, nq, bq]
    return _unblocks(o), lse.reshape(lse.shape[:2] + (-1,))


def tiled_grads(q, k, v, mask, o, lse, do, *, scale, causal_block, bq, bk, q_start=0, k_start=0):
    """``(dq, dk, dv)`` (float32) of :func:`tiled_attend`'s key range, given the final ``o``/``lse``
    of the query rows over all keys (FlashAttention backward, one score tile alive at a time)."""
    qb, ob, dob = _blocks(q, bq), _blocks(o, bq), _blocks(do, bq)
    lseb = jnp.moveaxis(lse.reshape(lse.shape[:-1] + (-1, bq)), -2, 0)    # [nq, B, H, bq]
    idx, kb, vb, mb = _key_tiles(k, v, mask, bk)

    def key_tile(dq_acc, kv):
        j, kj, vj, mj = kv

        def query_tile(dkv, qs):
            i, qi, oi, lsei, doi = qs

            def grads():
                dq, dk, dv = sb.attend_block_grads(qi, kj, vj, oi, lsei, doi, scale=scale, kv_mask=mj,
                                                   causal_block=causal_block, q_start=q_start + i * bq,
                                                   k_start=k_start + j * bk)
                return dq, (dkv[0] + dk, dkv[1] + dv)

            if causal_block is None:
                dq, dkv = grads()
            else:
                dq, dkv = jax.lax.cond(_hidden(i, j, bq, bk, causal_block, q_start, k_start),
                                       lambda: (jnp.zeros(qi.shape, jnp.float32), dkv), grads)
            return dkv, dq

        zeros = jnp.zeros(kj.shape, jnp.float32)
        (dk, dv), dq = jax.lax.scan(query_tile, (zeros, zeros), (jnp.arange(qb.shape[0]), qb, ob, lseb, dob))
        return dq_acc + dq, (dk, dv)

    dq, (dk, dv) = jax.lax.scan(key_tile, jnp.zeros(qb.shape, jnp.float32), (idx, kb, vb, mb))
    return _unblocks(dq), _unblocks(dk), _unblocks(dv)


@functools.lru_cache(maxsize=None)
def _kernel(scale: float, causal_block, bq: int, bk: int):
    """The custom-VJP kernel for fixed static settings (arrays already padded to the tiles)."""
    settings = dict(scale=scale, causal_block=causal_block, bq=bq, bk=bk)

    @jax.custom_vjp
    def kernel(q, k, v, mask):
        return tiled_attend(q, k, v, mask, **settings)[0]

    def kernel_fwd(q, k, v, mask):
        o, lse = tiled_attend(q, k, v, mask, **settings)
        return o, (q, k, v, mask, o, lse)

    def kernel_bwd(res, do):
        q, k, v, mask, o, lse = res
        dq, dk, dv = tiled_grads(q, k, v, mask, o, lse, do, **settings)
        return dq.astype(q.dtype), dk.astype(k.dtype), dv.astype(v.dtype), None

    kernel.defvjp(kernel_fwd, kernel_bwd)
    return kernel


def blockwise_attention(q, k, v, *, scale, kv_mask=None, causal_block=None, block_q: int = 512,
                        block_k: int = 512):
    """Softmax attention ``[B, Lq, H, D]`` in O(L) memory (see the module docstring).

    ``kv_mask [B, Lk]`` (True = attend), ``causal_block`` as in
    :mod:`jaxdrive.parallel.softmax_blocks`. Inputs are checked by
    :func:`jaxdrive.models.attention.attention`; this kernel assumes consistent shapes.
    """
    b, lq = q.shape[:2]
    lk = k.shape[1]
    bq, bk = min(block_q, lq), min(block_k, lk)
    lq_pad, lk_pad = -(-lq // bq) * bq, -(-lk // bk) * bk
    mask = jnp.ones((b, lk), bool) if kv_mask is None else jnp.asarray(kv_mask, bool)
    out = _kernel(float(scale), causal_block, bq, bk)(
        _pad(q, lq_pad), _pad(k, lk_pad), _pad(v, lk_pad), _pad(mask, lk_pad, value=False))
    return out[:, :lq].astype(q.dtype)
