"""Attention over one (query block, key block) pair, in pieces that merge exactly.

Every memory-efficient and sequence-sharded attention in jaxdrive (blockwise on one device,
ring over the ``seq`` axis, the local kernel of all-to-all) is built from these three pieces:

- :func:`attend_block`: softmax attention of a query block against a key block, returning the
  block-normalised output and the log-sum-exp of each query row's scores;
- :func:`merge`: the online-softmax combination of two such partial results (Milakov &
  Gimelshein 2018; Rabe & Staats 2021; Dao et al. 2022), exact up to rounding;
- :func:`attend_block_grads`: the gradient contribution of one block pair given the *final*
  log-sum-exp and :func:`delta` of the query rows (the FlashAttention backward), so backward
  passes recompute scores block by block instead of storing the ``L x L`` matrix.

Shapes: ``q [B, Lq, H, D]``, ``k, v [B, Lk, H, D]``, outputs ``[B, Lq, H, D]``, log-sum-exp
``[B, H, Lq]``. Scores, probabilities, the softmax statistics and every accumulator are float32;
the matmuls take their operands in the inputs' dtype (bf16 operands, f32 accumulation in a bf16
step: a float32 dot there runs at a fraction of the chip's bf16 rate). Masking: ``kv_mask [B, Lk]`` (True = attend) and
``causal_block = n``: query token i may attend to key token j iff ``j // n <= i // n`` with
``i, j`` global positions (``q_start``/``k_start`` give the block's offset). A query row with no
allowed key gets output 0 and log-sum-exp -inf (never NaN), in every implementation.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

NEG_INF = -jnp.inf


def pad_sequence(x, length: int, value=0):
    """Pad ``x [B, L, ...]`` along the sequence axis to ``length`` with ``value``."""
    extra = length - x.shape[1]
    if extra == 0:
        return x
    return jnp.pad(x, [(0, 0), (0, extra)] + [(0, 0)] * (x.ndim - 2), constant_values=value)


def hidden(q_start, q_len: int, k_start, causal_block):
    """True when causal masking hides keys from ``k_start`` on from all ``q_len`` queries starting
    at ``q_start`` (global positions; may be traced): the key range can be skipped."""
    if causal_block is None:
        return False
    return k_start // causal_block > (q_start + q_len - 1) // causal_block


def allowed(batch: int, lq: int, lk: int, *, kv_mask=None, causal_block=None, q_start=0, k_start=0):
    """Boolean ``[B, 1, Lq, Lk]`` (or broadcastable) mask of allowed (query, key) pairs, or None."""
    mask = None
    if kv_mask is not None:
        mask = jnp.asarray(kv_mask, bool)[:, None, None, :]
    if causal_block is not None:
        qi = (q_start + jnp.arange(lq)) // causal_block
        kj = (k_start + jnp.arange(lk)) // causal_block
        causal = (kj[None, :] <= qi[:, None])[None, None]
        mask = causal if mask is None else mask & causal
    return mask


def _dot(spec: str, a, b):
    """``einsum(spec, a, b)`` accumulated and returned in float32, its operands in the dtype of
    ``b`` (the layer's q / k / v / dO: bfloat16 in a bf16 step): the scores and probabilities stay
    float32 between the matmuls, the matmuls themselves run at the chip's bf16 rate, as a flash
    kernel runs them. For float32 inputs this is the float32 einsum it replaced."""
    return _operand_dtype_dot(spec, a.astype(b.dtype), b)


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _operand_dtype_dot(spec: str, a, b):
    return jnp.einsum(spec, a, b, preferred_element_type=jnp.float32)


def _operand_dtype_dot_fwd(spec, a, b):
    return _operand_dtype_dot(spec, a, b), (a, b)


def _operand_dtype_dot_bwd(spec, res, g):
    # the float32 cotangent enters the transposed dots in the operands' dtype: autodiff would
    # multiply it as float32 against the bf16 operand, a float32 matmul in every backward
    a, b = res
    _, vjp = jax.vjp(lambda a, b: jnp.einsum(spec, a, b), a, b)
    return vjp(g.astype(b.dtype))


_operand_dtype_dot.defvjp(_operand_dtype_dot_fwd, _operand_dtype_dot_bwd)


def _scores(q, k, scale, mask):
    s = _dot("bqhd,bkhd->bhqk", q, k) * scale
    return s if mask is None else jnp.where(mask, s, NEG_INF)


def attend_block(q, k, v, *, scale, kv_mask=None, causal_block=None, q_start=0, k_start=0):
    """``(o [B, Lq, H, D], lse [B, H, Lq])`` of softmax attention restricted to this key block."""
    mask = allowed(
        q.shape[0], q.shape[1], k.shape[1], kv_mask=kv_mask, causal_block=causal_block, q_start=q_start, k_start=k_start
    )
    s = _scores(q, k, scale, mask)
    m = jnp.max(s, axis=-1, keepdims=True)
    m = jnp.where(jnp.isfinite(m), m, 0.0)  # rows with no allowed key
    p = jnp.exp(s - m)
    total = jnp.sum(p, axis=-1, keepdims=True)
    o = _dot("bhqk,bkhd->bqhd", p / jnp.where(total > 0, total, 1.0), v)
    lse = jnp.where(total[..., 0] > 0, m[..., 0] + jnp.log(jnp.where(total[..., 0] > 0, total[..., 0], 1.0)), NEG_INF)
    return o, lse


def merge(o1, lse1, o2, lse2):
    """Combine two partial results over disjoint key sets into the result over their union."""
    lse = jnp.logaddexp(lse1, lse2)
    ref = jnp.where(jnp.isfinite(lse), lse, 0.0)
    w1 = jnp.exp(lse1 - ref)  # 0 where lse1 = -inf
    w2 = jnp.exp(lse2 - ref)
    to_rows = lambda w: jnp.swapaxes(w, 1, 2)[..., None]  # [B, H, Lq] -> [B, Lq, H, 1]
    return o1 * to_rows(w1) + o2 * to_rows(w2), lse


def empty(q):
    """The neutral partial result for ``q``'s rows (no keys seen yet)."""
    # *_like keeps q's sharding type: loop carries started from it match what the loop body makes
    # under an Explicit mesh (a plain jnp.zeros would be unsharded and the carry types would differ)
    lse = jnp.swapaxes(jnp.full_like(q[..., 0], NEG_INF, dtype=jnp.float32), 1, 2)
    return jnp.zeros_like(q, dtype=jnp.float32), lse


def delta(o, do):
    """``rowsum(dO * O)`` of each query row, ``[B, H, Lq]`` float32: the one place the backward
    needs the output. Computed once per query row before the tile loops, so the output itself need
    not stay alive through them."""
    # a fused multiply-and-reduce: as a batched dot, XLA would transpose both operands first
    rows = jnp.sum(do.astype(jnp.float32) * o.astype(jnp.float32), axis=-1)  # [B, Lq, H]
    return jnp.swapaxes(rows, 1, 2)


def attend_block_grads(q, k, v, lse, delta_rows, do, *, scale, kv_mask=None, causal_block=None, q_start=0, k_start=0):
    """``(dq, dk, dv)`` contributed by this (query block, key block) pair.

    ``lse`` is the final log-sum-exp of the query rows over *all* keys, ``delta_rows`` their
    :func:`delta` and ``do`` the output cotangent; summing the contributions over all key blocks
    gives ``dq``, over all query blocks ``dk`` and ``dv``. Float32 results.
    """
    mask = allowed(
        q.shape[0], q.shape[1], k.shape[1], kv_mask=kv_mask, causal_block=causal_block, q_start=q_start, k_start=k_start
    )
    s = _scores(q, k, scale, mask)
    finite = jnp.isfinite(lse)[..., None]
    p = jnp.where(finite, jnp.exp(s - jnp.where(finite, lse[..., None], 0.0)), 0.0)  # [B, H, Lq, Lk]
    dv = _dot("bhqk,bqhd->bkhd", p, do)
    dp = _dot("bqhd,bkhd->bhqk", do, v)
    ds = p * (dp - delta_rows[..., None])
    dq = _dot("bhqk,bkhd->bqhd", ds, k) * scale
    dk = _dot("bhqk,bqhd->bkhd", ds, q) * scale
    return dq, dk, dv
