"""A function over host items in batches, each batch split over the mesh's batch axes: what the
evaluation networks' features (:mod:`jaxdrive.eval.features`) and the segmenter's classes
(:func:`jaxdrive.models.segmenter.predict`) are computed with.
"""

from __future__ import annotations

import jax
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from jaxdrive.parallel.mesh import batch_axes, batch_shards
from jaxdrive.validate import check_positive_int


def extract(fn, params, items, *, batch_size: int = 16, mesh=None) -> np.ndarray:
    """``fn(params, batch)`` over ``items [N, ...]`` in batches of ``batch_size`` -> ``[N, D]``.

    With a ``mesh`` each batch is padded to a multiple of the ``data`` x ``fsdp`` axes and split
    over them (the parameters replicated), so every device extracts its share; the padding's
    features are dropped."""
    check_positive_int("batch_size", batch_size)
    items = np.asarray(items)
    shards, sharding = 1, None
    if mesh is not None:
        shards = batch_shards(mesh)
        sharding = NamedSharding(mesh, P(batch_axes(mesh) or None))
    step = -(-batch_size // shards) * shards
    out = []
    for lo in range(0, len(items), step):
        batch = items[lo : lo + step]
        n = len(batch)
        if n % shards:
            batch = np.concatenate([batch, np.repeat(batch[-1:], shards - n % shards, 0)])
        x = jax.device_put(batch, sharding) if sharding is not None else batch
        out.append(np.asarray(fn(params, x))[:n])
    return np.concatenate(out) if out else np.zeros((0, 0), np.float32)
