"""Precomputed latents: ``jaxdrive data encode`` writes the windows' latents exactly as the codec
encodes ``sample_clip``, latent batches give the video batches' loss, Run rejects a dataset that
does not match its config, the latent iterator resumes exactly, and a run trains on them."""

import dataclasses
import logging
from pathlib import Path
from types import SimpleNamespace

import jax
import numpy as np
import pytest

from jaxdrive.cli import main as cli
from jaxdrive.config import load_config
from jaxdrive.data.batches import model_inputs
from jaxdrive.data.tfds_io import dataset_info, open_source
from jaxdrive.data.transforms import collate, sample_clip, take_window
from jaxdrive.generate.rollout import rollout, window_starts
from jaxdrive.generate.samples import dataset_inputs
from jaxdrive.models.latents import LatentCodec
from jaxdrive.train import flow_step
from jaxdrive.train.metrics import read_metrics
from jaxdrive.train.run import Run, train

from train_fixtures import MACHINERY, save_run, write_same_clips, write_synthetic

TINY = Path(__file__).resolve().parents[1] / "configs" / "tiny.py"
SMALLER = [
    "data.views=2",
    "data.frames=5",
    "data.batch_size=2",
    "model.depth=1",
    "optim.warmup_steps=2",
    "train.log_every=1",
    "mesh.data=2",
    "mesh.seq=4",
]
EVERY = 4  # 9-frame clips, 5-frame windows: starts 0 and 4, two windows a clip


@pytest.fixture(scope="module")
def datasets(tmp_path_factory):
    """(clip dataset, its latent windows written by the CLI)."""
    root = tmp_path_factory.mktemp("latents")
    write_synthetic(root / "clips")
    args = [
        "data",
        "encode",
        "--config",
        str(TINY),
        "--out",
        str(root / "latents"),
        "--every",
        str(EVERY),
        "--batch",
        "4",
    ]
    for s in [f"data.path={root / 'clips'}", *SMALLER]:
        args += ["--set", s]
    assert cli(args) == 0
    return root / "clips", root / "latents"


def config(path, *sets, precomputed=True):
    return load_config(TINY, [f"data.path={path}", *SMALLER, f"latents.precomputed={precomputed}", *sets])


