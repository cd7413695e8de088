"""Mixed resolution / length training (MagicDrive-V2 appendix B): ``data.buckets`` in a run, one
compiled step per bucket shape, the bucket schedule resumed exactly, bad buckets named."""

from pathlib import Path

import pytest

from jaxdrive.config import load_config
from jaxdrive.data.pipeline import parse_bucket_specs
from jaxdrive.train.metrics import read_metrics
from jaxdrive.train.run import Run, train

from train_fixtures import assert_same_state, train_with_a_stop, write_synthetic

ROOT = Path(__file__).resolve().parents[1]
BUCKETS = "data.buckets=32x56x1:4:4,16x24x5:2,32x56x5:2"     # images (2/3 of the clips), a small short clip, a clip


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    return write_synthetic(tmp_path_factory.mktemp("buckets") / "data", train=16)


def tiny(data, *sets):
    return load_config(ROOT / "configs" / "tiny.py", [
        f"data.path={data}", "data.views=2", "data.frames=5", "data.batch_size=2", "model.depth=1",
        "optim.warmup_steps=2", "train.log_every=1", "train.steps=6", "train.checkpoint_every=3",
        "mesh.data=2", "mesh.seq=4", *sets])


def test_bucket_specs_worked_example_and_bad_text():
    assert parse_bucket_specs(["224x400x1:32", "224x400x33:4:0.5", "848X1600x33:1"]) == {
        (224, 400, 1): (32, 1.0), (224, 400, 33): (4, 0.5), (848, 1600, 33): (1, 1.0)}
    for bad, match in ((["224x400:32"], r"expected 'HxWxF:batch\[:prob\]'"), (["1x2x3"], "expected 'HxWxF"),
                       (["8x8x1:0"], "positive H, W, F and batch"), (["8x8x1:2:-1"], "probability >= 0"),
                       (["8x8x1:2", "8x8x1:4"], r"each \(H, W, F\) once"), ([], "at least one bucket"),
                       ("8x8x1:2", "a sequence of")):
        with pytest.raises(ValueError, match=r"data\.buckets: .*" + match):
            parse_bucket_specs(bad)


@pytest.mark.parametrize("sets, match", [
    (["data.buckets=32x56x5:3"], r"data.buckets 32x56x5: expected a multiple of optim.grad_accum \(1\) x the batch"),
    (["data.buckets=32x52x5:2"], r"data.buckets 32x52x5: expected multiples of latent compression x patch \(8\)"),
    (["data.buckets=32x56x5:2", "optim.grad_accum=2", "data.batch_size=4"],
     r"optim.grad_accum: expected 1 with data.buckets, got 2"),
    (["data.buckets=32x56x5"], r"data.buckets: expected 'HxWxF:batch\[:prob\]'"),
])
def test_bad_buckets_fail_before_compiling(scenes, sets, match):
    with pytest.raises(ValueError, match=match):
        Run(tiny(scenes, *sets))


def test_buckets_compile_once_each_and_resume_bit_exact(scenes, tmp_path):
    cfg = tiny(scenes, BUCKETS)
    run = Run(cfg)
    assert [(b.key, b.batch_size) for b in run.buckets] == [((32, 56, 1), 4), ((16, 24, 5), 2), ((32, 56, 5), 2)]
    # the schedule: every bucket appears in the first six batches, in a seeded order
    shapes = [next(it)["video"].shape for it in [iter(run.dataset())] for _ in range(6)]
    assert {s[0:1] + s[2:5] for s in shapes} == {(4, 1, 32, 56), (2, 5, 16, 24), (2, 5, 32, 56)}
    whole = train(cfg, tmp_path / "whole", progress=False)
    assert whole["status"] == "done" and whole["compiled_steps"] == 3       # one program per bucket, not per step

    part, resumed = train_with_a_stop(cfg, tmp_path / "split", stop_at=3)
    assert part["status"] == "interrupted" and part["step"] == 3
    assert resumed["status"] == "done" and resumed["step"] == 6
    assert_same_state(whole["state"], resumed["state"])                  # the same buckets in the same order
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
        it = iter(Run(tiny(scenes, BUCKETS, "data.shuffle_seed=2")).dataset())   # a seed that fills every shard
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
    assert _fit_batch([(4, 0.1), (8, 0.2)], 0.4, groups=2, max_batch=256) == 16        # exact on a line
    assert _fit_batch([(4, 0.1), (8, 0.2)], 10.0, groups=2, max_batch=64) == 64        # capped
    assert _fit_batch([(4, 0.1), (4, 0.1)], 0.2, groups=4, max_batch=0) == 8           # one batch: proportional
