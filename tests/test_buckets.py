"""Mixed resolution / length training (MagicDrive-V2 appendix B): ``data.buckets`` in a run, one
compiled step per bucket shape, the bucket schedule resumed exactly, bad buckets named."""

from pathlib import Path

import pytest

from jaxdrive.config import load_config
from jaxdrive.data.buckets import parse_bucket_specs, parse_buckets
from jaxdrive.train.metrics import read_metrics
from jaxdrive.train.run import Run, train

from train_fixtures import MACHINERY, assert_same_state, train_with_a_stop, write_synthetic

ROOT = Path(__file__).resolve().parents[1]
BUCKETS = "data.buckets=32x56x1:4:4,16x24x5:2,32x56x5:2"  # images (2/3 of the clips), a small short clip, a clip


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    return write_synthetic(tmp_path_factory.mktemp("buckets") / "data", train=16)


def tiny(data, *sets):
    return load_config(
        ROOT / "configs" / "tiny.py",
        [
            f"data.path={data}",
            "data.views=2",
            "data.frames=5",
            "data.batch_size=2",
            "model.depth=1",
            *MACHINERY,  # each bucket compiles a step: the buckets' machinery, not the model, is tested
            "optim.warmup_steps=2",
            "train.log_every=1",
            "train.steps=6",
            "train.checkpoint_every=3",
            "mesh.data=2",
            "mesh.seq=4",
            *sets,
        ],
    )


def test_bucket_specs_worked_example_and_bad_text():
    # the fourth field is the repeat: an integer, or 'auto' (None), the default
    assert parse_bucket_specs(
        ["224x400x1:32", "224x400x33:4:0.5", "848X1600x33:1", "224x400x241:1:1:3", "424x800x1:8:2:auto"]
    ) == {
        (224, 400, 1): (32, 1.0, None),
        (224, 400, 33): (4, 0.5, None),
        (848, 1600, 33): (1, 1.0, None),
        (224, 400, 241): (1, 1.0, 3),
        (424, 800, 1): (8, 2.0, None),
    }
    fmt = r"expected 'HxWxF:batch\[:prob\[:repeat\]\]'"
    for bad, match in (
        (["224x400:32"], fmt),
        (["1x2x3"], "expected 'HxWxF"),
        (["8x8x1:0"], "positive H, W, F and batch"),
        (["8x8x1:2:-1"], "probability >= 0"),
        (["8x8x1:2:1:0"], r"a repeat >= 1 or 'auto', got '8x8x1:2:1:0'"),
        (["8x8x1:2:1:1.5"], fmt + r" .*got '8x8x1:2:1:1.5'"),
        (["8x8x1:2:1:often"], fmt),
        (["8x8x1:2:1:2:5"], fmt),
        (["8x8x1:2", "8x8x1:4"], r"each \(H, W, F\) once"),
        ([], "at least one bucket"),
        ("8x8x1:2", "a sequence of"),
    ):
        with pytest.raises(ValueError, match=r"data\.buckets: .*" + match):
            parse_bucket_specs(bad)
    # the mapping form of make_pipeline: (batch, prob, repeat), repeat None for automatic
    assert [b.repeat for b in parse_buckets({(8, 8, 1): (2, 1.0, 3), (8, 8, 5): (2, 1.0, None), (8, 8, 9): 2})] == [
        3,
        None,
        None,
    ]
    for value, match in (
        (
            (2, 1.0, 0),
            r"buckets\[\(8, 8, 1\)\] repeat \(None: automatic\): expected an integer "
            r">= 1, got 0",
        ),
        ((2, 1.0, True), r"repeat .*expected an integer >= 1, got True"),
        (
            (2, 1.0, 2, 1),
            r"buckets\[\(8, 8, 1\)\]: expected batch_size, \(batch_size, prob\) or "
            r"\(batch_size, prob, repeat\), got \(2, 1.0, 2, 1\)",
        ),
    ):
        with pytest.raises(ValueError, match=match):
            parse_buckets({(8, 8, 1): value}, compression=4)


@pytest.mark.parametrize(
    "sets, match",
    [
        (
            ["data.buckets=32x56x5:3"],
            r"data.buckets 32x56x5: expected a multiple of optim.grad_accum \(1\) x the batch",
        ),
        (["data.buckets=32x52x5:2"], r"data.buckets 32x52x5: expected multiples of latent compression x patch \(8\)"),
        (
            ["data.buckets=32x56x5:2", "optim.grad_accum=2", "data.batch_size=4"],
            r"optim.grad_accum: expected 1 with data.buckets, got 2",
        ),
        (["data.buckets=32x56x5"], r"data.buckets: expected 'HxWxF:batch\[:prob\[:repeat\]\]'"),
    ],
)
def test_bad_buckets_fail_before_compiling(scenes, sets, match):
    with pytest.raises(ValueError, match=match):
        Run(tiny(scenes, *sets))


