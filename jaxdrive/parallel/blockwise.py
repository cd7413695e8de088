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


def _hidden(i, j, bq, bk, causal_block):
    """True when causal masking hides key block j from every query of query block i."""
    if causal_block is None:
        return False
    return (j * bk) // causal_block > ((i + 1) * bq - 1) // causal_block


@functools.lru_cache(maxsize=None)
def _kernel(scale: float, causal_block, bq: int, bk: int):
    """The custom-VJP kernel for fixed static settings (arrays already padded to the blocks)."""

    def forward(q, k, v, mask):
        kb, vb, mb = _blocks(k, bk), _blocks(v, bk), _blocks(mask, bk)

        def one_query_block(args):
            i, qi = args

            def step(acc, kv):
                j, kj, vj, mj = kv

                def attend():
                    o, lse = sb.attend_block(qi, kj, vj, scale=scale, kv_mask=mj,
                                             causal_block=causal_block, q_start=i * bq, k_start=j * bk)
                    return sb.merge(*acc, o, lse)
                return jax.lax.cond(_hidden(i, j, bq, bk, causal_block), lambda: acc, attend), None

            (o, lse), _ = jax.lax.scan(step, sb.empty(qi), (jnp.arange(kb.shape[0]), kb, vb, mb))
            return o, lse

        qb = _blocks(q, bq)
        o, lse = jax.lax.map(one_query_block, (jnp.arange(qb.shape[0]), qb))
        lse = jnp.moveaxis(lse, 0, 2)                                     # [B, H, nq, bq]
        return _unblocks(o), lse.reshape(lse.shape[:2] + (-1,))

    @jax.custom_vjp
    def kernel(q, k, v, mask):
        return forward(q, k, v, mask)[0]

    def kernel_fwd(q, k, v, mask):
        o, lse = forward(q, k, v, mask)
        return o, (q, k, v, mask, o, lse)

    def kernel_bwd(res, do):
        q, k, v, mask, o, lse = res
        qb, ob, dob = _blocks(q, bq), _blocks(o, bq), _blocks(do, bq)
        lseb = jnp.moveaxis(lse.reshape(lse.shape[:-1] + (-1, bq)), -2, 0)   # [nq, B, H, bq]
        kb, vb, mb = _blocks(k, bk), _blocks(v, bk), _blocks(mask, bk)
        nq = qb.shape[0]

        def key_block(dq_acc, kv):
            j, kj, vj, mj = kv

            def query_block(dkv, qs):
                i, qi, oi, lsei, doi = qs

                def grads():
                    dq, dk, dv = sb.attend_block_grads(qi, kj, vj, oi, lsei, doi, scale=scale, kv_mask=mj,
                                                       causal_block=causal_block, q_start=i * bq,
                                                       k_start=j * bk)
                    return dq, (dkv[0] + dk, dkv[1] + dv)

                def skip():
                    return jnp.zeros(qi.shape, jnp.float32), dkv
                dq, dkv = jax.lax.cond(_hidden(i, j, bq, bk, causal_block), skip, grads)
                return dkv, dq

            zeros = jnp.zeros(kj.shape, jnp.float32)
            (dk, dv), dq = jax.lax.scan(query_block, (zeros, zeros),
                                        (jnp.arange(nq), qb, ob, lseb, dob))
            return dq_acc + dq, (dk, dv)

        dq, (dk, dv) = jax.lax.scan(key_block, jnp.zeros(qb.shape, jnp.float32),
                                    (jnp.arange(kb.shape[0]), kb, vb, mb))
        return (_unblocks(dq).astype(q.dtype), _unblocks(dk).astype(k.dtype),
                _unblocks(dv).astype(v.dtype), None)

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
