"""Memory-efficient attention on one device: O(L) memory forward and backward.

Queries are processed in blocks of ``block_q``; for each, a loop over key blocks of
``block_k`` merges partial softmax results (:mod:`jaxdrive.attention.softmax_blocks`), so at most
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

from jaxdrive.attention import softmax_blocks as sb


def _tile(x, start, size, axis=1):
    return jax.lax.dynamic_slice_in_dim(x, start, size, axis=axis)


def _put(x, tile, start, axis=1):
    return jax.lax.dynamic_update_slice_in_dim(x, _as_carry(tile, x), start, axis=axis)


def _as_carry(new, old):
    """``new`` with the sharding type of the loop carry ``old``: under an Explicit mesh a body that
    mixes operands of other shardings (q batch-replicated, kv_mask batch-sharded) makes a carry of
    another type than it was given, which ``fori_loop`` refuses."""
    want = jax.typeof(old).sharding
    if want.mesh.empty or jax.typeof(new).sharding.spec == want.spec:
        return new
    return jax.sharding.reshard(new, want.spec)


def _fori(lower, upper, body, init):
    return jax.lax.fori_loop(lower, upper, lambda i, c: jax.tree_util.tree_map(_as_carry, body(i, c), c), init)


# The tile loops slice their operands in place (dynamic_slice) and write results into carried
# buffers (dynamic_update_slice) rather than stacking blocked copies: besides the inputs and
# outputs, only one score tile per head and a few tile-sized arrays are alive.


def tiled_attend(q, k, v, mask, *, scale, causal_block, bq, bk, q_start=0, k_start=0, k_step=None, acc=None):
    """``(o [B, Lq, H, D], lse [B, H, Lq])`` over tiles of ``bq x bk`` (lengths multiples of them).

    The building block of :func:`blockwise_attention` and of each ring or all-to-all step.
    ``q_start`` / ``k_start`` (may be traced) are the global positions of the first query and
    key, for causal masking, and ``k_step`` the global distance between the starts of consecutive
    key tiles (``bk`` unless given: contiguous keys); ``mask [B, Lk]`` or None. ``acc`` is a
    partial ``(o, lse)`` over other keys to merge into, tile by tile and in place, so a step adds
    its keys to the running result without a second query-sized array. Float32 results.
    """
    nq, nk = q.shape[1] // bq, k.shape[1] // bk
    k_step = bk if k_step is None else k_step

    def query_tile(i, out):
        qi = _tile(q, i * bq, bq)

        def key_tile(j, acc):
            def attend():
                o, lse = sb.attend_block(
                    qi,
                    _tile(k, j * bk, bk),
                    _tile(v, j * bk, bk),
                    scale=scale,
                    kv_mask=None if mask is None else _tile(mask, j * bk, bk),
                    causal_block=causal_block,
                    q_start=q_start + i * bq,
                    k_start=k_start + j * k_step,
                )
                return sb.merge(*acc, o, lse)

            if causal_block is None:
                return attend()
            hidden = sb.hidden(q_start + i * bq, bq, k_start + j * k_step, causal_block)
            return jax.lax.cond(hidden, lambda: acc, attend)

        start = (_tile(out[0], i * bq, bq), _tile(out[1], i * bq, bq, axis=2))
        o, lse = _fori(0, nk, key_tile, start)
        return _put(out[0], o, i * bq), _put(out[1], lse, i * bq, axis=2)

    return _fori(0, nq, query_tile, sb.empty(q) if acc is None else acc)


def tiled_grads(
    q, k, v, mask, lse, delta, do, *, scale, causal_block, bq, bk, q_start=0, k_start=0, k_step=None, acc=None
):
    """``(dq, dk, dv)`` (float32) of :func:`tiled_attend`'s key range, given the final ``lse`` and
    :func:`~jaxdrive.attention.softmax_blocks.delta` of the query rows over all keys (FlashAttention
    backward, one score tile alive at a time). ``k_step`` as in :func:`tiled_attend`; ``acc``:
    float32 ``(dq, dk, dv)`` to add into in place (a step's running gradients), zeros when None."""
    nq, nk = q.shape[1] // bq, k.shape[1] // bk
    k_step = bk if k_step is None else k_step
    if acc is None:
        acc = tuple(jnp.zeros_like(x, dtype=jnp.float32) for x in (q, k, v))

    def key_tile(j, grads):
        dq, dk, dv = grads
        kj, vj = _tile(k, j * bk, bk), _tile(v, j * bk, bk)
        mj = None if mask is None else _tile(mask, j * bk, bk)

        def query_tile(i, inner):
            dq, dkj, dvj = inner

            def add():
                gq, gk, gv = sb.attend_block_grads(
                    _tile(q, i * bq, bq),
                    kj,
                    vj,
                    _tile(lse, i * bq, bq, axis=2),
                    _tile(delta, i * bq, bq, axis=2),
                    _tile(do, i * bq, bq),
                    scale=scale,
                    kv_mask=mj,
                    causal_block=causal_block,
                    q_start=q_start + i * bq,
                    k_start=k_start + j * k_step,
                )
                return _put(dq, _tile(dq, i * bq, bq) + gq, i * bq), dkj + gk, dvj + gv

            if causal_block is None:
                return add()
            hidden = sb.hidden(q_start + i * bq, bq, k_start + j * k_step, causal_block)
            return jax.lax.cond(hidden, lambda: inner, add)

        start = (dq, _tile(dk, j * bk, bk), _tile(dv, j * bk, bk))
        dq, dkj, dvj = _fori(0, nq, query_tile, start)
        return dq, _put(dk, dkj, j * bk), _put(dv, dvj, j * bk)

    return _fori(0, nk, key_tile, acc)


@functools.cache
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
        dq, dk, dv = tiled_grads(q, k, v, mask, lse, sb.delta(o, do), do, **settings)
        return dq.astype(q.dtype), dk.astype(k.dtype), dv.astype(v.dtype), None

    kernel.defvjp(kernel_fwd, kernel_bwd)
    return kernel


def blockwise_attention(q, k, v, *, scale, kv_mask=None, causal_block=None, block_q: int = 512, block_k: int = 512):
    """Softmax attention ``[B, Lq, H, D]`` in O(L) memory (see the module docstring).

    ``kv_mask [B, Lk]`` (True = attend), ``causal_block`` as in
    :mod:`jaxdrive.attention.softmax_blocks`. Inputs are checked by
    :func:`jaxdrive.attention.attention`; this kernel assumes consistent shapes.
    """
    b, lq = q.shape[:2]
    lk = k.shape[1]
    bq, bk = min(block_q, lq), min(block_k, lk)
    lq_pad, lk_pad = -(-lq // bq) * bq, -(-lk // bk) * bk
    mask = jnp.ones((b, lk), bool) if kv_mask is None else jnp.asarray(kv_mask, bool)
    out = _kernel(float(scale), causal_block, bq, bk)(
        sb.pad_sequence(q, lq_pad),
        sb.pad_sequence(k, lk_pad),
        sb.pad_sequence(v, lk_pad),
        sb.pad_sequence(mask, lk_pad, value=False),
    )
    return out[:, :lq].astype(q.dtype)
