import re

import numpy as np
import pytest
from test_tfds_io import random_clip

from jaxdrive.data import pipeline, resize, schema, tfds_io, transforms
from jaxdrive.data.batch_plan import BatchPlan
from jaxdrive.data.buckets import Bucket, frame_offsets, frames_for, parse_buckets


def make_clips(n=24, V=3, H=12, W=20, base_frames=9, seed=0):
    """Clips of 9.. frames with a moving ego (pure translation along x plus a yaw)."""
    clips = []
    for i in range(n):
        F = base_frames + i % 8
        c = random_clip(seed + i, V=V, F=F, H=H, W=W, N=2 + i % 3, instance_ids=False)
        yaw = 0.1 * np.arange(F)
        e2w = np.tile(np.eye(4), (F, 1, 1))
        e2w[:, 0, 0], e2w[:, 0, 1], e2w[:, 1, 0], e2w[:, 1, 1] = np.cos(yaw), -np.sin(yaw), np.sin(yaw), np.cos(yaw)
        e2w[:, 0, 3], e2w[:, 1, 3] = 100.0 + 2.0 * np.arange(F), 50.0
        c["ego_to_world"] = e2w
        c["intrinsics"] = np.tile(np.array([[20, 0, W / 2], [0, 20, H / 2], [0, 0, 1]], np.float32), (V, 1, 1))
        clips.append(c)
    return clips


CLIPS = make_clips()
BUCKETS = {(8, 8, 5): 2, (4, 6, 9): (3, 0.5)}


def batches(n, **kw):
    kw = {"buckets": BUCKETS, "seed": 3, "shard_index": 0, "shard_count": 1, "num_threads": 2, **kw}
    it = iter(pipeline.make_pipeline(kw.pop("source", CLIPS), **kw))
    return [next(it) for _ in range(n)]


def assert_batches_equal(a, b):
    for x, y in zip(a, b):
        assert set(x) == set(y)
        for k in x:
            if k == "drop":
                for n in x[k]:
                    np.testing.assert_array_equal(x[k][n], y[k][n])
            else:
                np.testing.assert_array_equal(np.asarray(x[k]), np.asarray(y[k]), err_msg=k)


def test_shapes_dtypes_ranges_from_tfds(tmp_path):
    path = tfds_io.write_dataset(tmp_path / "ds", {"train": CLIPS[:12]})
    src = tfds_io.open_source(path, "train")
    ds = pipeline.make_pipeline(
        src, {(8, 8, 5): 2}, stride=1, views=("CAM_FRONT", 2), seed=0, shard_index=0, shard_count=1, max_boxes=6
    )
    b = next(iter(ds))
    assert b["video"].shape == (2, 2, 5, 8, 8, 3) and b["video"].dtype == np.float32
    assert -1 <= b["video"].min() and b["video"].max() <= 1 and b["video"].std() > 0.1
    assert b["intrinsics"].shape == (2, 2, 3, 3) and b["cam_to_ego"].shape == (2, 2, 4, 4)
    assert b["ego_to_world"].shape == (2, 5, 4, 4) and b["ego_to_world"].dtype == np.float32
    assert b["boxes"].shape == (2, 5, 6, 7) and b["box_valid"].dtype == np.bool_
    assert b["box_classes"].shape == b["box_ids"].shape == (2, 5, 6) and b["box_classes"].dtype == np.int32
    assert b["bev_map"].shape == (2, 5, 4, 4, 8) and b["bev_map"].dtype == np.uint8
    assert b["waypoints"].shape == (2, 5, 2) and b["fps"].shape == (2,)
    assert len(b["caption"]) == 2 and isinstance(b["caption"][0], str)
    assert set(b["drop"]) == set(pipeline.CONDITIONS) and b["drop"]["text"].dtype == np.bool_
    for j, idx in enumerate(b["index"]):
        np.testing.assert_allclose(b["fps"][j], CLIPS[idx]["fps"])
        np.testing.assert_array_equal(b["cam_to_ego"][j], CLIPS[idx]["cam_to_ego"][[0, 2]])
        # padded box slots are invalid
        n = CLIPS[idx]["boxes"].shape[1]
        assert not b["box_valid"][j, :, n:].any()


