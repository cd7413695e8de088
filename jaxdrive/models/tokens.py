"""Token layouts under sequence parallelism: merging and splitting axes, reshapes and
transposes into attention sequences that keep an Explicit mesh's sharding, frame pooling.

Under Explicit sharding a reshape must say where the sharded axes go: these helpers change one
axis at a time, or only unsharded axes, so that the sharding of the rest carries over.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import PartitionSpec

from jaxdrive.parallel.mesh import explicit_mesh, spec_of

# Logical names of the DiT's video activations [B, F, S, V, D]: F token frames, S spatial patches
# of one view (the axis sequence parallelism shards), V views.
VIDEO = ("batch", "frames", "tokens", "views", "embed")
TEXT = ("batch", "text_tokens", "embed")


def merge(x, axis: int):
    """Merge ``axis`` and ``axis + 1`` into one. One merge at a time: under Explicit sharding a
    merge whose major axis is sharded (and minor axis not) keeps a block-contiguous sharding."""
    s = x.shape
    return x.reshape(*s[:axis], s[axis] * s[axis + 1], *s[axis + 2 :])


def split(x, axis: int, major: int):
    """Split ``axis`` into ``(major, rest)`` (inverse of :func:`merge`)."""
    s = x.shape
    return x.reshape(*s[:axis], major, s[axis] // major, *s[axis + 1 :])


def reshape(x, shape: Sequence[int]):
    """``x.reshape(shape)`` where only unsharded axes change: the longest common prefix of the two
    shapes keeps its sharding and the rest is unsharded (Explicit mode cannot infer a reshape that
    touches several axes at once)."""
    shape = tuple(int(s) for s in shape)
    if explicit_mesh() is None:
        return x.reshape(shape)
    keep = 0
    while keep < min(x.ndim, len(shape)) and x.shape[keep] == shape[keep]:
        keep += 1
    spec = spec_of(x)
    if any(e is not None for e in spec[keep:]):
        raise ValueError(f"x: reshape {list(x.shape)} -> {list(shape)} would move sharded axes {spec}")
    return jax.lax.reshape(x, shape, out_sharding=PartitionSpec(*spec[:keep], *([None] * (len(shape) - keep))))


def to_sequence(x, order: Sequence[int]):
    """Transpose ``x [B, ...axes..., H, Dh]`` so the axes in ``order`` (indices into x, the sharded
    one first) follow the batch, then merge them into one sequence axis: ``[B, L, H, Dh]``."""
    perm = [0, *order] + [i for i in range(1, x.ndim) if i not in order]
    y = jnp.transpose(x, perm)
    for _ in range(len(order) - 1):
        y = merge(y, 1)
    return y


def from_sequence(y, shape: Sequence[int], order: Sequence[int]):
    """Inverse of :func:`to_sequence` for an array whose pre-transpose shape was ``shape``."""
    sizes = [shape[i] for i in order]
    for i in range(len(order) - 1):
        y = split(y, 1 + i, sizes[i])
    perm = [0, *order] + [i for i in range(1, len(shape)) if i not in order]
    inv = np.argsort(perm).tolist()
    return jnp.transpose(y, inv)


def pool_frames(x, pt: int, axis: int = 1):
    """Mean over groups of ``pt`` consecutive frames along ``axis`` (latent frames -> token frames
    when the patch spans ``pt`` frames)."""
    if pt == 1:
        return x
    return jnp.mean(split(x, axis, x.shape[axis] // pt), axis=axis + 1)