@pytest.mark.slow(seconds=83)
def test_buckets_compile_once_each_and_resume_bit_exact(scenes, tmp_path):
    cfg = tiny(scenes, BUCKETS)
    run = Run(cfg)
    assert [(b.key, b.batch_size) for b in run.buckets] == [((32, 56, 1), 4), ((16, 24, 5), 2), ((32, 56, 5), 2)]
    # the schedule: every bucket appears in the first six batches, in a seeded order
    shapes = [next(it)["video"].shape for it in [iter(run.dataset())] for _ in range(6)]
    assert {s[0:1] + s[2:5] for s in shapes} == {(4, 1, 32, 56), (2, 5, 16, 24), (2, 5, 32, 56)}
    whole = train(cfg, tmp_path / "whole", progress=False)
    assert whole["status"] == "done" and whole["compiled_steps"] == 3  # one program per bucket, not per step

    part, resumed = train_with_a_stop(cfg, tmp_path / "split", stop_at=3)
    assert part["status"] == "interrupted" and part["step"] == 3
    assert resumed["status"] == "done" and resumed["step"] == 6
    assert_same_state(whole["state"], resumed["state"])  # the same buckets in the same order
    # tokens/s counts each step's own bucket: an image step of 4 x 2 views x 8 x 14 / 4 tokens, ...
    per_step = {(4, 1, 32, 56): 4 * 2 * 1 * 4 * 7, (2, 5, 16, 24): 2 * 2 * 5 * 2 * 3, (2, 5, 32, 56): 2 * 2 * 5 * 4 * 7}
    rows = read_metrics(tmp_path / "whole")
    assert [r["step"] for r in rows] == list(range(1, 7))
    ratios = [r["tokens_per_s"] / r["steps_per_s"] for r in rows[1:]]
    assert sorted({round(x) for x in ratios}) == sorted({per_step[s[0:1] + s[2:5]] for s in shapes[1:]})


def test_two_processes_take_the_same_bucket_at_every_step(scenes, monkeypatch):
    """Each process loads its share of every bucket's global batch, and all take the same bucket
    at every step (the global arrays are assembled from one shape); their clips are disjoint."""
    import jax

    loads = []
    for pid in (0, 1):
        monkeypatch.setattr(jax, "process_index", lambda: pid)
        monkeypatch.setattr(jax, "process_count", lambda: 2)
        it = iter(Run(tiny(scenes, BUCKETS, "data.shuffle_seed=2")).dataset())  # a seed that fills every shard
        loads.append([next(it) for _ in range(8)])
    shapes = [[b["video"].shape for b in load] for load in loads]
    assert shapes[0] == shapes[1]
    assert {s[0] for s in shapes[0] if s[2] == 1} == {2} and {s[0] for s in shapes[0] if s[2] > 1} == {1}
    for a, b in zip(*loads):
        assert not set(a["index"].tolist()) & set(b["index"].tolist())


def test_bench_rebalance_fits_all_points_and_survives_timing_noise():
    """The batch search of ``jaxdrive bench buckets --rebalance``: a least-squares line through all
    of a bucket's points; two noisy points whose time falls as the batch grows (measured: 120 ->
    0.315 s, 128 -> 0.296 s) must not send the batch to the floor or the cap."""
    from jaxdrive.bench.buckets import _fit_batch

    points = [(60, 0.16), (120, 0.3152), (128, 0.2957)]
    assert 100 <= _fit_batch(points, 0.30, groups=2, max_batch=256) <= 130
    assert _fit_batch([(4, 0.1), (8, 0.2)], 0.4, groups=2, max_batch=256) == 16  # exact on a line
    assert _fit_batch([(4, 0.1), (8, 0.2)], 10.0, groups=2, max_batch=64) == 64  # capped
    assert _fit_batch([(4, 0.1), (4, 0.1)], 0.2, groups=4, max_batch=0) == 8  # one batch: proportional


@pytest.fixture(scope="module")
def three_scenes(tmp_path_factory):
    """``jaxdrive data synth --scenes 3 --frames 65``'s shape: two train scenes, one validation."""
    return write_synthetic(tmp_path_factory.mktemp("three") / "data", train=2, frames=65, views=1)


@pytest.mark.parametrize("stage", [1, 2, 3])
def test_magicdrive_tiny_fills_every_bucket_from_three_scenes(three_scenes, stage, caplog):
    """Issue 34: two train clips fill every bucket of each tiny MagicDrive-V2 stage (images at a
    batch of 4, 33-frame clips) by automatic repetition; an image batch takes several frames of one
    clip, each a different one; the repeats are logged once per epoch."""
    import numpy as np

    config = load_config(
        f"{ROOT / 'configs' / 'magicdrive_v2.py'}:size=tiny,stage={stage}",
        [f"data.path={three_scenes}", "data.views=1"],
    )
    run = Run(config)
    want = {(b.batch_size, b.frames, b.height, b.width) for b in run.buckets}
    with caplog.at_level("INFO", logger="jaxdrive.data.batch_plan"):
        it = iter(run.dataset())
        # two clips give each bucket exactly one batch an epoch: epoch 0 is the first len(buckets)
        batches = [next(it) for _ in range(2 * len(want))]
    for epoch in (batches[: len(want)], batches[len(want) :]):
        assert {b["video"].shape[:1] + b["video"].shape[2:5] for b in epoch} == want
    assert caplog.text.count("epoch 0: bucket repeats") == caplog.text.count("epoch 1: bucket repeats") == 1
    images = [b for b in batches if b["video"].shape[2] == 1]
    assert all(len(set(b["index"].tolist())) < len(b["index"]) for b in images)  # 4 samples of 2 clips
    for b in images:
        for i in set(b["index"].tolist()):
            poses = b["ego_to_world"][b["index"] == i, 0]  # each sample's frame
            assert len(np.unique(poses.reshape(len(poses), -1), axis=0)) == len(poses)


def test_a_bucket_no_clip_can_fill_is_named(three_scenes):
    """No repeat helps a bucket longer than every clip (65 frames): the error names it."""
    config = load_config(
        f"{ROOT / 'configs' / 'magicdrive_v2.py'}:size=tiny,stage=2",
        [f"data.path={three_scenes}", "data.views=1", "data.buckets=16x32x1:4,16x32x129:2"],
    )
    with pytest.raises(
        ValueError,
        match=r"bucket \(H, W, F\) = \(16, 32, 129\): zero samples after bucketing: "
        r"each clip needs .* = 129 source frames at stride 1, but the longest "
        r"of the 2 clips has 65",
    ):
        Run(config).dataset()
