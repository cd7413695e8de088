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
  (:class:`_BatchPlan`). No repeat helps a bucket that no clip is long enough for: an error.
- Per-sample draws (start frame, crop offset, drop masks, the stride after the head of a mixed-rate
  clip) are seeded by (seed, epoch, index, and the round after the first): the same for any shard
  count.
- Mixed frame rates (MiLA [2503.15875v1] appendix B, stage 2: 12-fps condition frames, generated frames at other
  rates): ``rate_head`` frames at ``stride``, then the rest at one stride per clip drawn uniformly
  from ``rate_strides``; a clip must be long enough for the longest of them. Iterator state is
  grain's (the next batch index), exact on resume.
- Resize and crop: :mod:`jaxdrive.data.resize` (intrinsics adjusted to match exactly).
- Unreadable clips (``skip_bad_records``; a corrupt or truncated ArrayRecord shard): dropping
  one would leave a short batch, or a shard one batch behind the others, and break the invariant
  above; so the slot is filled by the next readable clip of the same shard and bucket in the
  epoch's planned order (:meth:`_BatchPlan.substitutes`: the clips after it, the epoch's leftovers,
  then the first ones, wrapping round), sampled with the draws of the slot it fills (start frame,
  crop, drops), so it is not an exact repeat. The choice depends on the plan and on which records
  are unreadable, nothing else: the same on resume and for any number of read threads. Each batch
  carries ``bad_records`` (int, its slots filled so: a count per process), and every unreadable
  file is named once in a warning (:class:`jaxdrive.data.faults.OncePerFile`), not once per
  record. Without it, an unreadable clip raises :class:`BadRecordError` naming the shard file.
- Clip frame counts come from ``source.frame_counts`` (the TFDS source stores them) or the
  ``frame_counts`` argument; otherwise every clip is read once at construction (logged).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Mapping, Sequence

import grain
import numpy as np

from jaxdrive.data import schema
from jaxdrive.data.buckets import Bucket, frame_offsets, parse_buckets
from jaxdrive.data.faults import BadRecordError, OncePerFile
from jaxdrive.data.resize import adjust_intrinsics, resize_crop_labels, resize_crop_video, resize_plan
from jaxdrive.validate import check_positive_int

log = logging.getLogger(__name__)

CONDITIONS = ("text", "boxes", "map", "trajectory", "camera")
DEFAULT_DROP_PROBS = {name: 0.15 for name in CONDITIONS}
_INFINITE = 2**62
_TAG_PERM, _TAG_BUCKET, _TAG_ORDER, _TAG_SAMPLE, _TAG_START = 1, 2, 3, 4, 5
MAX_AUTO_REPEAT = 1000  # rounds an automatic repeat may take before it gives up (a bucket of tiny probability)


# ----------------------------------------------------------------------------- per-clip transforms


def _view_indices(views, num_views: int, where: str) -> np.ndarray:
    if views is None:
        return np.arange(num_views)
    idx = [schema.CAMERAS.index(v) if isinstance(v, str) and v in schema.CAMERAS else v for v in views]
    if any(isinstance(i, str) for i in idx) or any(not 0 <= int(i) < num_views for i in idx):
        raise ValueError(
            f"views: expected indices in [0, {num_views}) or names in {list(schema.CAMERAS)} "
            f"for {where} with {num_views} views, got {list(views)}"
        )
    return np.asarray(idx, np.int64)