def test_frames_stride_and_waypoints():
    clip = CLIPS[5]  # 14 frames
    s = transforms.sample_clip(clip, size=(12, 20), frames=5, stride=3, start=1)
    t = 1 + 3 * np.arange(5)
    np.testing.assert_allclose(s["video"], clip["video"][:, t] / 127.5 - 1, atol=1e-5)  # same size: identity
    np.testing.assert_array_equal(s["boxes"], clip["boxes"][t])
    np.testing.assert_allclose(s["fps"], clip["fps"] / 3)
    # waypoints: ego positions in the ego frame of frame t[0] (yaw 0.1 * t[0], moving 2 m/frame in world x)
    d = np.stack([2.0 * (t - t[0]), np.zeros(5)], 1)
    yaw = 0.1 * t[0]
    rot = np.array([[np.cos(yaw), np.sin(yaw)], [-np.sin(yaw), np.cos(yaw)]])
    np.testing.assert_allclose(s["waypoints"], d @ rot.T, atol=1e-5)
    assert np.all(s["waypoints"][0] == 0)
    with pytest.raises(ValueError, match="need 13 source frames, but the clip has 14.*too long|need 17"):
        transforms.sample_clip(clip, size=(12, 20), frames=5, stride=4, start=0)


def test_intrinsics_follow_resize_and_crop():
    """A 3D point lit in the source image lands, after resize + crop, where the new K projects it."""
    h, w = 30, 50
    K = np.array([[40.0, 0, 25.0], [0, 40.0, 15.0], [0, 0, 1]], np.float32)
    P = np.array([0.3, -0.1, 2.0])  # camera frame
    u, v = (K @ P)[:2] / P[2]  # (31, 13): pixel centres at c + 0.5
    video = np.zeros((1, 1, h, w, 3), np.uint8)
    video[..., int(v) - 1 : int(v) + 1, int(u) - 1 : int(u) + 1, :] = 255  # 2x2 block centred on (u, v)
    for crop, seed in (("center", 0), ("random", 1), ("random", 2)):
        plan = resize.resize_plan((h, w), (16, 20), crop=crop, rng=np.random.default_rng(seed))
        img = (resize.resize_crop_video(video, plan)[0, 0, ..., 0] + 1) / 2
        K2 = resize.adjust_intrinsics(K, plan)
        u2, v2 = (K2 @ P)[:2] / P[2]
        rows, cols = np.mgrid[:16, :20] + 0.5
        cu, cv = (img * cols).sum() / img.sum(), (img * rows).sum() / img.sum()
        assert abs(cu - u2) < 0.05 and abs(cv - v2) < 0.05, (crop, cu, u2, cv, v2)
    # worked example: cover scale 0.54 along x (50 -> 27), 16/30 along y, centre crop 3 px in x
    plan = resize.resize_plan((h, w), (16, 20))
    np.testing.assert_allclose(
        resize.adjust_intrinsics(K, plan),
        [[40 * 0.54, 0, 25 * 0.54 - 3], [0, 40 * 16 / 30, 15 * 16 / 30], [0, 0, 1]],
        rtol=1e-6,
    )


def test_deterministic_for_a_seed():
    a, b = batches(5), batches(5)
    assert_batches_equal(a, b)
    c = batches(5, seed=4)
    assert any(not np.array_equal(x["index"], y["index"]) for x, y in zip(a, c))


def test_resume_is_exact():
    ds = pipeline.make_pipeline(CLIPS, BUCKETS, seed=3, shard_index=0, shard_count=1, num_threads=2)
    it = iter(ds)
    for _ in range(7):  # crosses an epoch boundary (~5 batches per epoch)
        next(it)
    state = it.get_state()
    cont = [next(it) for _ in range(4)]
    fresh = iter(pipeline.make_pipeline(CLIPS, BUCKETS, seed=3, shard_index=0, shard_count=1, num_threads=2))
    fresh.set_state(state)
    assert_batches_equal([next(fresh) for _ in range(4)], cont)


def test_repeating_buckets_resume_exactly_across_an_epoch_boundary(caplog):
    """Four clips for a bucket of a fixed repeat 2 and one of batch 3 (automatic repeat): batches
    hold a clip more than once, and a state saved in epoch 1 resumes it exactly."""
    clips, buckets = CLIPS[:4], {(8, 8, 5): (2, 1.0, 2), (4, 6, 9): 3}
    kw = dict(seed=3, shard_index=0, shard_count=1, num_threads=2)
    plan = BatchPlan(
        [9, 10, 11, 12], parse_buckets(buckets), stride=1, seed=3, shard_index=0, shard_count=1, num_epochs=None
    )
    first = len(plan._epoch(0))
    assert {b for b, *_ in plan._epoch(0)} == {0, 1} and first < 5  # both buckets; epoch 1 from batch 5 on
    with caplog.at_level("INFO", logger="jaxdrive.data.batch_plan"):
        it = iter(pipeline.make_pipeline(clips, buckets, **kw))
        seen = [next(it) for _ in range(first + 1)]
        state = it.get_state()
        cont = [next(it) for _ in range(4)]
    assert re.search(r"epoch 0: bucket repeats \(rounds of clips\): 8x8x5 2, 4x6x9 \d+ \(auto\)", caplog.text)
    assert caplog.text.count("epoch 1: bucket repeats") == 1
    assert any(len(set(b["index"].tolist())) < len(b["index"]) for b in seen + cont)  # a clip twice in a batch
    fresh = iter(pipeline.make_pipeline(clips, buckets, **kw))
    fresh.set_state(state)
    assert_batches_equal([next(fresh) for _ in range(4)], cont)


