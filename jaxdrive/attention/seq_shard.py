"""Plumbing shared by the sequence-sharded attentions (:mod:`~jaxdrive.attention.ring`,
:mod:`~jaxdrive.attention.ulysses`): input checks and the mesh layout, padding to whole tiles per
``seq`` chunk, the tile-size rule, and running a per-device kernel under ``shard_map``.

Lengths the ``seq`` axis cannot split are padded: padded keys are masked out through ``kv_mask``
and padded query rows are dropped from the output, so any ``Lq``/``Lk`` works (``Lq != Lk``
included: positions for ``causal_block`` are global indices counted from 0 in each of q and k).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
from jax.sharding import PartitionSpec as P

from jaxdrive import validate
from jaxdrive.attention import softmax_blocks as sb
from jaxdrive.parallel.mesh import BATCH_AXES

HEAD_AXIS = "tensor"


@dataclass(frozen=True)
class Layout:
    """How ``[B, L, H, D]`` arrays are laid out on the mesh for sequence-sharded attention."""

    seq_axis: str
    n: int  # size of the seq axis
    batch_axes: tuple  # mesh axes sharding the batch
    head_axis: str | None  # mesh axis sharding the heads
    heads_per_shard: int  # heads on one tensor shard

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
        raise ValueError(
            f"q: expected a batch size divisible by the batch mesh axes {batch_axes} (size {nb}), got batch {b}"
        )
    head_axis = HEAD_AXIS if HEAD_AXIS in names else None
    nt = sizes[head_axis] if head_axis else 1
    if h % nt:
        raise ValueError(
            f"q: expected a number of heads divisible by the mesh axis {HEAD_AXIS!r} (size {nt}), got {h} heads"
        )
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


# A score tile holds at most 1 / TILE_FRACTION of the elements of a device's query rows, so the
# handful of tiles alive in the backward stay a fraction of the chunk-sized arrays at every ``seq``
# size (fixed 512 x 512 tiles dominate a device's memory once its chunk gets short).
TILE_FRACTION = 16
# Below this many tokens a tile costs more in loop overhead than it saves in memory.
MIN_TILE = 16


def tile_size(rows: int, dim: int, block: int) -> int:
    """Tile length for a device holding ``rows`` query rows per head of head dim ``dim`` (its
    chunk for the ring, the whole sequence for all-to-all): ``block`` halved while a
    ``tile x tile`` score tile has more than ``rows * dim / TILE_FRACTION`` elements, down to
    ``MIN_TILE``. Long chunks get ``block``; short ones get tiles that shrink with them."""
    tile = block
    while tile > MIN_TILE and tile * tile * TILE_FRACTION > rows * dim:
        tile = max(tile // 2, MIN_TILE)
    return tile


def chunk(length: int, n: int) -> int:
    """Tokens per device when ``length`` tokens are split over ``n`` devices (before tile padding)."""
    return -(-length // n)


def pad_to_tiles(q, k, v, kv_mask, n: int, tile: int | None):
    """Pad q and k/v so that every ``seq`` chunk is a whole number of tiles.

    Returns ``(q, k, v, kv_mask, bq, bk, has_mask)``: the tile lengths (``tile``, or the whole
    chunk where it is shorter or ``tile`` is None) and whether the kernel must read the mask;
    ``kv_mask`` is a placeholder of ones where it need not.
    """
    fit = lambda length: chunk(length, n) if tile is None else min(tile, chunk(length, n))
    bq, bk = fit(q.shape[1]), fit(k.shape[1])
    padded = lambda length, t: n * (-(-chunk(length, n) // t) * t)
    lk = padded(k.shape[1], bk)
    has_mask = kv_mask is not None or lk != k.shape[1]
    q, k, v, kv_mask = pad_inputs(q, k, v, kv_mask, n, lq=padded(q.shape[1], bq), lk=lk)
    if kv_mask is None:
        kv_mask = jnp.ones(k.shape[:2], bool)
    return q, k, v, kv_mask, bq, bk, has_mask


def run(kernel, mesh, lay: Layout, q, k, v, kv_mask, length: int, like):
    """``kernel(q, k, v, mask)`` on every device's chunks (``shard_map`` over the layout), then
    :func:`unpad` to ``length`` query rows typed like ``like``."""
    fn = jax.shard_map(
        kernel, mesh=mesh, in_specs=(lay.qkv_spec,) * 3 + (lay.mask_spec,), out_specs=lay.qkv_spec, check_vma=False
    )
    return unpad(fn(*to_specs(mesh, lay, q, k, v, kv_mask)), length, mesh, lay, like=like)
