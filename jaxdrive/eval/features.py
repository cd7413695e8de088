"""Feature extraction in batches, each batch sharded over the mesh's batch axes, into streamed
statistics: what FID (Inception features of frames) and FVD (I3D logits of 16-frame windows) read.
"""

from __future__ import annotations

from jaxdrive.eval.fid import FeatureStats
from jaxdrive.parallel.batches import extract  # noqa: F401  (its old home; the segmenter's inference uses it too)


def stats_of(fn, params, items, *, dim: int, batch_size: int = 16, mesh=None) -> FeatureStats:
    """:class:`FeatureStats` of ``fn``'s features of ``items`` (extracted as :func:`extract`)."""
    stats = FeatureStats(dim)
    for lo in range(0, len(items), 8 * batch_size):  # bounded host memory for long streams
        stats.add(extract(fn, params, items[lo : lo + 8 * batch_size], batch_size=batch_size, mesh=mesh))
    return stats