def test_shards_are_disjoint_and_in_step():
    kw = dict(num_epochs=1, drop_probs={}, shard_count=3)
    runs = [
        list(pipeline.make_pipeline(CLIPS, {(8, 8, 5): 1, (4, 6, 9): 1}, seed=0, shard_index=s, **kw)) for s in range(3)
    ]
    seen = [np.concatenate([b["index"] for b in r]) for r in runs]
    for s, idx in enumerate(seen):
        assert len(idx) > 0 and np.all(idx % 3 == s) and len(set(idx)) == len(idx)
    # every shard yields the same bucket at every step
    shapes = [[b["video"].shape for b in r] for r in runs]
    assert shapes[0] == shapes[1] == shapes[2]


def test_buckets_have_their_batch_sizes():
    seen = set()
    for b in batches(12):
        B, V, F, H, W, _ = b["video"].shape
        want = BUCKETS[(H, W, F)]
        assert B == (want[0] if isinstance(want, tuple) else want)
        assert b["waypoints"].shape == (B, F, 2) and b["intrinsics"].shape == (B, V, 3, 3)
        seen.add((H, W, F))
    assert seen == set(BUCKETS)


def test_empty_bucket_names_bucket_and_reason():
    # 9 frames at stride 3 need 25 source frames; the clips have 9..16
    with pytest.raises(
        ValueError,
        match=r"bucket \(H, W, F\) = \(4, 6, 9\): zero samples after bucketing: "
        r"each clip needs .* = 25 source frames at stride 3, but the longest "
        r"of the 24 clips has 16",
    ):
        pipeline.make_pipeline(CLIPS, {(8, 8, 5): 1, (4, 6, 9): 1}, stride=3, shard_index=0, shard_count=1)
    # a fixed repeat that leaves a bucket short of one batch; the automatic one repeats the clips
    with pytest.raises(
        ValueError,
        match=r"bucket \(H, W, F\) = \(4, 6, 9\).*fewer clips .* over its 2 round\(s\)\) "
        r"than its batch size 50",
    ):
        pipeline.make_pipeline(CLIPS, {(8, 8, 5): 1, (4, 6, 9): (50, 1.0, 2)}, shard_index=0, shard_count=1)
    it = iter(pipeline.make_pipeline(CLIPS, {(8, 8, 5): 1, (4, 6, 9): 50}, shard_index=0, shard_count=1))
    assert any(next(it)["video"].shape[0] == 50 for _ in range(60))
    # automatic repetition needs a long enough clip on every shard: here only the odd clips are
    with pytest.raises(
        ValueError,
        match=r"bucket \(H, W, F\) = \(4, 6, 13\): zero samples after bucketing: "
        r"expected a clip of at least 13 source frames on every shard, got none on "
        r"shard 0 of 2",
    ):
        pipeline.make_pipeline(
            CLIPS,
            {(8, 8, 5): 1, (4, 6, 13): 1},
            shard_index=1,
            shard_count=2,
            frame_counts=[9 + 7 * (i % 2) for i in range(24)],
        )


def test_stride_longer_than_every_scene():
    with pytest.raises(ValueError, match="frame stride or clip length is longer than every scene"):
        pipeline.make_pipeline(CLIPS, {(8, 8, 5): 1}, stride=5, shard_index=0, shard_count=1)


def test_short_clips_are_counted_in_the_log(caplog):
    with caplog.at_level("WARNING"):
        pipeline.make_pipeline(CLIPS, {(8, 8, 5): 1}, stride=3, shard_index=0, shard_count=1)
    # 13 source frames needed; 24 clips of 9 + (i % 8) frames: 12 have fewer than 13
    assert "skipping 12 of 24 clips" in caplog.text


