"""The input pipeline's plan (:mod:`jaxdrive.data.pipeline`, its "Choices"): which clips, in which
bucket, on which shard, at which step, for every epoch, in index space and without reading a clip.
Every draw is a seeded generator keyed by what it decides (:func:`seeded_rng` with a ``TAG_*``),
so any batch of any epoch is computed directly: an iterator's state is a batch number."""

from __future__ import annotations

import logging
import threading

import numpy as np

from jaxdrive.data.buckets import Bucket

log = logging.getLogger(__name__)

_INFINITE = 2**62
TAG_PERM, TAG_BUCKET, TAG_ORDER, TAG_SAMPLE, TAG_START, TAG_ROUTE = 1, 2, 3, 4, 5, 6
MAX_AUTO_REPEAT = 1000  # rounds an automatic repeat may take before it gives up (a bucket of tiny probability)


def seeded_rng(*keys: int) -> np.random.Generator:
    """A generator seeded by ``keys`` (the seed, the epoch, a ``TAG_*`` and what else keys the draw)."""
    return np.random.default_rng([int(k) for k in keys])


class BatchPlan:
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
        order = seeded_rng(self.seed, epoch, TAG_PERM, *k).permutation(n)
        u = seeded_rng(self.seed, epoch, TAG_BUCKET, *k).random(n)
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
        kinds = np.asarray(kinds, np.int64)[seeded_rng(self.seed, epoch, TAG_ORDER).permutation(len(kinds))]
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
        return int(seeded_rng(self.seed, epoch, index, TAG_START, bucket).permutation(starts)[occurrence % starts])

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