def window(clips, latents_index, cfg):
    """sample_clip of the clip window stored at ``latents_index`` of the train split."""
    d = cfg.data
    clip = clips[latents_index // 2]
    return sample_clip(
        clip,
        size=(d.height, d.width),
        frames=d.frames,
        stride=d.stride,
        start=EVERY * (latents_index % 2),
        views=list(range(d.views)),
    )


def test_encoded_windows_are_the_codec_of_sample_clip(datasets):
    clips_path, latents_path = datasets
    cfg = config(clips_path, precomputed=False)
    clips, windows = open_source(clips_path, "train"), open_source(latents_path, "train")
    assert windows.kind == "windows" and len(windows) == 6 and len(open_source(latents_path, "validation")) == 2
    codec = LatentCodec.from_config(cfg.latents)
    for j in range(len(windows)):  # 6 windows in batches of 4: one padded batch
        want, got = window(clips, j, cfg), windows[j]
        ref = np.asarray(codec.encode(None, want.pop("video")[None]))[0]
        # not stored (uniform frames): take_window gives sample_clip's times back from the fps
        times = want.pop("frame_times")
        np.testing.assert_allclose(take_window(got, frames=5)["frame_times"], times, rtol=1e-6)
        assert got["latents"].shape == (2, 5, 8, 14, 48) and got["latents"].dtype == np.float32
        np.testing.assert_allclose(got["latents"], ref, atol=1e-6)
        for k, v in want.items():
            if isinstance(v, str):
                assert got[k] == v
            else:
                np.testing.assert_array_equal(got[k], v, err_msg=k)
    meta = dataset_info(latents_path)["metadata"]["encoded"]
    assert meta["latents"] == {
        "source": "space_to_depth",
        "factor": 4,
        "scale": 1.0,
        "vae_path": "",
        "vae_mode": "chunked",
    }
    assert meta["data"] == {"height": 32, "width": 56, "frames": 5, "stride": 1, "views": 2}
    assert meta["latent_channels"] == 48 and meta["every"] == EVERY
    assert meta["source_path"] == str(clips_path.resolve())


@pytest.mark.slow(seconds=11)
def test_latent_batch_gives_the_video_batch_loss(datasets):
    clips_path, latents_path = datasets
    run = Run(config(latents_path))
    batch = next(iter(run.dataset()))
    video_run = Run(config(clips_path, precomputed=False))
    video_keys = set(next(iter(video_run.dataset())))
    assert set(batch) - {"latents"} == video_keys - {"video"} and "video" not in batch
    assert batch["latents"].shape == (2, 2, 5, 8, 14, 48) and batch["latents"].dtype == np.float32

    clips = open_source(clips_path, "train")
    video = collate([window(clips, int(i), run.config) for i in batch["index"]])
    video["drop"], video["index"] = batch["drop"], batch["index"]
    for k in set(batch) - {"latents", "drop"}:
        if isinstance(batch[k], list):
            assert batch[k] == video[k]
        else:
            np.testing.assert_array_equal(batch[k], video[k], err_msg=k)

    model = run.training.model
    params = run.training.dit.init_params(0, batch=1, views=2, frames=5, height=8, width=14)
    loss = jax.jit(lambda p, inp, k: flow_step.flow_loss_fn(run.training, p, None, inp, k)[0])
    key = jax.random.key(3)
    from_latents = loss(params, model_inputs(batch, model), key)
    from_video = loss(params, model_inputs(video, model), key)
    assert np.isfinite(float(from_latents))
    np.testing.assert_allclose(float(from_latents), float(from_video), rtol=1e-6)


@pytest.mark.parametrize(
    "which, sets, match",
    [
        ("clips", [], r"data.path: expected latent windows written by 'jaxdrive data encode'"),
        ("latents", ["latents.precomputed=false"], r"latents.precomputed: expected true"),
        ("latents", ["latents.scale=0.5"], r"latents.scale: expected 1.0 .* got 0.5"),
        (
            "latents",
            ["latents.factor=8", "model.in_channels=192", "data.height=64", "data.width=64"],
            r"latents.factor: expected 4 .* got 8",
        ),
        ("latents", ["data.height=64"], r"data.height: expected 32 .* got 64"),
        ("latents", ["data.frames=9"], r"data.frames: expected 5 .* got 9"),
        ("latents", ["data.views=1"], r"data.views: expected 2 .* got 1"),
        ("latents", ["data.stride=2"], r"data.stride: expected 1 .* got 2"),
    ],
)
def test_run_rejects_a_dataset_that_does_not_match(datasets, which, sets, match):
    path = dict(zip(("clips", "latents"), datasets))[which]
    with pytest.raises(ValueError, match=match):
        Run(config(path, *sets))


def test_latent_iterator_resumes_exactly(datasets):
    run = Run(config(datasets[1]))
    it = iter(run.dataset())
    next(it)
    state = it.get_state()
    want = next(it)
    again = iter(run.dataset())
    again.set_state(state)
    got = next(again)
    np.testing.assert_array_equal(got["index"], want["index"])
    np.testing.assert_array_equal(got["latents"], want["latents"])
    assert {k: v.tolist() for k, v in got["drop"].items()} == {k: v.tolist() for k, v in want["drop"].items()}


def test_sampling_conditions_on_the_stored_windows(datasets):
    clips_path, latents_path = datasets
    run = Run(config(latents_path))
    inputs = dataset_inputs(run.sampling(), frames=3)  # a prefix of the 5-frame windows
    assert inputs["latents"].shape == (1, 2, 3, 8, 14, 48) and inputs["cond"].waypoints.shape == (1, 3, 2)
    np.testing.assert_array_equal(inputs["latents"][0], open_source(latents_path, "validation")[0]["latents"][:, :3])
    with pytest.raises(ValueError, match=r"frames: expected at most the 5 frames of the dataset's latent windows"):
        dataset_inputs(run.sampling(), frames=9)
    missing = dataclasses.replace(run.sampling(), data=dataclasses.replace(run.sampling().data, path="no/such/dir"))
    with pytest.raises(
        ValueError,
        match=r"path: expected a TFDS dataset directory, got no/such/dir "
        r"\(it does not exist\)",
    ):
        dataset_inputs(missing, frames=3)  # named, where it once failed on len(None)

    # the rollout pins the stored condition latents (a stand-in velocity keeps the compile cheap)
    stand_in = StandIn()
    full = dataset_inputs(run.sampling(), frames=5)
    out = np.asarray(
        rollout(
            stand_in,
            run.codec,
            None,
            None,
            full,
            total_frames=5,
            window=5,
            overlap=1,
            cond_frames=2,
            steps=2,
            guidance=1.0,
            key=jax.random.key(0),
        )
    )
    assert out.shape == full["latents"].shape
    np.testing.assert_array_equal(out[:, :, :2], full["latents"][:, :, :2])
    assert not np.allclose(out[:, :, 2:], full["latents"][:, :, 2:])  # the rest was generated


def test_encode_shows_progress_unless_turned_off(datasets, tmp_path, capsys):
    args = ["data", "encode", "--config", str(TINY), "--every", str(EVERY), "--batch", "4"]
    for s in [f"data.path={datasets[0]}", *SMALLER]:
        args += ["--set", s]
    assert cli([*args, "--out", str(tmp_path / "a")]) == 0
    err = capsys.readouterr().err
    # stderr is not a terminal: plain lines, no tqdm frames (6 train + 2 validation windows, counted ahead)
    assert "INFO jaxdrive.progress: encode window 8/8" in err and "\r" not in err
    assert "INFO jaxdrive.train.encode: encoded" in err
    assert cli([*args, "--out", str(tmp_path / "b"), "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert "window/s" not in err and "8/8" not in err and "INFO jaxdrive.train.encode: encoded" in err


class StandIn:
    """A stand-in DiT whose velocity is ``-x/2`` (a model is a static jit argument: hashable)."""

    config = SimpleNamespace(
        controls=SimpleNamespace(cond_frames=None, warp=False), prediction="velocity", prediction_min_sigma=0.05
    )

    @staticmethod
    def forward(params, x, sigma, cond):
        return -0.5 * x


def test_window_starts_overlap_and_end_at_the_last_frame():
    assert window_starts(5, 5, 1) == [0]
    assert window_starts(9, 5, 1) == [0, 4]
    assert window_starts(10, 5, 1) == [0, 4, 5]  # the last window starts earlier, not past the end
    assert window_starts(11, 5, 2) == [0, 3, 6]
    assert window_starts(3, 3, 4) == [0]  # one window: the overlap is never used
    with pytest.raises(ValueError, match=r"overlap: expected fewer than window = 5 frames, got 5"):
        window_starts(9, 5, 5)
    with pytest.raises(ValueError, match=r"window: expected"):
        window_starts(9, 0, 1)


def test_rollout_progress_counts_windows(datasets, caplog):
    run = Run(config(datasets[0], precomputed=False))
    stand_in = StandIn()
    inputs = dataset_inputs(run.sampling(), frames=9)
    kw = dict(total_frames=9, window=5, overlap=1, cond_frames=1, steps=1, guidance=1.0, key=jax.random.key(0))
    lines = lambda: [r.getMessage().split("  ")[0] for r in caplog.records if r.name == "jaxdrive.progress"]
    with caplog.at_level(logging.INFO, logger="jaxdrive"):  # stderr is not a terminal: a line per window
        quiet = rollout(stand_in, run.codec, None, None, inputs, **kw)
        assert lines() == []
        shown = rollout(stand_in, run.codec, None, None, inputs, progress=True, **kw)
    assert lines() == ["window 1/2", "window 2/2"]
    np.testing.assert_array_equal(quiet, shown)  # the bar changes nothing else


@pytest.mark.slow(seconds=23)
def test_train_on_precomputed_latents(datasets, tmp_path):
    cfg = config(datasets[1], *MACHINERY, "train.steps=2", "train.checkpoint_every=2")
    out = train(cfg, tmp_path / "run", progress=False)
    assert out["status"] == "done" and out["step"] == 2
    assert (tmp_path / "run" / "checkpoints" / "2").is_dir()
    rows = read_metrics(tmp_path / "run")
    assert [r["step"] for r in rows] == [1, 2] and all(np.isfinite(r["loss"]) for r in rows)


# ------------------------------------------------------------------------- sharded encoding
def records(path):
    """Every split's records of a dataset, in order, and its metadata."""
    info = dataset_info(path)
    return {s: [open_source(path, s)[i] for i in range(n["num_examples"])] for s, n in info["splits"].items()}, info[
        "metadata"
    ]


def assert_same_datasets(got_path, want_path):
    (got, got_meta), (want, want_meta) = records(got_path), records(want_path)
    assert got_meta == want_meta and list(got) == list(want)
    for split in want:
        assert len(got[split]) == len(want[split]), split
        for a, b in zip(got[split], want[split]):
            assert sorted(a) == sorted(b)
            for k in b:
                np.testing.assert_array_equal(a[k], b[k], err_msg=f"{split} {k}")
    for split in want:
        np.testing.assert_array_equal(
            open_source(got_path, split).frame_counts, open_source(want_path, split).frame_counts
        )


def test_encode_shards_the_batch_over_the_mesh(datasets, tmp_path, monkeypatch):
    from jaxdrive.train import encode

    clips_path, latents_path = datasets
    one = encode.encode_dataset(
        config(clips_path, "mesh.data=-1", "mesh.seq=1", precomputed=False),
        tmp_path / "one",
        every=EVERY,
        batch=1,
        devices=jax.devices()[:1],
    )
    seen = []
    gather = encode.global_to_host_local
    monkeypatch.setattr(
        encode,
        "global_to_host_local",
        lambda x: seen.append((len(x.sharding.device_set), x.sharding.spec[0])) or gather(x),
    )
    eight = encode.encode_dataset(
        config(clips_path, "mesh.data=2", "mesh.fsdp=4", "mesh.seq=1", precomputed=False),
        tmp_path / "eight",
        every=EVERY,
        batch=8,
    )
    assert seen == [(8, ("data", "fsdp"))] * 2  # one padded call per split, all 8 devices
    assert_same_datasets(eight, one)
    assert_same_datasets(latents_path, one)  # the CLI's data 2 x seq 4 in batches of 4


@pytest.mark.parametrize(
    "sets, kwargs, match",
    [
        (
            ["mesh.data=8", "mesh.seq=1"],
            dict(batch=4),
            r"batch: expected a multiple of the mesh's batch axes data x "
            r"fsdp \(8\), got 4",
        ),
        ([], dict(batch=0), r"batch: expected"),
        ([], dict(every=0), r"every: expected"),
        ([], dict(splits=["test"]), r"splits: expected splits of .* got 'test'"),
        (["data.frames=12"], {}, r"data.frames: 12 frames at stride 1 need 12 source frames, but the longest clip"),
    ],
)
def test_encode_rejects_bad_arguments(datasets, tmp_path, sets, kwargs, match):
    from jaxdrive.train.encode import encode_dataset

    with pytest.raises(ValueError, match=match):
        encode_dataset(config(datasets[0], *sets, precomputed=False), tmp_path / "out", **kwargs)
    assert not (tmp_path / "out").exists() and not list(tmp_path.iterdir())


@pytest.mark.slow(seconds=6)
def test_two_processes_write_the_one_process_dataset(datasets, tmp_path):
    """2 processes x 4 fake devices (launch/local.py), the batch over data = 8 across both: each
    encodes its clips and writes its shards; together they are the one-process dataset."""
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    cmd = [
        sys.executable,
        str(root / "launch" / "local.py"),
        "--processes",
        "2",
        "--cpu-devices",
        "4",
        "--",
        sys.executable,
        "-m",
        "jaxdrive.cli",
        "data",
        "encode",
        "--config",
        str(TINY),
        "--out",
        str(tmp_path / "two"),
        "--every",
        str(EVERY),
        "--batch",
        "8",
        "--mesh",
        "data=8",
        "--no-progress",
    ]
    for s in [f"data.path={datasets[0]}", *SMALLER]:
        cmd += ["--set", s]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=root)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-4000:]
    assert_same_datasets(tmp_path / "two", datasets[1])
    # process 0 encoded clips 0-1 (4 windows) and the validation clip, process 1 clip 2: a shard each
    assert len(list((tmp_path / "two").glob("*-train.array_record-*"))) == 2
    assert len(list((tmp_path / "two").glob("*-validation.array_record-*"))) == 1
    assert [p.name for p in tmp_path.iterdir()] == ["two"]  # no temporary directory left


# ------------------------------------------------------------------------- distillation
LONGDWM = Path(__file__).resolve().parents[1] / "configs" / "longdwm.py"
DISTILL = ["data.views=2", "data.batch_size=2", "data.drop_prob=0.0", "model.depth=1", "mesh.data=-1", "mesh.seq=1"]


@pytest.fixture(scope="module")
def same_dense_clips(tmp_path_factory):
    """Copies of one 9-frame clip: a clip run and a latent-window run then feed the same samples."""
    return write_same_clips(tmp_path_factory.mktemp("dense") / "clips", seed=11, frames=9, copies=2)


@pytest.mark.slow(seconds=23)
def test_distillation_on_precomputed_latents_matches_encoding_in_the_step(same_dense_clips, tmp_path):
    """LongDWM's fine-to-coarse distillation (configs/longdwm.py:size=tiny,role=distill, 9 dense
    frames, segments of 5): the windows hold the dense clip's frame-wise latents, which is what both
    the coarse student (every 4th frame) and the fine teacher (each segment) read. A run on them
    gives the losses of the same run encoding the clips in the step (same batch, parameters, key)."""
    from jaxdrive.train.encode import encode_dataset

    one = jax.devices()[:1]
    fine = load_config(
        f"{LONGDWM}:size=tiny,role=fine", [f"data.path={same_dense_clips}", *DISTILL, "data.frames=5", "train.seed=7"]
    )
    save_run(fine, tmp_path / "fine", devices=one)
    sets = [*DISTILL, "data.frames=9", "flow.distill_segment_len=5", f"flow.distill_teacher={tmp_path / 'fine'}"]
    on_the_fly = load_config(f"{LONGDWM}:size=tiny,role=distill", [f"data.path={same_dense_clips}", *sets])
    encode_dataset(on_the_fly, tmp_path / "latents", devices=one)
    stored = load_config(
        f"{LONGDWM}:size=tiny,role=distill", [f"data.path={tmp_path / 'latents'}", *sets, "latents.precomputed=true"]
    )
    clip_run, window_run = Run(on_the_fly, devices=one), Run(stored, devices=one)
    params = clip_run.init_state()[0].params
    metrics = []
    for run in (clip_run, window_run):
        batch = jax.tree_util.tree_map(lambda x: x[0], run.global_batch([next(iter(run.dataset()))]))
        frozen = run.frozen_params()  # the fine model restored from its run directory
        loss = jax.jit(
            lambda p, f, inp, k, r=run: flow_step.flow_loss_fn(r.training, p, f["codec"], inp, k, f["teacher"])[1]
        )
        with jax.set_mesh(run.mesh):
            metrics.append(jax.device_get(loss(params, frozen, batch, jax.random.key(5))))
    a, b = metrics
    assert "video" in clip_run.global_batch([next(iter(clip_run.dataset()))])
    for key in ("loss", "flow_loss", "distill_loss"):
        assert a[key] > 0, key
        np.testing.assert_allclose(b[key], a[key], rtol=1e-5, err_msg=key)

    # sampling reads the coarse frames of the stored dense windows: every 4th, at a quarter of the rate
    want = dataset_inputs(clip_run.sampling(), frames=3)
    got = dataset_inputs(window_run.sampling(), frames=3)
    np.testing.assert_array_equal(got["latents"], window_run.codec.encode(None, want["video"]))
    np.testing.assert_allclose(got["cond"].fps, want["cond"].fps)
    np.testing.assert_allclose(got["cond"].waypoints, want["cond"].waypoints, atol=1e-6)
    with pytest.raises(ValueError, match=r"frames: expected at most the 3 frames of the dataset's latent windows"):
        dataset_inputs(window_run.sampling(), frames=4)