def sample_clip(
    clip: Mapping,
    *,
    size: tuple[int, int],
    frames: int,
    stride: int = 1,
    start: int = 0,
    views=None,
    crop: str = "center",
    rng: np.random.Generator | None = None,
    where: str = "clip",
    head: int = 0,
    tail_stride: int | None = None,
    instances: bool = False,
) -> dict:
    """One training sample from a clip: ``frames`` frames from ``start`` every ``stride``, a view
    subset, resized and cropped to ``size`` with intrinsics to match, waypoints re-expressed in
    the ego frame of the first sampled frame.

    Mixed rates (:func:`frame_offsets`): frames ``0 .. head - 1`` every ``stride``, then every
    ``tail_stride`` (``head = 0``: ``tail_stride`` throughout; None: ``stride``). ``frame_times``
    ``[F]`` are seconds from the first sampled frame (source index / clip fps); ``fps`` is the
    clip fps over the stride of the generated part (``tail_stride`` when ``head < frames``).
    ``instances``: also ``instance_ids [V, F, H, W]`` (the synthetic world's per-pixel track ids,
    resized by :func:`resize_crop_labels`); a clip without them is refused."""
    stride = check_positive_int("stride", stride)
    head = check_positive_int("head", head, minimum=0)
    tail = stride if tail_stride is None else check_positive_int("tail_stride", tail_stride)
    T = int(np.shape(clip["ego_to_world"])[0])
    offsets = frame_offsets(frames, stride, head, tail)
    need = int(offsets[-1]) + 1
    if start < 0 or start + need > T:
        rate = f"stride {stride}" if tail == stride else f"stride {stride} ({head} frames) then {tail}"
        raise ValueError(
            f"{where}: {frames} frames at {rate} from frame {start} need "
            f"{need} source frames, but the clip has {T}: the clip length or frame stride "
            f"is too long for this scene"
        )
    t = start + offsets
    v = _view_indices(views, int(np.shape(clip["video"])[0]), where)
    video = np.asarray(clip["video"])[v[:, None], t[None, :]]
    plan = resize_plan(video.shape[-3:-1], size, crop=crop, rng=rng)
    e2w = np.asarray(clip["ego_to_world"], np.float64)[t]
    rel = np.linalg.inv(e2w[0]) @ e2w
    rel[0] = np.eye(4)  # exactly (0, 0) at the first frame, as the schema states
    out = {
        "video": resize_crop_video(video, plan),
        "intrinsics": adjust_intrinsics(np.asarray(clip["intrinsics"])[v], plan),
        "cam_to_ego": np.asarray(clip["cam_to_ego"], np.float32)[v],
        "ego_to_world": e2w.astype(np.float32),
        "waypoints": rel[:, :2, 3].astype(np.float32),
        "fps": np.float32(float(clip["fps"]) / (tail if head < frames else stride)),
        "frame_times": (offsets / float(clip["fps"])).astype(np.float32),
    }
    for name in ("boxes", "box_classes", "box_ids", "box_valid", "bev_map"):
        out[name] = np.asarray(clip[name])[t]
    if instances:
        if "instance_ids" not in clip:
            raise ValueError(
                f"{where}: expected per-pixel instance_ids (synthetic clips have them; nuScenes clips "
                f"do not), got a clip without them"
            )
        out["instance_ids"] = resize_crop_labels(np.asarray(clip["instance_ids"])[v[:, None], t[None, :]], plan)
    for name, value in clip.items():
        if isinstance(value, str):
            out[name] = value
    return out


def take_window(record: Mapping, *, frames: int, views=None, where: str = "window") -> dict:
    """One training sample from a stored latent window (:data:`schema.WINDOW_FIELDS`): a view
    subset of the whole window, shaped and typed as :func:`sample_clip`'s output with
    ``latents`` for ``video``."""
    have = int(np.shape(record["ego_to_world"])[0])
    if have != frames:
        raise ValueError(
            f"{where}: expected a latent window of {frames} frames (the bucket's), got {have}: "
            f"encode the dataset with the frame count you train with"
        )
    v = _view_indices(views, int(np.shape(record["latents"])[0]), where)
    out = {}
    for name, (_, spec) in schema.WINDOW_FIELDS.items():
        value = np.asarray(record[name])
        out[name] = value[v] if spec[0] == "V" else value
    out["fps"] = np.float32(record["fps"])  # stored as float64 by TFDS; sample_clip's dtype
    out["frame_times"] = (np.arange(frames) / float(record["fps"])).astype(np.float32)  # uniform frames
    for name, value in record.items():
        if isinstance(value, str):
            out[name] = value
    return out


