"""The DiT's training engine on 8 fake CPU devices: the flow step's levels and latents, a sharded
step against the single-device step, exact resume after SIGTERM, non-finite losses stopping the
run, bad configs rejected before compiling, and ``jaxdrive train`` / ``sample`` from the CLI."""

import json
import logging
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdrive.cli import main as cli
from jaxdrive.config import FlowConfig, load_config
from jaxdrive.data.batches import model_inputs
from jaxdrive.models.latents import depth_to_space, space_to_depth
from jaxdrive.train import flow_step
from jaxdrive.train.metrics import read_metrics
from jaxdrive.train.run import Run, train

from train_fixtures import MACHINERY, assert_same_state, train_with_a_stop, write_synthetic

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "configs" / "tiny.py"


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return write_synthetic(tmp_path_factory.mktemp("synth") / "data")


SMALLER = [
    "data.views=2",
    "data.frames=5",
    "data.batch_size=2",
    "model.depth=1",
    "optim.warmup_steps=2",
    "train.log_every=1",
]


def tiny(dataset, *sets):
    """configs/tiny.py shrunk for tests: 2 views, 5 frames, one layer, on a data=2 x seq=4 mesh."""
    return load_config(
        TINY,
        [
            f"data.path={dataset}",
            *SMALLER,
            "train.steps=4",
            "train.checkpoint_every=2",
            "mesh.data=2",
            "mesh.seq=4",
            *sets,
        ],
    )


def test_space_to_depth_round_trip_and_layout():
    video = jax.random.normal(jax.random.key(0), (2, 3, 5, 8, 12, 3))
    z = space_to_depth(video, 4)
    assert z.shape == (2, 3, 5, 2, 3, 48)
    np.testing.assert_array_equal(depth_to_space(z, 4), video)
    # latent (0, 0) holds the top-left 4 x 4 patch, row-major, channels last
    np.testing.assert_array_equal(z[0, 0, 0, 0, 0], video[0, 0, 0, :4, :4].reshape(-1))


def test_draw_levels_condition_anchor_and_generated_frames():
    x = jnp.zeros((512, 1, 6, 2, 2, 4))
    cfg = FlowConfig(cond_frames=2, cond_frames_random=False, jdc_anchor_rate=0.5, jdc_slope=0.5)
    sigma, cond, levels, anchor = flow_step.draw_levels(jax.random.key(1), x, cfg, height=16, width=16)
    assert cond.shape == (512, 6) and bool(jnp.all(cond[:, :2])) and not bool(jnp.any(cond[:, 2:]))
    np.testing.assert_array_equal(levels[:, :2], 0.0)  # clean condition frames
    np.testing.assert_allclose(levels[:, 2:5], jnp.broadcast_to(sigma[:, None], (512, 3)))
    anchored = np.isclose(levels[:, 5], 0.5 * sigma)  # g = slope * sigma
    assert np.all(anchored | np.isclose(levels[:, 5], sigma))
    assert 0.35 < anchored.mean() < 0.65  # about the anchor rate
    np.testing.assert_array_equal(anchor[:, 5], anchored)  # the mask says which
    assert not bool(jnp.any(anchor[:, :5]))
    rand = flow_step.draw_levels(jax.random.key(2), x, FlowConfig(cond_frames=3), height=16, width=16)[1]
    assert set(np.asarray(rand.sum(1)).tolist()) == {0, 1, 2, 3}  # 0..cond_frames per clip


def test_model_inputs_map_the_pipeline_drops(dataset):
    cfg = tiny(dataset)
    run = Run(cfg)
    batch = next(iter(run.dataset()))
    batch["drop"] = {n: np.array([True, False]) for n in ("text", "camera", "trajectory", "boxes", "map")}
    inputs = model_inputs(batch, run.training.model)
    assert sorted(inputs["cond"].drop) == ["camera", "text", "waypoints"]  # the tiny model's conditions
    assert inputs["cond"].text.dtype == np.int32 and inputs["cond"].text.shape == (2, cfg.model.text_len)
    assert inputs["video"].shape == (2, 2, 5, 32, 56, 3)


