"""Pallas splash attention (TPU), adapted to jaxdrive's masks and layout.

JAX's splash kernel (``jax.experimental.pallas.ops.tpu.splash_attention``) computes block-sparse
flash attention with its own forward and backward kernels on TPU. jaxdrive maps its arguments
onto it:

- layout ``[B, L, H, D]`` -> the kernel's ``[H, L, D]``, vmapped over the batch; the kernel does
  not scale the logits, so ``q`` is multiplied by ``scale`` first;
- ``causal_block = n`` -> a computable block-causal mask (``k // n <= q // n``), evaluated in the
  kernel, never materialised as an ``L x L`` array;
- ``kv_mask [B, Lk]`` -> segment ids (valid keys in segment 0, masked keys in segment 1, queries
  in segment 0);
- lengths are padded to the tile size (padded keys masked), and query rows with no allowed key
  return 0 like every jaxdrive attention (the kernel's finite mask value would otherwise average
  the masked keys).

On a mesh the kernel runs inside ``shard_map``: a Mosaic kernel is one custom call that XLA
cannot partition, so each device calls it on its own examples (the batch split over ``data`` x
``fsdp``) and heads (split over ``tensor``), with the whole key sequence. Without a causal mask a
query sequence sharded over ``seq`` stays sharded (each device's rows against all keys: the video
queries of a text cross-attention); with one, a ``seq``-sharded input is gathered first (on a
``seq`` mesh ``"auto"`` picks the ring kernel instead). An axis that does not divide the batch or
the heads is left unsplit there. The output keeps q's sharding.

``interpret=True`` runs the same kernel through the Pallas interpreter on any backend: that is
how the CPU tests check it against dense attention, sharded on fake CPU devices too.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import PartitionSpec as P

from jaxdrive.attention.softmax_blocks import pad_sequence
from jaxdrive.parallel.mesh import BATCH_AXES, context_mesh, mesh_platform, spec_of

HEAD_AXIS = "tensor"


def available(mesh=None) -> bool:
    """Splash compiles for TPUs only (elsewhere it runs through the interpreter, for tests): the
    devices of ``mesh`` (default the context mesh, else the default backend) are TPUs."""
    return mesh_platform(mesh) == "tpu"


@functools.cache
def _block_causal_mask(shape: tuple[int, int], block: int):
    from jax.experimental.pallas.ops.tpu.splash_attention import splash_attention_mask as masks

    class BlockCausalMask(masks._ComputableMask):  # the kernel evaluates mask_function per tile
        def __init__(self):
            def mask_function(q_ids, kv_ids):
                return kv_ids // block <= q_ids // block

            super().__init__(shape=shape, mask_function=mask_function)

        def __eq__(self, other):
            return isinstance(other, BlockCausalMask) and other.shape == self.shape

        def __hash__(self):
            return hash(("jaxdrive.BlockCausalMask", shape, block))

    return BlockCausalMask()


@functools.cache
def _kernel(shape: tuple[int, int], heads: int, causal_block, tile_q: int, tile_k: int, interpret: bool):
    from jax.experimental.pallas.ops.tpu.splash_attention import splash_attention_kernel as splash
    from jax.experimental.pallas.ops.tpu.splash_attention import splash_attention_mask as masks

    one = masks.FullMask(shape) if causal_block is None else _block_causal_mask(shape, causal_block)
    blocks = splash.BlockSizes(
        block_q=tile_q,
        block_kv=tile_k,
        block_kv_compute=tile_k,
        block_q_dkv=tile_q,
        block_kv_dkv=tile_k,
        block_kv_dkv_compute=tile_k,
        block_q_dq=tile_q,
        block_kv_dq=tile_k,
    )
    return splash.make_splash_mha(
        masks.MultiHeadMask([one] * heads), block_sizes=blocks, head_shards=1, q_seq_shards=1, interpret=interpret
    )


def _has_key(kv_mask, lq: int, causal_block):
    """``[B, Lq]``: whether query row i has any allowed key."""
    if causal_block is None:
        return jnp.broadcast_to(jnp.any(kv_mask, axis=1, keepdims=True), (kv_mask.shape[0], lq))
    seen = jnp.cumsum(kv_mask, axis=1)  # allowed keys so far
    last = np.minimum((np.arange(lq) // causal_block + 1) * causal_block, kv_mask.shape[1]) - 1
    return seen[:, last] > 0


def _local(q, k, v, mask, *, scale, causal_block, tile, interpret):
    """The kernel on one device's ``[b, L, h, D]`` arrays (``mask [b, Lk]``, bool)."""
    from jax.experimental.pallas.ops.tpu.splash_attention import splash_attention_kernel as splash

    b, lq, h, _ = q.shape
    lk = k.shape[1]
    tile_q, tile_k = min(tile, -(-lq // 128) * 128), min(tile, -(-lk // 128) * 128)
    lq_pad, lk_pad = -(-lq // tile_q) * tile_q, -(-lk // tile_k) * tile_k
    heads_first = lambda x: jnp.swapaxes(x, 1, 2)  # [B, L, H, D] -> [B, H, L, D]
    qh = heads_first(pad_sequence(q * jnp.asarray(scale, q.dtype), lq_pad))
    kh, vh = heads_first(pad_sequence(k, lk_pad)), heads_first(pad_sequence(v, lk_pad))
    segments = splash.SegmentIds(
        q=jnp.zeros((b, lq_pad), jnp.int32), kv=jnp.where(pad_sequence(mask, lk_pad), 0, 1).astype(jnp.int32)
    )
    kernel = _kernel((lq_pad, lk_pad), h, causal_block, tile_q, tile_k, interpret)
    out = jax.vmap(lambda q, k, v, s: kernel(q, k, v, segment_ids=s))(qh, kh, vh, segments)
    out = jnp.swapaxes(out, 1, 2)[:, :lq]
    return jnp.where(_has_key(mask, lq, causal_block)[:, :, None, None], out, 0).astype(q.dtype)


def _split(mesh, b: int, h: int):
    """``(batch axes, head axis)`` of ``mesh`` that divide ``b`` examples and ``h`` heads."""
    sizes = dict(zip(mesh.axis_names, mesh.axis_sizes))
    batch = tuple(a for a in BATCH_AXES if a in sizes)
    if b % math.prod(sizes[a] for a in batch):
        batch = ()
    head = HEAD_AXIS if HEAD_AXIS in sizes and h % sizes[HEAD_AXIS] == 0 else None
    return batch, head


def splash_attention(
    q, k, v, *, scale, kv_mask=None, causal_block=None, tile: int = 512, interpret: bool = False, mesh=None
):
    """Softmax attention ``[B, Lq, H, D]`` through the splash kernel (see the module docstring);
    ``mesh`` defaults to the context mesh (none: one call over the whole arrays)."""
    mask = jnp.ones(k.shape[:2], bool) if kv_mask is None else jnp.asarray(kv_mask, bool)
    local = functools.partial(_local, scale=scale, causal_block=causal_block, tile=tile, interpret=interpret)
    mesh = context_mesh() if mesh is None else mesh
    if mesh is None:
        return local(q, k, v, mask)
    # a one-device mesh too goes through shard_map: under Explicit axes q is typed over the batch
    # axes even at size 1, and the kernel's vmap refuses operands typed apart (the mask's ids)
    batch, head = _split(mesh, q.shape[0], q.shape[2])
    like = spec_of(q)
    # without a causal mask every query row attends to the same whole keys, so a query sequence
    # sharded over `seq` (the video tokens of a text cross-attention) stays so: each device runs
    # its own rows, nothing of q is gathered
    rows = like[1] if causal_block is None else None
    if rows is not None and set((rows,) if isinstance(rows, str) else rows) & {*batch, head}:
        rows = None  # an axis already splitting the batch or the heads cannot split the rows too
    q_spec, kv_spec, mask_spec = (
        P(batch or None, rows, head, None),
        P(batch or None, None, head, None),
        P(batch or None, None),
    )
    named = lambda spec: jax.sharding.NamedSharding(mesh, spec)
    q, k, v, mask = jax.reshard((q, k, v, mask), (named(q_spec), named(kv_spec), named(kv_spec), named(mask_spec)))
    fn = jax.shard_map(
        local, mesh=mesh, in_specs=(q_spec, kv_spec, kv_spec, mask_spec), out_specs=q_spec, check_vma=False
    )
    out = fn(q, k, v, mask)
    return out if tuple(like) == tuple(q_spec) else jax.reshard(out, named(P(*like)))
