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

The helpers :func:`layout` (input checks), :func:`pad_inputs`, :func:`to_specs` and :func:`unpad`
are shared with :mod:`jaxdrive.parallel.ulysses`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import jax
import jax.numpy as jnp
from jax.sharding import PartitionSpec as P

from jaxdrive import validate
from jaxdrive.parallel import softmax_blocks as sb
from jaxdrive.parallel.blockwise import tiled_attend, tiled_grads

BATCH_AXES = ("data", "fsdp")
HEAD_AXIS = "tensor"


@dataclass(frozen=True)
class Layout:
    """How ``[B, L, H, D]`` arrays are laid out on the mesh for sequence-sharded attention."""

    seq_axis: str
    n: int                      # size of the seq axis
    batch_axes: tuple           # mesh axes sharding the batch
    head_axis: str | None       # mesh axis sharding the heads
    heads_per_shard: int        # heads on one tensor shard

    @property
    def qkv_spec(self):
        return P(self.batch_axes or None, self.seq_axis, self.head_axis, None)

    @property
    def mask_spec(self):
        return P(self.batch_axes or None, self.seq_axis)


def layout(q, k, v, kv_mask, causal_block, mesh, seq_axis) -> Layout:
    """Check the inputs of a sequence-sharded attention and return its :class:`Layout`."""
    validate.check_ndim("q", q, 4)
    validate.check_ndim("k", k, 4)
    b, _, h, d = q.shape
    validate.check_shape("k", k, [b, None, h, d])
    validate.check_same_shape("v", v, "k", k)
    if kv_mask is not None:
        validate.check_shape("kv_mask", kv_mask, [b, k.shape[1]])
        if jnp.asarray(kv_mask).dtype != jnp.bool_:
            raise ValueError(f"kv_mask: expected dtype bool, got {jnp.asarray(kv_mask).dtype}")
    if causal_block is not None:
        validate.check_positive_int("causal_block", causal_block)
    names = tuple(mesh.axis_names)
    if seq_axis not in names:
        raise ValueError(f"mesh: expected a mesh axis named {seq_axis!r}, got axes {list(names)}")
    sizes = dict(zip(names, mesh.axis_sizes))  # Mesh or AbstractMesh (the context mesh under jit)
    batch_axes = tuple(a for a in BATCH_AXES if a in names)
    nb = 1
    for a in batch_axes:
        nb *= sizes[a]
    if b % nb:
        raise ValueError(f"q: expected a batch size divisible by the batch mesh axes {batch_axes} "
                         f"(size {nb}), got batch {b}")
    head_axis = HEAD_AXIS if HEAD_AXIS in names else None
    nt = sizes[head_axis] if head_axis else 1
    if h % nt:
        raise ValueError(f"q: expected a number of heads divisible by the mesh axis "
                         f"{HEAD_AXIS!r} (size {nt}), got {h} heads")
    return Layout(seq_axis, sizes[seq_axis], batch_axes, head_axis, h // nt)


def pad_inputs(q, k, v, kv_mask, n, *, lq=None, lk=None):
    """Pad q and k/v along the sequence to multiples of ``n`` (or to ``lq``/``lk`` when given);
    the returned mask hides padded keys.

    Returns ``(q, k, v, kv_mask)``; ``kv_mask`` stays None when nothing was padded and none came.
    """
    lq = -(-q.shape[1] // n) * n if lq is None else lq
    lk = -(-k.shape[1] // n) * n if lk is None else lk
    if lk != k.shape[1]:
        if kv_mask is None:
            kv_mask = jnp.ones(k.shape[:2], bool)
        kv_mask = sb.pad_sequence(jnp.asarray(kv_mask, bool), lk, False)
    return sb.pad_sequence(q, lq), sb.pad_sequence(k, lk), sb.pad_sequence(v, lk), kv_mask


def to_specs(mesh, lay: Layout, q, k, v, kv_mask):
    """Reshard (no-op when already so) q, k, v and the mask to the layout's specs."""
    spec = lambda p: jax.sharding.NamedSharding(mesh, p)
    return jax.reshard((q, k, v, kv_mask), (spec(lay.qkv_spec),) * 3 + (spec(lay.mask_spec),))


def unpad(o, length, mesh, lay: Layout, like=None):
    """Drop padded query rows (gathering the sequence first: a ragged length cannot be split),
    then give the output the sharding of ``like`` (the input q's type) when it had one on this
    mesh. Under Explicit axes the transpose of the shard_map demands cotangents typed exactly like
    its out_specs; matching the caller's q makes any use of the output (slicing a size-1 head axis
    included) transpose back to that type."""
    if o.shape[1] != length:
        gathered = P(lay.batch_axes or None, None, lay.head_axis, None)
        o = jax.reshard(o, jax.sharding.NamedSharding(mesh, gathered))[:, :length]
    target = None if like is None else getattr(like, "sharding", None)
    spec = getattr(target, "spec", None)
    if spec is not None and tuple(getattr(target.mesh, "axis_names", ())) == tuple(mesh.axis_names):
        o = jax.reshard(o, jax.sharding.NamedSharding(mesh, spec))
    return o


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

        def grads(t, kc, vc, mc):
            src = (idx - t) % n

            def compute():
                return tiled_grads(q, kc, vc, mc if has_mask else None, o, lse, do, q_start=q_start,
                                   k_start=src * ck, **tiles)
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