def test_drop_mask_frequencies():
    clips = make_clips(n=8, V=1, H=4, W=4, base_frames=5)
    probs = {"text": 0.5, "boxes": 0.1, "map": 0.0, "trajectory": 1.0}
    ds = pipeline.make_pipeline(
        clips, {(4, 4, 5): 8}, drop_probs=probs, seed=0, shard_index=0, shard_count=1, num_threads=0
    )
    it = iter(ds)
    drops = [next(it)["drop"] for _ in range(60)]  # 480 samples
    for name, p in probs.items():
        freq = np.concatenate([d[name] for d in drops]).mean()
        assert abs(freq - p) < 0.07, (name, freq, p)


def test_argument_errors():
    with pytest.raises(ValueError, match=r"expected F = 1 \+ 4k frames, got 6"):
        pipeline.make_pipeline(CLIPS, {(8, 8, 6): 1}, shard_index=0, shard_count=1)
    with pytest.raises(ValueError, match="shard_index: expected in"):
        pipeline.make_pipeline(CLIPS, {(8, 8, 5): 1}, shard_index=2, shard_count=2)
    with pytest.raises(ValueError, match="views: expected indices"):
        transforms.sample_clip(CLIPS[0], size=(8, 8), frames=5, views=["CAM_BACK"])
    assert frames_for(4) == 17 and schema.CAMERAS[0] == "CAM_FRONT"


def test_mixed_rate_clip_frames_times_and_fps():
    """MiLA stage 2: condition frames at one stride, the generated frames at another."""
    np.testing.assert_array_equal(frame_offsets(7, 1, 4, 12), [0, 1, 2, 3, 15, 27, 39])
    assert Bucket(8, 8, 7, 1, 1.0).needed(1, 4, 12) == 1 + 3 * 1 + 3 * 12  # 40
    clip = CLIPS[7]  # 16 frames
    fps = clip["fps"]
    cases = [  # (head, stride, tail_stride) -> source offsets from the start; the generated part's stride
        ((3, 1, 4), [0, 1, 2, 6, 10], 4),
        ((0, 1, 3), [0, 3, 6, 9, 12], 3),  # no head: tail_stride throughout
        ((2, 2, None), [0, 2, 4, 6, 8], 2),  # no tail_stride: stride throughout
        ((5, 2, 4), [0, 2, 4, 6, 8], 2),  # all head
        ((1, 3, 2), [0, 2, 4, 6, 8], 2),
    ]
    for (head, stride, tail), offsets, gen in cases:
        s = transforms.sample_clip(clip, size=(12, 20), frames=5, stride=stride, start=2, head=head, tail_stride=tail)
        t = 2 + np.asarray(offsets)
        np.testing.assert_allclose(s["video"], clip["video"][:, t] / 127.5 - 1, atol=1e-5)  # same size: identity
        np.testing.assert_array_equal(s["boxes"], clip["boxes"][t])
        np.testing.assert_allclose(s["frame_times"], np.asarray(offsets) / fps, rtol=1e-6)
        assert s["frame_times"].dtype == np.float32 and s["frame_times"][0] == 0
        np.testing.assert_allclose(s["fps"], fps / gen, rtol=1e-6)
    with pytest.raises(
        ValueError,
        match=r"5 frames at stride 2 \(2 frames\) then 6 from frame 0 need 21 source "
        r"frames, but the clip has 16",
    ):
        transforms.sample_clip(clip, size=(12, 20), frames=5, stride=2, head=2, tail_stride=6)
    with pytest.raises(ValueError, match=r"head: expected an integer >= 0, got -1"):
        transforms.sample_clip(clip, size=(12, 20), frames=5, head=-1)
    with pytest.raises(ValueError, match=r"tail_stride: expected an integer >= 1, got 0"):
        transforms.sample_clip(clip, size=(12, 20), frames=5, tail_stride=0)


def _rate_batches(n, seed=0, **kw):
    clips = make_clips(n=8, V=1, H=4, W=4, base_frames=14)  # 14..21 frames: every stride fits
    ds = pipeline.make_pipeline(
        clips,
        {(4, 4, 5): 8},
        rate_head=2,
        rate_strides=(1, 2, 4),
        seed=seed,
        drop_probs={},
        shard_index=0,
        shard_count=1,
        num_threads=0,
        **kw,
    )
    it = iter(ds)
    return clips, it, [next(it) for _ in range(n)]