def pad_boxes(s: dict, n: int, where: str) -> None:
    """Pad (invalid slots) or cut the box axis to ``n``, keeping valid boxes first; log cuts."""
    valid = s["box_valid"]
    have = valid.shape[1]
    if have > n:
        order = np.argsort(~valid, axis=1, kind="stable")[:, :n]
        lost = int(valid.sum() - np.take_along_axis(valid, order, 1).sum())
        if lost:
            log.warning("%s: dropped %d valid boxes beyond max_boxes=%d", where, lost, n)
        for k in ("boxes", "box_classes", "box_ids", "box_valid"):
            idx = order[..., None] if s[k].ndim == 3 else order
            s[k] = np.take_along_axis(s[k], idx, 1)
    elif have < n:
        for k in ("boxes", "box_classes", "box_ids", "box_valid"):
            pad = [(0, 0)] * s[k].ndim
            pad[1] = (0, n - have)
            s[k] = np.pad(s[k], pad, constant_values=-1 if k in ("box_classes", "box_ids") else 0)


def collate(samples: Sequence[dict], *, max_boxes: int | None = None) -> dict:
    """Stack samples of one bucket into a batch (box slots padded to a common N)."""
    n = max_boxes or max(s["box_valid"].shape[1] for s in samples)
    for i, s in enumerate(samples):
        pad_boxes(s, n, f"sample {i} (index {s.get('index')})")
    batch = {}
    for k, v in samples[0].items():
        if isinstance(v, str):
            batch[k] = [s[k] for s in samples]
        elif isinstance(v, dict):
            batch[k] = {n: np.array([s[k][n] for s in samples]) for n in v}
        else:
            shapes = {np.shape(s[k]) for s in samples}
            if len(shapes) > 1:
                raise ValueError(
                    f"batch field {k!r}: expected one shape within a bucket, got {sorted(shapes)} "
                    f"(indices {[s.get('index') for s in samples]})"
                )
            batch[k] = np.stack([s[k] for s in samples])
    return batch


# ----------------------------------------------------------------------------- planning


def _rng(*keys: int) -> np.random.Generator:
    return np.random.default_rng([int(k) for k in keys])