@pytest.mark.slow(seconds=38)
def test_sharded_step_matches_single_device(dataset):
    cfg = tiny(dataset, "train.steps=1")
    losses, grads = {}, {}
    for name, devices in (("mesh", None), ("single", jax.devices()[:1])):
        c = cfg if devices is None else tiny(dataset, "train.steps=1", "mesh.data=1", "mesh.seq=1")
        run = Run(c, devices=devices)
        state, optimizer, shardings = run.init_state()
        batch = run.global_batch([next(iter(run.dataset()))])
        with jax.set_mesh(run.mesh):
            new, metrics = run.step_fn(optimizer, shardings)(state, None, batch)
        losses[name], grads[name] = float(metrics["loss"]), float(metrics["grad_norm"])
    assert losses["mesh"] == pytest.approx(losses["single"], rel=1e-5)
    assert grads["mesh"] == pytest.approx(grads["single"], rel=1e-4)


@pytest.mark.slow(seconds=27)
def test_resume_after_sigterm_is_bit_exact(dataset, tmp_path):
    cfg = tiny(dataset, *MACHINERY)
    whole = train(cfg, tmp_path / "whole", progress=False)
    assert whole["status"] == "done" and whole["step"] == 4

    part, resumed = train_with_a_stop(cfg, tmp_path / "split", stop_at=2)
    assert part["status"] == "interrupted" and part["step"] == 2
    assert resumed["status"] == "done" and resumed["step"] == 4
    assert_same_state(whole["state"], resumed["state"])
    rows = read_metrics(tmp_path / "split")
    assert [r["step"] for r in rows] == [1, 2, 3, 4] and all(np.isfinite(r["loss"]) for r in rows)


@pytest.mark.slow(seconds=11)
def test_non_finite_losses_skip_and_stop_with_the_last_good_state(dataset, tmp_path, monkeypatch, caplog):
    cfg = tiny(dataset, *MACHINERY, "train.max_bad_steps=2", "train.steps=6", "train.checkpoint_every=100")
    original = Run.global_batch
    calls = []

    def poisoned(self, micro_batches):
        calls.append(1)
        if len(calls) >= 2:  # every batch from step 2 on holds a NaN
            for b in micro_batches:
                b["video"] = np.array(b["video"], copy=True)
                b["video"][0, 0, 0, 0, 0, 0] = np.nan
        return original(self, micro_batches)

    monkeypatch.setattr(Run, "global_batch", poisoned)
    messages = []  # the deprecated log= callable still gets the messages, for one release
    with (
        caplog.at_level(logging.WARNING, logger="jaxdrive.train.run"),
        pytest.warns(DeprecationWarning, match=r"jaxdrive\.train\.run\.train\(log=\.\.\.\) is deprecated"),
    ):
        out = train(cfg, tmp_path / "nan", progress=False, log=messages.append)
    assert out["status"] == "diverged" and out["step"] == 3
    assert any(
        "2 non-finite losses in a row at step 3" in r.getMessage()
        for r in caplog.records
        if r.levelno == logging.WARNING
    )
    assert any("2 non-finite losses in a row at step 3" in m for m in messages)
    state = out["state"]
    assert int(state.skipped) == 2 and int(state.step) == 3
    for leaf in jax.tree_util.tree_leaves(state.params):
        assert np.all(np.isfinite(np.asarray(leaf)))
    assert (tmp_path / "nan" / "checkpoints" / "3").is_dir()
    rows = {r["step"]: r for r in read_metrics(tmp_path / "nan")}
    assert [(rows[s]["skipped"], rows[s]["bad_steps"], rows[s]["last_good_step"]) for s in (2, 3)] == [
        (1, 1, 1),
        (2, 2, 1),
    ]
    events = b"".join(p.read_bytes() for p in (tmp_path / "nan" / "tensorboard").rglob("*tfevents*"))
    assert b"skipped" in events and b"last_good_step" in events