def test_pipeline_draws_the_tail_stride_per_clip_from_the_set():
    clips, _, got = _rate_batches(60)  # 480 samples
    tails = []
    for b in got:
        assert b["frame_times"].shape == (8, 5) and b["frame_times"].dtype == np.float32
        for j, idx in enumerate(b["index"]):
            fps = clips[idx]["fps"]
            tail = int(round(fps / b["fps"][j]))
            # 2 head frames 1 source frame apart, then 3 frames `tail` apart
            np.testing.assert_allclose(np.diff(b["frame_times"][j]) * fps, [1, tail, tail, tail], rtol=1e-5)
            tails.append(tail)
    tails = np.asarray(tails)
    assert set(tails) == {1, 2, 4}
    for s in (1, 2, 4):
        assert abs((tails == s).mean() - 1 / 3) < 0.07, (s, (tails == s).mean())
    # deterministic in the seed, resumable, and the seed matters
    _, _, again = _rate_batches(6)
    assert_batches_equal(again, got[:6])
    _, it, _ = _rate_batches(3)
    state = it.get_state()
    _, fresh, _ = _rate_batches(0)
    fresh.set_state(state)
    assert_batches_equal([next(fresh) for _ in range(3)], got[3:6])
    _, _, other = _rate_batches(6, seed=1)
    assert any(not np.array_equal(x["frame_times"], y["frame_times"]) for x, y in zip(other, got[:6]))


def test_clip_lengths_count_the_mixed_rate_span(caplog):
    kw = dict(shard_index=0, shard_count=1)
    # 1 head frame, then 4 frames up to 4 apart: 17 source frames; the clips have 9..16
    with pytest.raises(
        ValueError,
        match=r"the mixed-rate span = 17 source frames at stride 1 for 1 frames then up "
        r"to 4, but the longest of the 24 clips has 16",
    ):
        pipeline.make_pipeline(CLIPS, {(8, 8, 5): 1}, rate_head=1, rate_strides=(1, 4), **kw)
    with caplog.at_level("WARNING"):  # 13 source frames: 12 of 24 clips are short
        pipeline.make_pipeline(CLIPS, {(8, 8, 5): 1}, rate_head=1, rate_strides=(3, 1), **kw)
    assert "skipping 12 of 24 clips" in caplog.text
    with pytest.raises(ValueError, match=r"rate_strides: expected an integer >= 1, got 0"):
        pipeline.make_pipeline(CLIPS, {(8, 8, 5): 1}, rate_strides=(2, 0), **kw)
    with pytest.raises(ValueError, match=r"rate_head: expected an integer >= 0, got -2"):
        pipeline.make_pipeline(CLIPS, {(8, 8, 5): 1}, rate_head=-2, **kw)


@pytest.mark.parametrize("how", ["overwrite", "truncate"])
def test_unreadable_clips_are_named_or_replaced_and_counted(tmp_path, how, caplog):
    import logging

    from shard_faults import damaged_dataset

    path, clips, bad, shard = damaged_dataset(tmp_path / "clips", how)
    src = tfds_io.open_source(path, "train")
    kw = dict(seed=1, shard_index=0, shard_count=1, num_threads=2, stride=1)
    with pytest.raises(ValueError, match=rf"{re.escape(str(shard))}: record \d \(clip [345] "):
        list(pipeline.make_pipeline(src, {(8, 16, 5): 2}, num_epochs=1, **kw))

    with caplog.at_level(logging.WARNING, logger="jaxdrive.data.pipeline"):
        got = list(pipeline.make_pipeline(src, {(8, 16, 5): 2}, num_epochs=2, skip_bad_records=True, **kw))
    assert len(got) == 12 and all(b["video"].shape == (2, 2, 5, 8, 16, 3) for b in got)  # 6 full batches an epoch
    for epoch in (got[:6], got[6:]):
        seen = np.concatenate([b["index"] for b in epoch])
        assert set(seen) == set(range(12)) - bad  # every readable clip, none of the others
        assert sum(int(b["bad_records"]) for b in epoch) == len(bad)
    assert caplog.text.count(str(shard)) == 1  # one line for the file, not one per record
    # resumed mid-epoch: the same stand-ins and counts
    ds = pipeline.make_pipeline(src, {(8, 16, 5): 2}, num_epochs=2, skip_bad_records=True, **kw)
    it = iter(ds)
    for _ in range(3):
        next(it)
    fresh = iter(pipeline.make_pipeline(src, {(8, 16, 5): 2}, num_epochs=2, skip_bad_records=True, **kw))
    fresh.set_state(it.get_state())
    assert_batches_equal(list(fresh), got[3:])
    with pytest.raises(ValueError, match="skip_bad_records: expected True or False"):
        pipeline.make_pipeline(src, {(8, 16, 5): 2}, skip_bad_records="yes", **kw)