class _BatchPlan:
    """Random access to batch specs ``(epoch, bucket, source indices, their rounds, their
    occurrences)``: the whole schedule (occurrences: how often the clip came earlier in the
    bucket's epoch; None for a bucket that takes one round).

    Repetition (MagicDrive-V2 [2411.13807v3] appendix B: "due to the limited number of full video clips, we
    repeat this type of data within an epoch"): an epoch draws a bucket for every clip in seeded
    rounds; a bucket of ``repeat`` r takes the clips drawn for it in the first r rounds, so about r
    times its share, a clip drawn for it in two rounds being two samples. Round 0 is the one draw
    of a plan without repetition, so a plan whose buckets all take one round is unchanged. A
    bucket's automatic repeat (``repeat`` None) is, each epoch, the fewest rounds that give it a
    full batch on every shard (1 whenever one round does): a dataset of a few clips still fills
    every bucket. A bucket that takes several rounds gives the j-th sample of a clip the j-th start
    frame of a seeded order of the clip's start frames (:meth:`start_frame`), so the samples of one
    clip differ while it has frames to spare (an image bucket takes several frames of a clip)."""

    def __init__(
        self, frame_counts, buckets, *, stride, seed, shard_index, shard_count, num_epochs, rate_head=0, rate_strides=()
    ):
        self.counts = np.asarray(frame_counts, np.int64)
        self.buckets, self.stride, self.seed = buckets, stride, seed
        self.rate_head, self.rate_strides = rate_head, tuple(rate_strides)
        self.shard_index, self.shard_count, self.num_epochs = shard_index, shard_count, num_epochs
        need = np.array([self.needed(b) for b in buckets])
        self.eligible = self.counts[:, None] >= need[None, :]  # [N, buckets]
        self._lock = threading.Lock()
        self._lengths: list[int] = []
        self._cache: dict[int, tuple] = {}
        self._logged: set[int] = set()
        self._check()

    def needed(self, bucket: Bucket, tail_stride: int | None = None) -> int:
        """Source frames a clip of ``bucket`` spans at ``tail_stride`` after the head (default: the
        longest of ``rate_strides``, which every eligible clip must fit)."""
        if tail_stride is None and self.rate_strides:
            tail_stride = max(self.rate_strides)
        return bucket.needed(self.stride, self.rate_head, tail_stride)

    def _rate(self) -> str:
        if not self.rate_strides:
            return f"stride {self.stride}"
        return f"stride {self.stride} for {self.rate_head} frames then up to {max(self.rate_strides)}"

    def _check(self) -> None:
        n, longest = len(self.counts), int(self.counts.max(initial=0))
        short = int((~self.eligible.any(1)).sum())
        if short:
            log.warning(
                "skipping %d of %d clips: shorter than the %d source frames the shortest bucket needs at %s",
                short,
                n,
                min(self.needed(b) for b in self.buckets),
                self._rate(),
            )
        for i, b in enumerate(self.buckets):  # no repeat can fill these: no clip (on a shard) is long enough
            if b.prob == 0:
                continue
            on_shard = np.bincount(np.flatnonzero(self.eligible[:, i]) % self.shard_count, minlength=self.shard_count)
            if not on_shard.any():
                span = "1 + (F - 1) * stride" if not self.rate_strides else "the mixed-rate span"
                self._refuse(
                    b,
                    f"each clip needs {span} = {self.needed(b)} source frames at {self._rate()}, but "
                    f"the longest of the {n} clips has {longest}: the frame stride or clip length is "
                    f"longer than every scene",
                )
            if b.repeat is None and not on_shard.all():
                s = int(np.argmin(on_shard))
                self._refuse(
                    b,
                    f"expected a clip of at least {self.needed(b)} source frames on every shard, got "
                    f"none on shard {s} of {self.shard_count} (the clips of index % {self.shard_count} "
                    f"== {s}): use more clips or fewer processes",
                )
        got = {b for b, *_ in self._epoch(0)}
        for i, b in enumerate(self.buckets):
            if b.prob > 0 and i not in got:  # only a fixed repeat gets here: an automatic one fills
                self._refuse(
                    b,
                    f"fewer clips were assigned to it ({self._assigned_min(i)} on some shard in epoch "
                    f"0, over its {b.repeat} round(s)) than its batch size {b.batch_size}: use a smaller "
                    f"batch size, a higher probability or repeat (or leave the repeat out: automatic), "
                    f"or more clips",
                )

    @staticmethod
    def _refuse(bucket: Bucket, why: str):
        raise ValueError(f"buckets: bucket (H, W, F) = {bucket.key}: zero samples after bucketing: {why}")

    def _assign(self, epoch: int, round_: int = 0):
        """Global order and bucket of every clip for ``round_`` of ``epoch`` (-1: fits no bucket);
        round 0 has the keys of a plan without repetition."""
        n, k = len(self.counts), (round_,) if round_ else ()
        order = _rng(self.seed, epoch, _TAG_PERM, *k).permutation(n)
        u = _rng(self.seed, epoch, _TAG_BUCKET, *k).random(n)
        p = self.eligible * np.array([b.prob for b in self.buckets])[None, :]
        tot = p.sum(1, keepdims=True)
        cdf = np.cumsum(p / np.where(tot > 0, tot, 1), axis=1)
        bucket = np.minimum((u[:, None] >= cdf).sum(1), len(self.buckets) - 1)
        bucket[tot[:, 0] == 0] = -1
        return order, bucket[order]

    def _assigned_min(self, b: int) -> int:
        pool, _ = self._pool(self._rounds(0)[0], b, self.buckets[b].repeat or 1)
        return int(np.bincount(pool % self.shard_count, minlength=self.shard_count).min())

    def _rounds(self, epoch: int) -> tuple[list, list[int]]:
        """``(draws, repeats)``: the epoch's rounds of :meth:`_assign` and the rounds each bucket
        takes (its ``repeat``, or the automatic count: class docstring)."""
        repeats = [b.repeat or (1 if b.prob == 0 else None) for b in self.buckets]
        have = np.zeros((len(self.buckets), self.shard_count), np.int64)
        draws = []
        while None in repeats or len(draws) < max(repeats):
            k = len(draws)
            if k == MAX_AUTO_REPEAT and None in repeats:  # unlikely: _check found a clip on every shard
                i = repeats.index(None)
                raise ValueError(
                    f"buckets: bucket (H, W, F) = {self.buckets[i].key}: expected a full batch within "
                    f"{MAX_AUTO_REPEAT} automatic repeats in epoch {epoch}, got {have[i].min()} clips "
                    f"on some shard: give it a higher probability or an explicit repeat"
                )
            draws.append(self._assign(epoch, k))
            order, bucket = draws[-1]
            for i, b in enumerate(self.buckets):
                if repeats[i] is None:
                    have[i] += np.bincount(order[bucket == i] % self.shard_count, minlength=self.shard_count)
                    if have[i].min() >= b.batch_size:
                        repeats[i] = k + 1
        return draws, repeats

    @staticmethod
    def _pool(draws: list, b: int, repeat: int) -> tuple[np.ndarray, np.ndarray]:
        """``(clips, rounds)``: the global clips of bucket ``b`` over its first ``repeat`` rounds,
        in planned order, and the round of each."""
        taken = [(order[bucket == b], k) for k, (order, bucket) in enumerate(draws[:repeat])]
        return (
            np.concatenate([c for c, _ in taken]).astype(np.int64),
            np.concatenate([np.full(len(c), k, np.int64) for c, k in taken]),
        )

    def _epoch(self, epoch: int) -> list:
        return self._schedule(epoch)[0]

    def _schedule(self, epoch: int) -> tuple[list, list]:
        """``(batches, mine)``: the epoch's batch specs and, per bucket, this shard's clips in
        planned order (the batches take consecutive runs of it; the leftovers are its tail)."""
        if epoch in self._cache:
            return self._cache[epoch]
        draws, repeats = self._rounds(epoch)
        kinds, dropped = [], 0
        mine = []
        for i, b in enumerate(self.buckets):
            pool, rounds = self._pool(draws, i, repeats[i])
            shard = pool % self.shard_count
            per_shard = np.bincount(shard, minlength=self.shard_count)
            nb = int(per_shard.min()) // b.batch_size
            kinds += [i] * nb
            here = shard == self.shard_index
            mine.append((pool[here], rounds[here], _occurrences(pool[here]) if repeats[i] > 1 else None))
            dropped += int(per_shard[self.shard_index]) - nb * b.batch_size
        kinds = np.asarray(kinds, np.int64)[_rng(self.seed, epoch, _TAG_ORDER).permutation(len(kinds))]
        used = [0] * len(self.buckets)
        batches = []
        for i in kinds:
            bs, u = self.buckets[i].batch_size, used[i]
            clips, rounds, occ = mine[i]
            batches.append((int(i), clips[u : u + bs], rounds[u : u + bs], None if occ is None else occ[u : u + bs]))
            used[i] += bs
        if dropped:  # the same count every epoch: said once at INFO (the CLI shows INFO), then DEBUG
            (log.info if epoch == 0 else log.debug)(
                "epoch %d shard %d/%d: %d clips left over after batching (not used this epoch)",
                epoch,
                self.shard_index,
                self.shard_count,
                dropped,
            )
        self._log_repeats(epoch, repeats)
        if len(self._cache) > 4:
            self._cache.pop(min(self._cache))
        self._cache[epoch] = batches, [clips for clips, _, _ in mine]
        return self._cache[epoch]

    def _log_repeats(self, epoch: int, repeats: list[int]) -> None:
        """Each bucket's repeat, once per epoch: INFO when a bucket repeats, else DEBUG."""
        if epoch in self._logged:
            return
        self._logged.add(epoch)
        said = ", ".join(
            f"{'x'.join(map(str, b.key))} {r}{'' if b.repeat else ' (auto)'}" for b, r in zip(self.buckets, repeats)
        )
        (log.info if max(repeats) > 1 else log.debug)("epoch %d: bucket repeats (rounds of clips): %s", epoch, said)

    def start_frame(self, epoch: int, bucket: int, index: int, occurrence: int, starts: int) -> int:
        """The start frame of the ``occurrence``-th sample of clip ``index`` in ``bucket`` of a
        repeating bucket: that place in a seeded order of the clip's ``starts`` start frames
        (distinct while it has them, then round again)."""
        return int(_rng(self.seed, epoch, index, _TAG_START, bucket).permutation(starts)[occurrence % starts])

    def substitutes(self, epoch: int, bucket: int, index: int) -> np.ndarray:
        """The clips that may stand in for an unreadable clip ``index`` of ``bucket`` in ``epoch``:
        the other clips this shard holds for that bucket in that epoch, in planned order from the one
        after ``index`` (the epoch's leftovers, then its first batches), so the choice depends on
        the plan alone."""
        with self._lock:
            mine = self._schedule(epoch)[1][bucket]
        at = int(np.flatnonzero(mine == index)[0])
        rest = np.concatenate([mine[at + 1 :], mine[:at]])
        return rest[rest != index]  # a repeating bucket holds a clip more than once

    def __len__(self) -> int:
        if self.num_epochs is None:
            return _INFINITE
        with self._lock:
            return sum(len(self._epoch(e)) for e in range(self.num_epochs))

    def __getitem__(self, j: int):
        j = int(j)
        with self._lock:
            epoch = 0
            while True:
                if epoch == len(self._lengths):
                    self._lengths.append(len(self._epoch(epoch)))
                if j < self._lengths[epoch]:
                    return (epoch, *self._epoch(epoch)[j])
                j -= self._lengths[epoch]
                epoch += 1

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_lock"], state["_cache"] = None, {}
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._lock = threading.Lock()


