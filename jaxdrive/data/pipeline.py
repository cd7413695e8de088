"""The grain input pipeline: random-access clip sources to bucketed, sharded training batches.

    ds = make_pipeline(open_source(path, "train"), buckets={(256, 448, 17): 4, (128, 224, 33): 16},
                       stride=2, views=("CAM_FRONT", "CAM_FRONT_LEFT"), seed=0)
    it = iter(ds); batch = next(it); state = it.get_state()   # it.set_state(state) resumes exactly

Every batch holds one bucket (H, W, F) (Open-Sora / MagicDrive-V2 mixed resolution and length):
``video [B, V, F, H, W, 3]`` float32 in [-1, 1]; ``intrinsics [B, V, 3, 3]`` in pixels of (H, W);
``cam_to_ego [B, V, 4, 4]``; ``ego_to_world [B, F, 4, 4]`` (float32); ``boxes [B, F, N, 7]``,
``box_classes``/``box_ids``/``box_valid [B, F, N]`` (N padded to the batch maximum or
``max_boxes``, padding invalid); ``bev_map [B, F, Hm, Wm, 8]`` uint8; ``waypoints [B, F, 2]`` in
the ego frame of the first sampled frame; ``fps [B]`` = source fps / stride (of the generated
frames, the stride after the head in a mixed-rate clip); ``frame_times [B, F]`` float32 seconds
from the first sampled frame; ``caption`` (list of
str, as other text fields of the clips); ``drop`` {condition: [B] bool} for classifier-free
guidance; ``index [B]`` the source indices; with ``skip_bad_records``, ``bad_records`` (int: the clips
of the batch that stood in for unreadable ones). ``instance_ids`` is not carried.

A source of latent windows (``jaxdrive data encode``, ``source.kind == "windows"``) gives the same
batches with ``latents [B, V, F', h, w, C]`` float32 in place of ``video``: each record is one
training sample, cut, strided and resized when it was encoded, so it is taken whole
(:func:`take_window`; ``stride`` must be 1), with the same planning, shuffling, sharding, drops and
iterator state.

Choices:
- Planning is in index space and global: each epoch, a seeded permutation of all clips, a seeded
  bucket per clip (among the buckets the clip is long enough for, probabilities renormalised),
  shard s taking the clips with ``index % shard_count == s``. A bucket yields, on every shard, the
  same number of batches (the minimum over shards), and the order of buckets is one seeded
  sequence shared by all shards, so all processes feed the same shapes at every step (required to
  assemble global arrays). ``batch_size`` is per process. Leftover clips are dropped and counted
  in the log.
- Repetition (MagicDrive-V2 [2411.13807v3] appendix B, scarce clips repeated within an epoch): a bucket's
  ``repeat`` r takes the clips of r seeded rounds of that draw; by default the fewest rounds that
  fill its batch on every shard, each epoch, so a few clips fill every bucket (a clip then gives
  several samples, at distinct start frames while it has them). Logged once per epoch
  (:class:`jaxdrive.data.batch_plan.BatchPlan`). No repeat helps a bucket that no clip is long enough for: an error.
- Per-sample draws (start frame, crop offset, drop masks, the stride after the head of a mixed-rate
  clip) are seeded by (seed, epoch, index, and the round after the first): the same for any shard
  count.
- Mixed frame rates (MiLA [2503.15875v1] appendix B, stage 2: 12-fps condition frames, generated frames at other
  rates): ``rate_head`` frames at ``stride``, then the rest at one stride per clip drawn uniformly
  from ``rate_strides``; a clip must be long enough for the longest of them. Iterator state is
  grain's (the next batch index), exact on resume.
- Resize and crop: :mod:`jaxdrive.data.resize` (intrinsics adjusted to match exactly).
- Unreadable clips (``skip_bad_records``; a corrupt or truncated ArrayRecord shard): dropping one
  would leave a short batch, or a shard one batch behind the others, and break the invariant above;
  so the slot is filled by the next readable clip of the same shard and bucket in the epoch's
  planned order (:meth:`jaxdrive.data.batch_plan.BatchPlan.substitutes`: the clips after it, the
  epoch's leftovers, then the first ones, wrapping round), sampled with the draws of the slot it
  fills (start frame, crop, drops), so it is not an exact repeat. The choice depends on the plan and
  on which records are unreadable, nothing else: the same on resume and for any number of read
  threads. Each batch carries ``bad_records`` (int, its slots filled so: a count per process), and
  every unreadable file is named once in a warning (:class:`jaxdrive.data.faults.OncePerFile`), not
  once per record. Without it, an unreadable clip raises :class:`BadRecordError` naming the shard
  file.
- Scenes under several routes (a :class:`jaxdrive.data.route_mix.RoutedScenes` source,
  ``data.routes``): each sample reads its scene along a route drawn per (seed, epoch, index,
  round) from a generator of its own, so the same past gets different futures within an epoch
  and the other draws are those of the recorded scenes alone; the batch's ``route`` (list of str)
  names each sample's route. ``route_parting`` (``data.route_parting``): with that probability
  (drawn from the route's generator) a counterfactual sample's window starts where all its
  ``given_frames`` precede the routes' part (the source's ``part_frame``), so the same given
  frames are followed by different futures inside the window; otherwise, and for ``recorded``,
  the window starts at the uniform draw. A clip whose part comes too early for its given frames
  keeps the uniform start.
- Clip frame counts come from ``source.frame_counts`` (the TFDS source stores them) or the
  ``frame_counts`` argument; otherwise every clip is read once at construction (logged).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence

import grain
import numpy as np

from jaxdrive.data.batch_plan import TAG_ROUTE, TAG_SAMPLE, BatchPlan, seeded_rng
from jaxdrive.data.buckets import frame_offsets, parse_buckets
from jaxdrive.data.faults import BadRecordError, OncePerFile
from jaxdrive.data.transforms import clip_warp, collate, sample_clip, take_window
from jaxdrive.validate import check_positive_int, check_probability

log = logging.getLogger(__name__)

CONDITIONS = ("text", "boxes", "map", "trajectory", "camera")
DEFAULT_DROP_PROBS = {name: 0.15 for name in CONDITIONS}


class _LoadBatch:
    """Loads, transforms and collates the clips of one batch spec (picklable for grain workers).

    With ``skip_bad_records``, a clip that cannot be read (:class:`BadRecordError`) is replaced by
    the first readable clip of :meth:`BatchPlan.substitutes`, sampled with the draws of the slot
    it fills; the batch carries ``bad_records``, the number of its slots so filled."""

    def __init__(
        self,
        source,
        plan: BatchPlan,
        *,
        views,
        crop,
        drop_probs,
        max_boxes,
        warp_depth=0.0,
        warp_frame=0,
        skip_bad_records=False,
        route_parting=0.0,
        given_frames=1,
    ):
        self.source, self.plan, self.views, self.crop = source, plan, views, crop
        self.drop_probs, self.max_boxes, self.warp_depth = dict(drop_probs), max_boxes, warp_depth
        self.warp_frame, self.route_parting, self.given_frames = warp_frame, route_parting, given_frames
        self.skip_bad_records = skip_bad_records
        self.routed = callable(getattr(source, "read", None))
        self.bad_files = OncePerFile(log, "its records are skipped and counted in bad_records (data.skip_bad_records)")

    def _get(self, idx: int, route_rng) -> dict:
        """Clip ``idx``; from a source of scenes under several routes
        (:class:`jaxdrive.data.route_mix.RoutedScenes`), along the route ``route_rng`` draws, its
        name in ``"route"``."""
        if route_rng is None:
            return self.source[idx]
        clip, route = self.source.read(idx, route_rng)
        return {**clip, "route": route}

    def _read(self, epoch: int, b: int, idx: int, route_rng=None) -> tuple[int, dict, bool]:
        """``(index read, clip, whether it stands in for idx)``."""
        try:
            return idx, self._get(idx, route_rng), False
        except BadRecordError as e:
            if not self.skip_bad_records:
                raise
            self.bad_files.note(e)
            first = e
        for other in self.plan.substitutes(epoch, b, idx):
            try:
                return int(other), self._get(int(other), route_rng), True
            except BadRecordError as e:
                self.bad_files.note(e)
        raise ValueError(
            f"data.skip_bad_records: no readable clip left to stand in for clip {idx} of bucket "
            f"{self.plan.buckets[b].key} on shard {self.plan.shard_index}/{self.plan.shard_count} "
            f"in epoch {epoch}: every one is unreadable (the first: {first})"
        )

    def _parted_start(self, start: int, starts: int, tail, route_rng) -> int:
        """``start`` or, with probability ``route_parting`` (one draw of ``route_rng`` always), a
        start drawn uniformly among those whose given frames all precede the routes' part."""
        offsets = frame_offsets(self.given_frames, self.plan.stride, self.plan.rate_head, tail)
        latest = min(int(self.source.part_frame) - 1 - int(offsets[-1]), starts - 1)
        if route_rng.random() < self.route_parting and latest >= 0:
            return int(route_rng.integers(0, latest + 1))
        return start

    def __call__(self, spec) -> dict:
        epoch, b, indices, rounds, occurrences = spec
        bucket = self.plan.buckets[b]
        samples, replaced = [], 0
        for j, planned in enumerate(indices):
            # round 0 keeps the keys of a plan without repetition; a later round is a sample of its own
            again = (int(rounds[j]),) if rounds[j] else ()
            rng = seeded_rng(self.plan.seed, epoch, int(planned), TAG_SAMPLE, *again)
            # the route has a generator of its own: the other draws stay those of a plain source
            route_rng = seeded_rng(self.plan.seed, epoch, int(planned), TAG_ROUTE, *again) if self.routed else None
            idx, clip, stand_in = self._read(epoch, b, int(planned), route_rng)
            replaced += stand_in
            T = int(np.shape(clip["ego_to_world"])[0])
            strides = self.plan.rate_strides  # no draw without them: the same samples as before
            tail = int(strides[rng.integers(len(strides))]) if strides else None
            starts = T - self.plan.needed(bucket, tail) + 1
            start = int(rng.integers(0, starts))  # drawn always: the crop and drops draw after it
            if occurrences is not None:
                start = self.plan.start_frame(epoch, b, int(planned), int(occurrences[j]), starts)
            if self.route_parting and clip["route"] != "recorded":
                start = self._parted_start(start, starts, tail, route_rng)
            if "latents" in clip:
                s = take_window(clip, frames=bucket.frames, views=self.views, where=f"source window {idx}")
            else:
                s = sample_clip(
                    clip,
                    size=(bucket.height, bucket.width),
                    frames=bucket.frames,
                    stride=self.plan.stride,
                    start=start,
                    views=self.views,
                    crop=self.crop,
                    rng=rng,
                    where=f"source clip {idx}",
                    head=self.plan.rate_head,
                    tail_stride=tail,
                )
            if self.warp_depth > 0:
                s["warp_video"] = clip_warp(s, self.warp_depth, self.warp_frame)
            s["drop"] = {n: bool(rng.random() < p) for n, p in sorted(self.drop_probs.items())}
            s["index"] = np.int64(idx)
            if self.routed:
                s["route"] = clip["route"]
            samples.append(s)
        batch = collate(samples, max_boxes=self.max_boxes)
        if self.skip_bad_records:
            batch["bad_records"] = np.int64(replaced)
        return batch


