"""LongDWM's fine pass in groups of segments (LongDWM [2506.01546v1] sec. 3.2 and inference: the fine model fills
every segment between consecutive keyframes, both ends pinned, segments stacked on the batch).

Stacking every segment in one sampler call is the fewest sequential calls, but its device memory
grows with the length (a minute of video on the tiny models: about 5x the memory of 12 s). The
default, ``segment_batch="auto"``, takes the largest group whose compiled fine call fits a
per-device budget (:func:`jaxdrive.parallel.memory.device_budget`: ``--device-memory``, else the
device's free memory), chosen before anything runs from the compiled programs' own memory
analysis (nothing is sampled to find it), so the memory of a long video stays that of the group
whatever its length. On a CPU without ``--device-memory`` it is the smallest group: a CPU runs a
batched call about as fast as its members one by one (``jaxdrive bench longvideo``).
"""

from __future__ import annotations

import math

import jax
import numpy as np

from jaxdrive import flow
from jaxdrive.generate.windows import Horizon, WindowModel, abstract_on_mesh, window_controls
from jaxdrive.models.dit.conditions import Conditions
from jaxdrive.parallel.memory import device_budget, footprint_bytes, shard_bytes
from jaxdrive.parallel.mesh import batch_shards
from jaxdrive.validate import check_positive_int

AUTO = "auto"


def fine_group(fine: WindowModel, horizon: Horizon, group, controls: Conditions, *, given: int, warp=None):
    """The fine call of the segments in ``group`` (indices): their horizon positions, and its host
    inputs ``(x, cond_mask, controls)`` with the segments stacked on the batch axis. Both ends
    are pinned; the first segment also keeps every given frame."""
    seg, b = fine.window - 1, horizon.latents.shape[0]
    idx = [np.arange(i * seg, i * seg + fine.window) for i in group]
    x = np.concatenate([horizon.latents[:, :, i] for i in idx], axis=0)
    n_cond = np.concatenate([np.full(b, given if i == 0 else 1) for i in group])
    cond, _ = flow.pattern_masks("ends", fine.window, n_cond)
    ctrl = [window_controls(fine, horizon, i, controls, warp=warp) for i in idx]
    ctrl = jax.tree_util.tree_map(lambda *v: np.concatenate([np.asarray(a) for a in v], axis=0), *ctrl)
    return idx, (x, np.asarray(cond), ctrl)


def check_segment_batch(segment_batch):
    """``"auto"`` or a positive int; ``ValueError`` naming ``segment_batch`` otherwise."""
    if segment_batch == AUTO or segment_batch is None:
        return AUTO
    if isinstance(segment_batch, str) and segment_batch.strip().isdigit():
        segment_batch = int(segment_batch)
    if isinstance(segment_batch, bool) or not isinstance(segment_batch, (int, np.integer)) or segment_batch < 1:
        raise ValueError(
            f"segment_batch: expected 'auto' or a positive number of segments per fine call, got {segment_batch!r}"
        )
    return int(segment_batch)


def choose_segment_batch(
    fine: WindowModel,
    horizon: Horizon,
    controls: Conditions,
    segments: int,
    *,
    given: int,
    key,
    tracker,
    mesh=None,
    warp=None,
    device_memory=None,
) -> dict:
    """The largest number of segments per fine call whose compiled call fits the per-device
    budget (``device_memory``, else :func:`device_budget`'s default), and what decided it:
    ``segment_batch``, ``segments``, ``budget_bytes``, ``budget_source``, ``footprint_bytes`` (of
    the chosen call, per device) and ``probed`` (``{group: footprint}`` of every call compiled
    to find it). Groups are multiples of what keeps the batch evenly sharded, or all segments.
    Memory grows with the group, so a line through the smallest and the largest group predicts
    the answer and a walk from there confirms it (a few compiles; the chosen one is reused by the
    run). Without ``device_memory`` on a CPU (no hard budget) it is the smallest group. ``ValueError``
    naming ``device_memory`` when not even the smallest group fits."""
    check_positive_int("segments", segments)
    b = horizon.latents.shape[0]
    shards = batch_shards(mesh)
    unit = shards // math.gcd(shards, b)  # segments whose clips fill every batch shard
    groups = sorted(set(range(unit, segments + 1, unit)) | {segments})
    # the fine params already on a device are arguments of the call: free memory counts them once
    params_bytes = sum(
        shard_bytes(x) if isinstance(x, jax.Array) else np.asarray(x).nbytes
        for x in jax.tree_util.tree_leaves(fine.params)
    )
    budget, source, strict = device_budget(device_memory, counted_bytes=params_bytes)
    _, one = fine_group(fine, horizon, [0], controls, given=given, warp=warp)
    probed: dict[int, int] = {}

    def footprint(n: int) -> int:
        if n not in probed:
            args = (abstract_on_mesh(fine.params, mesh), *abstract_on_mesh(one, mesh, batch=n))
            compiled = tracker.compiled(fine, *args, key, probe=True)  # as the run's call: to_mesh(...)
            probed[n] = footprint_bytes(compiled) or 0  # no analysis: nothing to bound by
        return probed[n]

    lo, hi = groups[0], groups[-1]
    if not strict:  # a CPU: a batched call runs no faster there than its segments one by one
        best = lo
    elif footprint(lo) > budget:
        raise ValueError(
            f"device_memory: expected a budget that holds one fine call of {lo} segment(s) "
            f"({footprint(lo)} bytes per device), got {budget} bytes ({source})"
        )
    elif footprint(hi) <= budget:
        best = hi
    else:  # memory is about linear in the group
        slope = (footprint(hi) - footprint(lo)) / (hi - lo)
        guess = lo + (budget - footprint(lo)) / max(slope, 1)
        i = max(j for j, g in enumerate(groups) if g <= max(guess, lo))
        while i > 0 and footprint(groups[i]) > budget:
            i -= 1
        while i + 1 < len(groups) and footprint(groups[i + 1]) <= budget:
            i += 1
        best = groups[i]
    return {
        "segment_batch": best,
        "segments": segments,
        "budget_bytes": int(budget),
        "budget_source": source,
        "footprint_bytes": footprint(best),
        "probed": {str(k): v for k, v in sorted(probed.items())},
    }