@pytest.mark.parametrize(
    "sets, match",
    [
        (["mesh.data=3"], r"mesh: expected sizes whose product is the device count 8"),
        (["train.on_save_error=retry"], r"train.on_save_error: expected one of \['continue', 'stop'\], got 'retry'"),
        (["data.batch_size=3", "mesh.data=2"], r"data.batch_size: expected a multiple of"),
        (["model.heads=3", "mesh.tensor=2", "mesh.seq=2"], r"model.heads: expected a multiple of the mesh axis tensor"),
        (["model.in_channels=16"], r"model.in_channels: expected 48 to match the latents"),
        (["data.height=30"], r"data.height, data.width: expected multiples"),
    ],
)
def test_bad_configs_fail_before_compiling(dataset, sets, match):
    with pytest.raises(ValueError, match=match):
        Run(tiny(dataset, *sets))


def test_cli_rejects_unknown_keys_and_bad_meshes(dataset, tmp_path, capsys):
    assert cli(["train", "--config", str(TINY), "--workdir", str(tmp_path), "--set", "optim.lrate=1"]) == 2
    assert "unknown key 'lrate' in optim" in capsys.readouterr().err
    assert cli(["train", "--config", str(TINY), "--workdir", str(tmp_path), "--set", "train.steps=x"]) == 2
    assert "train.steps: expected int, got 'x'" in capsys.readouterr().err
    assert (
        cli(
            [
                "train",
                "--config",
                str(TINY),
                "--workdir",
                str(tmp_path),
                "--mesh",
                "data=3",
                "--set",
                f"data.path={dataset}",
            ]
        )
        == 2
    )
    assert "product is the device count 8" in capsys.readouterr().err


@pytest.mark.slow(seconds=22)
def test_cli_train_then_sample_writes_video_and_grid(dataset, tmp_path):
    work = tmp_path / "run"
    args = [
        "train",
        "--config",
        str(TINY),
        "--workdir",
        str(work),
        "--steps",
        "2",
        "--checkpoint-every",
        "1",
        "--mesh",
        "data=2,seq=4",
        "--no-progress",
    ]
    for s in [f"data.path={dataset}", *SMALLER, *MACHINERY]:
        args += ["--set", s]
    assert cli(args) == 0
    rows = [json.loads(line) for line in (work / "metrics.jsonl").read_text().splitlines()]
    assert rows[-1]["step"] == 2 and "loss" in rows[-1] and "tokens_per_s" in rows[-1]
    assert any(p.name.startswith("events") for p in (work / "tensorboard").iterdir())
    out = tmp_path / "sample"
    assert (
        cli(
            [
                "sample",
                "--workdir",
                str(work),
                "--frames",
                "9",
                "--steps",
                "2",
                "--cfg",
                "2.0",
                "--out",
                str(out),
                "--mesh",
                "data=1,seq=8",
            ]
        )
        == 0
    )
    assert (out / "sample.mp4").stat().st_size > 0 and (out / "frames.png").stat().st_size > 0
    latents = np.load(out / "latents.npy")
    assert latents.shape == (1, 2, 9, 8, 14, 48) and np.all(np.isfinite(latents))


@pytest.mark.parametrize("name", ["tiny", "world", "small", "mila", "magicdrive_v2", "longdwm", "stdit3_xl"])
def test_every_config_loads_and_checks(name):
    from jaxdrive.config_checks import check_sections

    config = load_config(ROOT / "configs" / f"{name}.py")
    check_sections(config)
    assert config.model.in_channels == (48 if config.latents.source == "space_to_depth" else 16)
    if name == "world":  # the controls the bench found learnable, and not the others
        on = config.model.controls.enabled()
        assert {"waypoints", "boxes", "camera"} <= set(on) and config.model.controls.layout, on
        assert not {"trajectory", "map"} & set(on) and not config.model.controls.boxes, on
        assert load_config(f"{ROOT / 'configs' / 'world.py'}:steps=10").train.steps == 10
        # the levels near pure noise get the gradient (docs/results/demo.md: shift 1's samples fell below repeat)
        assert config.flow.shift == 3.0 and load_config(ROOT / "configs" / "tiny.py").flow.shift == 1.0