def make_pipeline(
    source,
    buckets,
    *,
    stride: int = 1,
    views=None,
    crop: str = "center",
    drop_probs: Mapping[str, float] | None = None,
    max_boxes: int | None = None,
    seed: int = 0,
    num_epochs: int | None = None,
    shard_index: int | None = None,
    shard_count: int | None = None,
    frame_counts: Sequence[int] | None = None,
    num_threads: int = 4,
    prefetch: int = 8,
    compression: int = 4,
    rate_head: int = 0,
    rate_strides: Sequence[int] = (),
    warp_depth: float = 0.0,
    warp_frame: int = 0,
    skip_bad_records: bool = False,
    route_parting: float = 0.0,
    given_frames: int = 1,
) -> grain.IterDataset:
    """A grain ``IterDataset`` of training batches from a random-access clip ``source``.

    ``buckets``: ``{(H, W, F): batch_size}``, ``{(H, W, F): (batch_size, prob)}`` or
    ``{(H, W, F): (batch_size, prob, repeat)}`` with F = 1 + ``compression`` * k; ``repeat``: the
    rounds of clips the bucket takes an epoch, None (the default) the fewest that fill its batch
    (:class:`BatchPlan`). ``views``: indices or camera names (:data:`schema.CAMERAS`), None
    for all. ``drop_probs``: condition -> drop probability (default 0.15 for each of
    :data:`CONDITIONS`). Shards default to ``jax.process_index()`` / ``jax.process_count()``.
    ``num_epochs=None`` repeats forever. ``iter(ds)`` has grain's ``get_state`` / ``set_state``.
    ``rate_head`` / ``rate_strides``: mixed frame rates (module docstring; ``sample_clip``'s
    ``head`` and ``tail_stride``, one tail stride per clip drawn from ``rate_strides``; empty:
    ``stride`` throughout). ``warp_depth`` > 0: each sample also gets ``warp_video``
    (:func:`clip_warp`, LongDWM's warp-guided control) from the sample's frame ``warp_frame``
    (0: the first, LongDWM's). ``skip_bad_records``: an unreadable clip
    (a corrupt or truncated shard) is replaced, not raised, and each batch carries ``bad_records``
    (module docstring); False: it raises :class:`BadRecordError` naming the shard file.
    ``route_parting`` in [0, 1] (a source of scenes under several routes with a ``part_frame``):
    the share of counterfactual samples whose first ``given_frames`` source frames all come before
    the routes part (module docstring).
    """
    parsed = parse_buckets(buckets, compression=compression)
    stride = check_positive_int("stride", stride)
    if getattr(source, "kind", "clips") == "windows" and stride != 1:
        raise ValueError(
            f"stride: expected 1 for a source of latent windows (their frames were strided when encoded), got {stride}"
        )
    rate_head = check_positive_int("rate_head", rate_head, minimum=0)
    rate_strides = tuple(check_positive_int("rate_strides", s) for s in rate_strides)
    if getattr(source, "kind", "clips") == "windows" and rate_strides:
        raise ValueError(
            f"rate_strides: expected () for a source of latent windows (their frames are uniform), got {rate_strides}"
        )
    if shard_index is None or shard_count is None:
        import jax

        shard_index, shard_count = jax.process_index(), jax.process_count()
    shard_count = check_positive_int("shard_count", shard_count)
    if not 0 <= shard_index < shard_count:
        raise ValueError(f"shard_index: expected in [0, {shard_count}), got {shard_index}")
    if num_epochs is not None:
        check_positive_int("num_epochs", num_epochs)
    drop_probs = DEFAULT_DROP_PROBS if drop_probs is None else dict(drop_probs)
    for name, p in drop_probs.items():
        check_probability(f"drop_probs[{name!r}]", p)
    if max_boxes is not None:
        check_positive_int("max_boxes", max_boxes)
    if not (np.isfinite(warp_depth) and warp_depth >= 0):
        raise ValueError(f"warp_depth: expected a depth in metres >= 0 (0: no warped frames), got {warp_depth}")
    if check_positive_int("warp_frame", warp_frame, minimum=0) >= min(b.frames for b in parsed):
        raise ValueError(
            f"warp_frame: expected a frame of every bucket's clip (< {min(b.frames for b in parsed)}), got {warp_frame}"
        )
    if warp_depth > 0 and getattr(source, "kind", "clips") == "windows":
        raise ValueError(f"warp_depth: expected 0 for a source of latent windows (no pixels to warp), got {warp_depth}")
    if len(source) == 0:
        raise ValueError(f"source: expected at least one clip, got an empty {source!r}")
    if frame_counts is None:
        frame_counts = getattr(source, "frame_counts", None)
    if frame_counts is None:
        log.info("reading %d clips once to learn their frame counts (give frame_counts to skip)", len(source))
        frame_counts = [int(np.shape(source[i]["ego_to_world"])[0]) for i in range(len(source))]
    if len(frame_counts) != len(source):
        raise ValueError(f"frame_counts: expected {len(source)} counts (one per clip), got {len(frame_counts)}")
    plan = BatchPlan(
        frame_counts,
        parsed,
        stride=stride,
        seed=seed,
        shard_index=int(shard_index),
        shard_count=shard_count,
        num_epochs=num_epochs,
        rate_head=rate_head,
        rate_strides=rate_strides,
    )
    route_parting = check_probability("route_parting", route_parting)
    if route_parting and getattr(source, "part_frame", None) is None:
        raise ValueError(
            f"route_parting: expected 0 for a source without counterfactual routes that part at a known "
            f"frame (a RoutedScenes of 'jaxdrive data synth --counterfactuals'), got {route_parting} for {source!r}"
        )
    given_frames = check_positive_int("given_frames", given_frames)
    if not isinstance(skip_bad_records, bool):
        raise ValueError(f"skip_bad_records: expected True or False, got {skip_bad_records!r}")
    load = _LoadBatch(
        source,
        plan,
        views=views,
        crop=crop,
        drop_probs=drop_probs,
        max_boxes=max_boxes,
        warp_depth=float(warp_depth),
        warp_frame=int(warp_frame),
        skip_bad_records=skip_bad_records,
        route_parting=route_parting,
        given_frames=given_frames,
    )
    return (
        grain.MapDataset.source(plan)
        .map(load)
        .to_iter_dataset(grain.ReadOptions(num_threads=num_threads, prefetch_buffer_size=prefetch))
    )
