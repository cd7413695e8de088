"""The papers' recipes at size=tiny: every stage / role trains a few steps from its config
argument, and samples with its long-video strategy through ``jaxdrive sample --strategy``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from jaxdrive.cli import main as cli
from jaxdrive.config import load_config
from jaxdrive.config_checks import check_sections

from train_fixtures import write_synthetic

ROOT = Path(__file__).resolve().parents[1]
MESH = ["mesh.data=2", "mesh.seq=4"]
SMALL = ["data.views=2", "data.batch_size=2", "optim.warmup_steps=1", "train.log_every=1", "train.checkpoint_every=1"]


@pytest.fixture(scope="module")
def long_scenes(tmp_path_factory):
    """Scenes long enough for the low-rate clips (LongDWM's coarse model: 9 frames 8 apart)."""
    return write_synthetic(tmp_path_factory.mktemp("long") / "data", train=2, frames=72)


def train(config: str, workdir, data, *sets, steps: int = 1):
    args = [
        "train",
        "--config",
        str(ROOT / "configs" / config),
        "--workdir",
        str(workdir),
        "--steps",
        str(steps),
        "--no-progress",
        "--mesh",
        "data=2,seq=4",
    ]
    for s in [f"data.path={data}", *SMALL, *sets]:
        args += ["--set", s]
    assert cli(args) == 0
    return workdir


@pytest.mark.parametrize(
    "arg",
    [
        "size=tiny,stage=1",
        "size=tiny,stage=2",
        "size=tiny,stage=3",
        "stage=1",
        "stage=3",
        "size=tiny,role=coarse",
        "size=tiny,role=fine",
        "size=tiny,role=distill",
        "role=coarse",
        "role=fine",
        "role=distill",
    ],
)
def test_paper_configs_take_their_argument(arg):
    name = "longdwm" if "role" in arg else "mila"
    config = load_config(f"{ROOT / 'configs' / name}.py:{arg}")
    check_sections(config)
    if "stage=1" in arg:
        assert config.optim.trainable and config.data.rate_head == 0 and config.data.rate_strides
    if "stage=3" in arg:
        assert config.flow.jdc_anchor_rate == 0.75 and config.flow.tpd and config.model.controls.frame_time
    if name == "mila" and "tiny" not in arg:  # what makes 4 clips a device fit 80 GiB (docs/results/memory.md)
        assert config.model.remat == "full" and config.latents.vae_frame_batch == 1
        # scanned layers for the compile, the last a run of its own: stage 1's trainable set names it
        import flax.linen as nn
        import jax

        from jaxdrive.models.dit import DiT
        from jaxdrive.models.dit.inputs import example_inputs
        from jaxdrive.train.optim import trainable_labels

        m = config.model
        assert m.scan_layers and m.scan_breaks == (m.depth - 1,)
        params = jax.eval_shape(lambda: nn.unbox(DiT(m).init(jax.random.PRNGKey(0), **example_inputs(m))["params"]))
        assert {f"layers_0_{m.depth - 1}", f"layers_{m.depth - 1}"} <= set(params)
        if "stage=1" in arg:  # every pattern matches (else ValueError); the rest freezes
            labels = jax.tree_util.tree_leaves_with_path(trainable_labels(params, config.optim.trainable))
            trained = {jax.tree_util.keystr(k) for k, v in labels if v == "train"}
            assert any(f"layers_{m.depth - 1}" in k for k in trained)
            assert not any(f"layers_0_{m.depth - 1}" in k for k in trained)
    if "role=fine" in arg:
        assert config.flow.patterns == ("prefix", "ends")
    if "role=coarse" in arg:
        assert config.data.stride == config.data.frames - 1
    with pytest.raises(ValueError, match=r"config argument (stage|role): expected"):
        load_config(f"{ROOT / 'configs' / name}.py:{arg.replace('stage=', 'stage=9').replace('role=', 'role=x')}")


@pytest.mark.slow(seconds=143)
def test_mila_tiny_stages_train_and_sample_coarse_to_refine(long_scenes, tmp_path, capsys):
    one = "model.depth=1"  # one layer (stage 1's trainable set names it: "{last}"); the stages need no second
    for stage in (1, 2):
        train(f"mila.py:size=tiny,stage={stage}", tmp_path / f"stage{stage}", long_scenes, one)
    run = train("mila.py:size=tiny,stage=3", tmp_path / "stage3", long_scenes, one, steps=2)
    out = tmp_path / "c2r"
    assert (
        cli(
            [
                "sample",
                "--workdir",
                str(run),
                "--strategy",
                "coarse-to-refine",
                "--frames",
                "20",
                "--steps",
                "2",
                "--out",
                str(out),
                "--no-progress",
            ]
        )
        == 0
    )
    report = json.loads((out / "report.json").read_text())
    # window 8 with 2 given: anchors every 6 frames at 7, 13, 19; the coarse pass draws them in one
    # window, the refine pass takes 3 windows (0, 6, 12)
    assert (report["strategy"], report["frames"], report["views"]) == ("coarse-to-refine", 20, 2)
    assert report["sequential_sampler_calls"] == 1 + 3 and report["peak_device_bytes"] > 0
    assert report["guidance"] == {"main": {"cfg": 3.0}}  # the recipe's sample.cfg (no --cfg given)
    latents = np.load(out / "latents.npy")
    assert latents.shape == (2, 2, 20, 8, 14, 48) and np.isfinite(latents).all()
    assert (out / "sample.mp4").stat().st_size > 0 and (out / "frames.png").stat().st_size > 0
    # the dataset clip covers the 20 frames: every generated frame is scored against it, part by part
    quality = report["quality"]
    assert quality["all_generated"]["frames"] == list(range(2, 20)) and quality["window"] == 8
    assert [f for h in quality["horizon"] for f in h["frames"]] == list(range(2, 20))
    assert np.isfinite(quality["all_generated"]["psnr"]) and 0 < quality["all_generated"]["noise_psnr"] < 100
    per_frame = json.loads((out / "quality.json").read_text())["per_frame"]
    assert len(per_frame) == 20 and per_frame[0]["psnr"] > per_frame[5]["psnr"]  # given frames decode near-exactly
    # rollout of one clip on a mesh whose batch axes have size 1 (the frame-time embedding once lost
    # its batch sharding there)
    out = tmp_path / "rollout"
    assert (
        cli(
            [
                "sample",
                "--workdir",
                str(run),
                "--strategy",
                "rollout",
                "--frames",
                "12",
                "--steps",
                "2",
                "--mesh",
                "data=1,seq=8",
                "--out",
                str(out),
                "--no-progress",
            ]
        )
        == 0
    )
    report = json.loads((out / "report.json").read_text())
    assert report["sequential_sampler_calls"] == 2 and np.load(out / "latents.npy").shape == (1, 2, 12, 8, 14, 48)
    # stage 2 never trained anchors: it cannot refine them, and says so before compiling
    capsys.readouterr()
    assert (
        cli(
            [
                "sample",
                "--workdir",
                str(tmp_path / "stage2"),
                "--strategy",
                "coarse-to-refine",
                "--frames",
                "20",
                "--out",
                str(tmp_path / "bad"),
            ]
        )
        == 2
    )
    assert "coarse-to-refine needs a model trained to correct JDC anchors" in capsys.readouterr().err


@pytest.mark.slow(seconds=121)
def test_longdwm_tiny_roles_train_and_sample_coarse_fine(long_scenes, tmp_path, capsys):
    one = "model.depth=1"  # one layer: the roles' data, losses and strategy do not need two
    coarse = train("longdwm.py:size=tiny,role=coarse", tmp_path / "coarse", long_scenes, one)
    fine = train("longdwm.py:size=tiny,role=fine", tmp_path / "fine", long_scenes, one, steps=2)
    train("longdwm.py:size=tiny,role=distill", tmp_path / "distill", long_scenes, one, f"flow.distill_teacher={fine}")
    out = tmp_path / "cf"
    args = [
        "sample",
        "--workdir",
        str(coarse),
        "--fine-workdir",
        str(fine),
        "--strategy",
        "coarse-fine",
        "--steps",
        "2",
        "--no-progress",
    ]
    assert cli([*args, "--frames", "17", "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    # keyframes 0, 8, 16 in one coarse window, then the segments one a call (the default on a CPU)
    assert report["strategy"] == "coarse-fine" and report["frames"] == 17 and report["sequential_sampler_calls"] == 3
    assert report["segment_batch"]["segment_batch"] == 1 and report["options"]["segment_batch"] == "auto"
    latents = np.load(out / "latents.npy")
    assert latents.shape == (2, 2, 17, 8, 14, 48) and np.isfinite(latents).all()
    capsys.readouterr()
    for bad, message in (
        (
            ["--workdir", str(coarse), "--strategy", "coarse-fine", "--frames", "17"],
            "--fine-workdir: strategy 'coarse-fine' needs a fine model run, got none",
        ),
        (
            ["--workdir", str(coarse), "--fine-workdir", str(coarse), "--strategy", "coarse-fine", "--frames", "17"],
            "--fine-workdir: expected a model trained for interpolation",
        ),
        ([*args[1:], "--frames", "18"], "frames: coarse-fine reaches 1 + n * 8 latent frames"),
        ([*args[1:], "--frames", "17", "--segment-batch", "0"], "--segment-batch: expected 'auto' or a positive"),
        ([*args[1:], "--frames", "17", "--device-memory", "lots"], "--device-memory: expected a positive size"),
        (
            ["--workdir", str(coarse), "--strategy", "rollout", "--frames", "17", "--device-memory", "8GiB"],
            "--device-memory: not an option of strategy 'rollout'",
        ),
    ):
        assert cli(["sample", *bad, "--out", str(tmp_path / "bad")]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


@pytest.mark.slow(seconds=215)
def test_magicdrive_tiny_stages_grow_from_images_and_train_on_their_buckets(tmp_path, capsys):
    """MagicDrive-V2 at size=tiny: stage 1 (spatial-only, images) -> 2 (temporal blocks grown,
    images and videos of two resolutions) -> 3 (three resolutions, seq = 4), each from the last
    with train.init_from, on the configs' own buckets; then the stage-3 model's one-shot window."""
    from jaxdrive.train.run import Run

    data = write_synthetic(tmp_path / "data", train=2, frames=33, views=1)  # 3 scenes: buckets repeat clips
    runs = {}
    for stage in (1, 2, 3):
        config = load_config(
            f"{ROOT / 'configs' / 'magicdrive_v2.py'}:size=tiny,stage={stage}", [f"data.path={data}", "data.views=1"]
        )
        run = Run(config)  # every bucket's batch and grid checked
        assert len(run.buckets) == {1: 1, 2: 7, 3: 9}[stage]
        sets = [] if stage == 1 else [f"train.init_from={runs[stage - 1]}"]
        capsys.readouterr()
        runs[stage] = train(
            f"magicdrive_v2.py:size=tiny,stage={stage}",
            tmp_path / f"stage{stage}",
            data,
            "data.views=1",
            "model.depth=1",  # one layer: the stages' buckets and growth do not need two
            *sets,
            steps=1,
        )
        out = capsys.readouterr().err  # the CLI logs init_from's report (INFO) on stderr
        if stage == 2:  # the stage-1 model has no temporal blocks: they start at their zero init
            assert "kept the new initialisation of" in out and "temporal" in out
        if stage == 3:
            assert "kept the new initialisation" not in out
    # one window of all 33 frames (its sampling window is 17), tokens over seq = 4
    out = tmp_path / "sample"
    assert (
        cli(
            [
                "sample",
                "--workdir",
                str(runs[3]),
                "--strategy",
                "window",
                "--frames",
                "33",
                "--steps",
                "2",
                "--out",
                str(out),
                "--no-progress",
            ]
        )
        == 0
    )
    report = json.loads((out / "report.json").read_text())
    assert (report["strategy"], report["frames"], report["sequential_sampler_calls"]) == ("window", 33, 1)
    assert report["guidance"] == {"main": {"cfg": 2.0}}
    assert np.load(out / "latents.npy").shape == (2, 1, 33, 8, 14, 48)
    capsys.readouterr()  # a model trained on one length cannot: said before compiling
    assert (
        cli(
            [
                "sample",
                "--workdir",
                str(runs[1]),
                "--strategy",
                "window",
                "--frames",
                "33",
                "--out",
                str(tmp_path / "bad"),
            ]
        )
        == 2
    )
    assert "needs a model trained on several lengths" in capsys.readouterr().err


@pytest.mark.slow(seconds=141)
def test_stage_tiny_stages_train_htft_only_in_stage_2_and_stream(long_scenes, tmp_path, capsys):
    """STAGE at size=tiny: stage 1 (windows of recorded frames, no HTFT) -> 2 (HTFT added at zero,
    only its parameters trained, from stage 1); then ``--strategy streaming`` with the stage-2
    model, and the options it refuses. (Stage 3's loss, the model's own rollout as conditions, is
    tested in tests/test_streaming.py; its config in test_stage_configs_take_their_argument.)"""
    import jax

    from jaxdrive.train.run import Run, load_run_config, restore_params

    # two steps: the first has the warm-up's zero learning rate, and a model whose output layer is
    # still at its zero initialisation passes no gradient back to HTFT
    # shorter scans over the clip than the config's, and one layer (HTFT's, at depth // 2 - 1 = 0)
    fast = ["data.frames=7", "stream.rollout_steps=2", "model.depth=1"]
    runs = {1: train("stage.py:size=tiny,stage=1", tmp_path / "stage1", long_scenes, *fast, steps=2)}
    with pytest.raises(ValueError, match=r"train.init_from: HTFT learning \(STAGE stage 2\)"):
        Run(load_config(f"{ROOT / 'configs' / 'stage.py'}:size=tiny,stage=2", [f"data.path={long_scenes}", *MESH]))
    capsys.readouterr()
    runs[2] = train(
        "stage.py:size=tiny,stage=2", tmp_path / "stage2", long_scenes, f"train.init_from={runs[1]}", *fast, steps=2
    )
    assert "kept the new initialisation of" in capsys.readouterr().err  # HTFT's, at zero output (logged)

    def params(stage, ema):
        run = Run(load_run_config(runs[stage]))
        return jax.tree_util.tree_map(np.asarray, restore_params(run, runs[stage], ema=ema)[1])

    before, after = params(1, True), params(2, False)  # stage 2 starts from stage 1's EMA weights
    flat = dict(jax.tree_util.tree_leaves_with_path(after))
    for path, value in jax.tree_util.tree_leaves_with_path(before):  # the base frozen, bit for bit
        np.testing.assert_array_equal(flat[path], value, err_msg=jax.tree_util.keystr(path))
    assert float(np.abs(after["htft_0"]["linear_out"]["kernel"]).max()) > 0  # HTFT trained off its zero
    out = tmp_path / "stream"
    assert (
        cli(
            [
                "sample",
                "--workdir",
                str(runs[2]),
                "--strategy",
                "streaming",
                "--frames",
                "14",
                "--steps",
                "2",
                "--cfg",
                "1",
                "--out",
                str(out),
                "--no-progress",
            ]
        )
        == 0
    )
    report = json.loads((out / "report.json").read_text())
    assert (report["strategy"], report["frames"], report["sequential_sampler_calls"]) == ("streaming", 14, 13)
    assert report["compiled_programs"] == 1
    assert report["stream"]["taps"] == [-1, -5, -10] and report["stream"]["buffer_bytes"] > 0
    latents = np.load(out / "latents.npy")
    assert latents.shape == (2, 2, 14, 8, 14, 48) and np.isfinite(latents).all()
    capsys.readouterr()
    for workdir, extra, message in (
        (runs[2], ["--taps=-1,-11"], "--taps: expected offsets in [-10, -1]"),
        (runs[1], ["--taps=-1"], "--taps: HTFT streaming needs a model with HTFT layers"),
        (runs[2], ["--strategy", "rollout"], "--strategy: a model trained frame by frame"),
        (long_scenes, [], "--workdir: expected a run directory"),
    ):
        args = ["sample", "--workdir", str(workdir), "--strategy", "streaming", "--frames", "14", *extra]
        assert cli([*args, "--out", str(tmp_path / "bad")]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()
    with pytest.raises(ValueError, match=r"stream.taps: expected offsets in \[-10, -1\]"):
        Run(
            load_config(
                f"{ROOT / 'configs' / 'stage.py'}:size=tiny,stage=3",
                [f"data.path={long_scenes}", "stream.taps=-1,-12", *MESH],
            )
        )
    with pytest.raises(ValueError, match=r"stream.taps: HTFT needs a model with HTFT layers"):
        Run(
            load_config(
                f"{ROOT / 'configs' / 'stage.py'}:size=tiny,stage=1",
                [f"data.path={long_scenes}", "stream.taps=-1", *MESH],
            )
        )


def test_stage_sampler_shifts_as_its_training_step():
    """At paper size the shift is the resolution rule's (flow.shift=0), which counts the frames of
    one sampler call: a streaming model's are the window's 3, in the sampler as in the step (not
    the 12 of data.frames)."""
    from types import SimpleNamespace

    from jaxdrive.flow import resolution_shift
    from jaxdrive.generate.samples import Sampling
    from jaxdrive.generate.windows import WindowModel
    from jaxdrive.models.latents import LatentCodec
    from jaxdrive.train.stream_step import _shift

    config = load_config(f"{ROOT / 'configs' / 'stage.py'}:size=paper,stage=3")
    d = config.data
    assert config.flow.shift == 0 and d.frames == 12
    spec = Sampling(config.model, LatentCodec("space_to_depth", 8), None, d, config.flow, stream=config.stream)
    shift = WindowModel.from_sampling(spec, None).shift
    assert shift == pytest.approx(_shift(SimpleNamespace(flow=config.flow), (d.height, d.width)))
    assert shift == pytest.approx(resolution_shift(512, 768, 3))


@pytest.mark.parametrize("stage", [1, 2, 3])
@pytest.mark.parametrize("size", ["tiny", "paper"])
def test_stage_configs_take_their_argument(size, stage):
    config = load_config(f"{ROOT / 'configs' / 'stage.py'}:size={size},stage={stage}")
    check_sections(config)
    s = config.stream
    assert s.enabled and s.buffer == 10 and config.flow.foreground_k > 0
    assert bool(config.model.htft_layers) == (stage > 1) and bool(s.taps) == (stage > 1)
    assert config.optim.trainable == (("htft_",) if stage == 2 else ())
    assert s.self_rollout == (stage == 3)
    if size == "paper":  # what makes stage 3 fit 80 GiB at fsdp 32 (docs/results/memory.md)
        assert config.model.remat == "full" and config.latents.vae_frame_batch == 1 and config.model.scan_layers
    with pytest.raises(ValueError, match=r"config argument stage: expected"):
        load_config(f"{ROOT / 'configs' / 'stage.py'}:size={size},stage=4")


@pytest.mark.parametrize("stage", [1, 2, 3])
def test_magicdrive_paper_config_encodes_a_clip_a_device_at_a_time(stage):
    """What makes MagicDrive-V2's stage-3 step fit 80 GiB at fsdp 8 x seq 4 (docs/results/memory.md): its 3D
    VAE encoding 3 clips x 6 views of 848 x 1600 a device at once held 420 GiB."""
    config = load_config(f"{ROOT / 'configs' / 'magicdrive_v2.py'}:stage={stage}")
    check_sections(config)
    assert config.model.remat == "full" and config.latents.vae_clip_batch == 1 and config.model.scan_layers
    assert config.latents.vae_mode == "chunked" and not config.latents.precomputed