@pytest.mark.slow(seconds=100)
def test_demo_runs_end_to_end(tmp_path, capsys):
    # no mesh given: the demo fits its batch of 2 to the 8 test devices (data 2 x seq 4)
    sets = [*SMALLER, "train.sample_steps=2", "train.checkpoint_every=100"]
    args = [
        "demo",
        "--workdir",
        str(tmp_path / "demo"),
        "--steps",
        "2",
        "--scenes",
        "4",
        "--frames",
        "11",
        "--routes",
        "stop",
        "--no-progress",
    ]
    for s in sets:
        args += ["--set", s]
    assert cli(args) == 0
    out = capsys.readouterr().out
    for name in (
        "sample.mp4",
        "frames.png",
        "loss.png",
        "quality.json",
        "repeat last given",
        "mesh: data=2 x seq=4 over the 8 cpu devices",
    ):
        assert name in out
    assert (tmp_path / "demo" / "samples" / "demo" / "sample.mp4").stat().st_size > 0
    q = json.loads((tmp_path / "demo" / "samples" / "demo" / "quality.json").read_text())
    assert len(q["per_frame"]) == 11 and q["cond_frames"] == 2 and q["window"] == 5
    assert q["first_window"]["frames"] == [2, 3, 4] and q["all_generated"]["frames"] == list(range(2, 11))
    assert (tmp_path / "demo" / "loss.png").stat().st_size > 0
    # control, shown: the recorded route and 'stop' from the same given frames, each against its render
    assert "| rollout @ stop |" in out and "| stop | rollout |" in out and "routes.png" in out
    routes = json.loads((tmp_path / "demo" / "samples" / "routes" / "eval.json").read_text())
    assert routes["routes"] == ["recorded", "stop"] and routes["clips"] == 2
    # the demo's recipe (configs/world.py) draws the boxes as a layout: a row with them removed
    assert any(k.endswith("(no boxes)") for k in routes["strategies"]), list(routes["strategies"])
    assert (tmp_path / "demo" / "samples" / "routes" / "routes.png").stat().st_size > 0
    # the default recipe follows routes (configs/world.py:control=warp): its training scenes are rendered
    # along the counterfactual routes of data.routes, and the route following is read from the pixels
    from jaxdrive.data.synthetic import read_counterfactuals

    assert "the training scenes along" in out
    # by default a stop, a lane change and a turn (those the 3 training scenes can drive)
    assert set(read_counterfactuals(tmp_path / "demo" / "data")["train_routes"]) <= {"stop", "lane-left", "branch"}
    assert routes.get("route_following_ceiling"), sorted(routes)


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--train-routes", "stop,zigzag"], "--train-routes: expected distinct comma-separated routes from"),
        (["--train-routes", "lane-right"], "--train-routes: expected routes of the config's data.routes (stop, "),
        (
            ["--config", str(Path(__file__).parents[1] / "configs" / "world.py"), "--train-routes", "stop"],
            "--train-routes: expected routes of the config's data.routes (none), got stop",
        ),
    ],
)
def test_demo_refuses_training_routes_its_config_does_not_mix(tmp_path, capsys, extra, message):
    assert cli(["demo", "--workdir", str(tmp_path / "demo"), "--steps", "1", *extra]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "demo").exists()


@pytest.mark.optimized_xla
@pytest.mark.slow(seconds=123)
def test_demo_recipe_learns_a_continuation_not_noise(dataset, tmp_path):
    """A short run of the demo recipe (configs/tiny.py on 2 views, 5 frames): its first sampled
    window must have the spread of real latents (the 64-wide velocity model once gave 3x the
    data's standard deviation, saturated colour noise) and beat noise on PSNR by a margin.
    On one device, as the demo runs on a CPU: 8 fake devices on 2 cores made it slower (101 CPU-s
    against 85), for the same figures (final loss 0.3285, PSNR 22.63 against noise's 17.45)."""
    from jaxdrive.eval.frames import clip_quality
    from jaxdrive.generate.samples import generate

    config = load_config(
        TINY,
        [
            f"data.path={dataset}",
            "data.views=2",
            "data.frames=5",
            "train.steps=150",
            "train.checkpoint_every=0",
            "train.log_every=50",
            "optim.warmup_steps=10",
        ],
    )
    out = train(config, tmp_path / "run", progress=False, devices=jax.devices()[:1])
    assert out["run"].mesh.devices.size == 1
    g = generate(out["run"].sampling(), out["state"].ema, frames=5, guidance=1.0, steps=10)
    data = out["run"].codec.encode(None, g.recorded)
    ratio = float(np.std(g.latents[:, :, g.cond_frames :]) / np.std(np.asarray(data)[:, :, g.cond_frames :]))
    assert 0.75 < ratio < 1.25, ratio
    q = clip_quality(g.video[0], g.recorded[0], cond_frames=g.cond_frames, window=g.window)["first_window"]
    assert q["psnr"] > q["noise_psnr"] + 3.0, q
    assert q["psnr"] > q["repeat_psnr"] - 3.0, q  # the goal for the demo's first window