def _occurrences(clips: np.ndarray) -> np.ndarray:
    """For each entry, how many times its clip came earlier in ``clips``."""
    order = np.argsort(clips, kind="stable")
    first = np.r_[True, clips[order][1:] != clips[order][:-1]]
    run_start = np.maximum.accumulate(np.where(first, np.arange(len(clips)), 0))
    out = np.empty(len(clips), np.int64)
    out[order] = np.arange(len(clips)) - run_start
    return out


def clip_warp(sample: Mapping, depth: float) -> np.ndarray:
    """LongDWM's warped frames of a training sample (sec. 3.4: from the clip's own future poses, so
    the model learns to correct the warp's distortions): its first frame of every view warped
    along the sample's ego poses at one ``depth``, holes inpainted on the host
    (:func:`jaxdrive.warp.warp_views`): ``[V, F, H, W, 3]`` in [-1, 1] like ``video``."""
    from jaxdrive.warp import warp_views

    e2w = np.asarray(sample["ego_to_world"], np.float64)
    poses = np.linalg.inv(e2w[0]) @ e2w
    return warp_views(
        np.asarray(sample["video"])[:, 0],
        np.asarray(sample["intrinsics"]),
        np.asarray(sample["cam_to_ego"]),
        poses.astype(np.float32),
        depth,
    )


class _LoadBatch:
    """Loads, transforms and collates the clips of one batch spec (picklable for grain workers).

    With ``skip_bad_records``, a clip that cannot be read (:class:`BadRecordError`) is replaced by
    the first readable clip of :meth:`_BatchPlan.substitutes`, sampled with the draws of the slot
    it fills; the batch carries ``bad_records``, the number of its slots so filled."""

    def __init__(
        self, source, plan: _BatchPlan, *, views, crop, drop_probs, max_boxes, warp_depth=0.0, skip_bad_records=False
    ):
        self.source, self.plan, self.views, self.crop = source, plan, views, crop
        self.drop_probs, self.max_boxes, self.warp_depth = dict(drop_probs), max_boxes, warp_depth
        self.skip_bad_records = skip_bad_records
        self.bad_files = OncePerFile(log, "its records are skipped and counted in bad_records (data.skip_bad_records)")

    def _read(self, epoch: int, b: int, idx: int) -> tuple[int, dict, bool]:
        """``(index read, clip, whether it stands in for idx)``."""
        try:
            return idx, self.source[idx], False
        except BadRecordError as e:
            if not self.skip_bad_records:
                raise
            self.bad_files.note(e)
            first = e
        for other in self.plan.substitutes(epoch, b, idx):
            try:
                return int(other), self.source[int(other)], True
            except BadRecordError as e:
                self.bad_files.note(e)
        raise ValueError(
            f"data.skip_bad_records: no readable clip left to stand in for clip {idx} of bucket "
            f"{self.plan.buckets[b].key} on shard {self.plan.shard_index}/{self.plan.shard_count} "
            f"in epoch {epoch}: every one is unreadable (the first: {first})"
        )

    def __call__(self, spec) -> dict:
        epoch, b, indices, rounds, occurrences = spec
        bucket = self.plan.buckets[b]
        samples, replaced = [], 0
        for j, planned in enumerate(indices):
            # round 0 keeps the keys of a plan without repetition; a later round is a sample of its own
            rng = _rng(self.plan.seed, epoch, int(planned), _TAG_SAMPLE, *((int(rounds[j]),) if rounds[j] else ()))
            idx, clip, stand_in = self._read(epoch, b, int(planned))
            replaced += stand_in
            T = int(np.shape(clip["ego_to_world"])[0])
            strides = self.plan.rate_strides  # no draw without them: the same samples as before
            tail = int(strides[rng.integers(len(strides))]) if strides else None
            starts = T - self.plan.needed(bucket, tail) + 1
            start = int(rng.integers(0, starts))  # drawn always: the crop and drops draw after it
            if occurrences is not None:
                start = self.plan.start_frame(epoch, b, int(planned), int(occurrences[j]), starts)
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
                s["warp_video"] = clip_warp(s, self.warp_depth)
            s["drop"] = {n: bool(rng.random() < p) for n, p in sorted(self.drop_probs.items())}
            s["index"] = np.int64(idx)
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
    skip_bad_records: bool = False,
) -> grain.IterDataset:
    """A grain ``IterDataset`` of training batches from a random-access clip ``source``.

    ``buckets``: ``{(H, W, F): batch_size}``, ``{(H, W, F): (batch_size, prob)}`` or
    ``{(H, W, F): (batch_size, prob, repeat)}`` with F = 1 + ``compression`` * k; ``repeat``: the
    rounds of clips the bucket takes an epoch, None (the default) the fewest that fill its batch
    (:class:`_BatchPlan`). ``views``: indices or camera names (:data:`schema.CAMERAS`), None
    for all. ``drop_probs``: condition -> drop probability (default 0.15 for each of
    :data:`CONDITIONS`). Shards default to ``jax.process_index()`` / ``jax.process_count()``.
    ``num_epochs=None`` repeats forever. ``iter(ds)`` has grain's ``get_state`` / ``set_state``.
    ``rate_head`` / ``rate_strides``: mixed frame rates (module docstring; ``sample_clip``'s
    ``head`` and ``tail_stride``, one tail stride per clip drawn from ``rate_strides``; empty:
    ``stride`` throughout). ``warp_depth`` > 0: each sample also gets ``warp_video``
    (:func:`clip_warp`, LongDWM's warp-guided control). ``skip_bad_records``: an unreadable clip
    (a corrupt or truncated shard) is replaced, not raised, and each batch carries ``bad_records``
    (module docstring); False: it raises :class:`BadRecordError` naming the shard file.
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
        if not (isinstance(p, (int, float)) and 0 <= p <= 1):
            raise ValueError(f"drop_probs[{name!r}]: expected a probability in [0, 1], got {p!r}")
    if max_boxes is not None:
        check_positive_int("max_boxes", max_boxes)
    if not (np.isfinite(warp_depth) and warp_depth >= 0):
        raise ValueError(f"warp_depth: expected a depth in metres >= 0 (0: no warped frames), got {warp_depth}")
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
    plan = _BatchPlan(
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
        skip_bad_records=skip_bad_records,
    )
    return (
        grain.MapDataset.source(plan)
        .map(load)
        .to_iter_dataset(grain.ReadOptions(num_threads=num_threads, prefetch_buffer_size=prefetch))
    )