@pytest.mark.slow(seconds=14)
@pytest.mark.parametrize("choice", ["continue", "stop"])
def test_a_checkpoint_that_cannot_be_written_keeps_the_earlier_ones(dataset, tmp_path, monkeypatch, choice, caplog):
    """Disk full at step 4's save (simulated): the message names it, checkpoint 2 stays readable, and
    the run goes on to step 6 or stops at 4, as train.on_save_error says."""
    from jaxdrive.train.checkpoint import Checkpoints

    cfg = tiny(dataset, *MACHINERY, "train.steps=6", "train.checkpoint_every=2", f"train.on_save_error={choice}")
    save = Checkpoints.save

    def full_disk(self, step, *args, **kwargs):
        if step == 4:
            raise OSError(28, "No space left on device")
        return save(self, step, *args, **kwargs)

    monkeypatch.setattr(Checkpoints, "save", full_disk)
    with caplog.at_level(logging.WARNING, logger="jaxdrive.train.run"):
        out = train(cfg, tmp_path / choice, progress=False)
    messages = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any(
        "checkpoints/4 could not be written (OSError: [Errno 28] No space left on device); checkpoints kept: [2]" in m
        for m in messages
    )
    steps = sorted(int(p.name) for p in (tmp_path / choice / "checkpoints").iterdir() if p.name.isdigit())
    if choice == "continue":
        assert (out["status"], out["step"], steps) == ("done", 6, [2, 6])
    else:
        assert (out["status"], out["step"], steps) == ("save_failed", 4, [2])
        assert any("stopping at step 4 (train.on_save_error = 'stop')" in m for m in messages)
    ck = Checkpoints(tmp_path / choice)
    state, _, _ = ck.restore(2, out["run"].abstract_state()[0])
    assert int(state.step) == 2
    ck.close()


@pytest.mark.slow(seconds=38)
def test_a_corrupt_shard_stops_the_run_or_is_skipped_and_counted(dataset, tmp_path):
    """Two of the three training clips in truncated shards: without data.skip_bad_records the run
    stops with a ValueError naming the first shard it meets; with it the run trains to the end, every
    batch full, and metrics.jsonl counts the clips replaced (kept by the checkpoint for a resume)."""
    import re

    from jaxdrive.data.tfds_io import open_source, write_dataset

    from shard_faults import shard_files, truncate

    splits = {
        s: [open_source(dataset, s)[i] for i in range(len(open_source(dataset, s)))] for s in ("train", "validation")
    }
    data = write_dataset(tmp_path / "data", splits, shard_bytes=1)  # one clip per shard
    shards = shard_files(data)
    for shard in shards[1:]:
        truncate(shard)
    cfg = tiny(data, *MACHINERY)
    with pytest.raises(ValueError, match="|".join(re.escape(f"{s}: record 0 (clip") for s in shards[1:])):
        train(cfg, tmp_path / "strict", progress=False)

    cfg = tiny(data, *MACHINERY, "data.skip_bad_records=true")  # the resume test's step: compiled once
    it = iter(Run(cfg).dataset())
    expected = np.cumsum([int(next(it)["bad_records"]) for _ in range(4)])
    assert expected[-1] >= 4  # >= 1 unreadable clip in every batch of 2
    out = train(cfg, tmp_path / "run", progress=False)
    assert out["status"] == "done" and out["step"] == 4
    assert [r["bad_records"] for r in read_metrics(tmp_path / "run")] == list(expected)
    assert out["bad_records"] == expected[-1]
    again = train(cfg, tmp_path / "run", progress=False)  # resumed at its end: the count comes back
    assert again["step"] == 4 and again["bad_records"] == expected[-1]
