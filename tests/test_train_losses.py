"""The losses the train step adds to MiLA eq. 15: STAGE's foreground-weighted map W_aux and
LongDWM's fine-to-coarse distillation from a frozen fine model (eq. 7-8)."""

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdrive import flow
from jaxdrive.config import load_config
from jaxdrive.models.dit import DiT
from jaxdrive.models.dit.conditions import Conditions
from jaxdrive.train import distill_step, flow_step
from jaxdrive.train.run import Run

from train_fixtures import save_run, write_synthetic

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "configs" / "tiny.py"
SMALL = ["data.views=2", "data.batch_size=2", "model.depth=1", "optim.warmup_steps=2", "train.log_every=1"]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    # scenes 2 and 3: scene 2 has objects in front of the first two cameras
    return write_synthetic(tmp_path_factory.mktemp("synth") / "data", first=2, train=2, frames=11)


def config(dataset, *sets):
    return load_config(TINY, [f"data.path={dataset}", *SMALL, "mesh.data=2", "mesh.seq=4", *sets])


def one_batch(run):
    return run.global_batch([next(iter(run.dataset()))])


def micro(batch):
    return jax.tree_util.tree_map(lambda x: x[0], batch)


# ------------------------------------------------------------------------- STAGE's W_aux
@pytest.mark.slow(seconds=9)
def test_foreground_weighting_is_eq15_times_w_aux(dataset):
    one = ["data.frames=5", "mesh.data=1", "mesh.seq=1"]
    plain = Run(config(dataset, *one), devices=jax.devices()[:1])
    weighted = Run(config(dataset, *one, "flow.foreground_k=4", "flow.foreground_c=0.5"), devices=jax.devices()[:1])
    batch = one_batch(weighted)
    assert sorted(batch["loss"]) == ["box_valid", "boxes", "cam_to_ego", "intrinsics"]
    params = plain.training.dit.init_params(0, views=2, frames=5, height=8, width=14)
    key = jax.random.key(3)

    @jax.jit
    def losses(inputs):
        loss_w = flow_step.flow_loss_fn(weighted.training, params, None, inputs, key)[0]
        without = {k: v for k, v in inputs.items() if k != "loss"}
        loss_plain = flow_step.flow_loss_fn(plain.training, params, None, without, key)[0]
        # the same loss by hand: the step's draws, the map of each frame's boxes, eq. 15 weighted
        t = weighted.training
        video = without["video"]
        x = t.codec.encode(None, video)
        k_levels, k_noise = jax.random.split(key)
        noise = jax.random.normal(k_noise, x.shape)
        _, cond, levels, _ = flow_step.draw_levels(k_levels, x, t.flow, height=32, width=56)
        x_t = flow.add_noise(x, noise, levels)
        out = t.dit.forward(params, x_t, levels, without["cond"].replace(cond_latents=x, cond_mask=cond))
        v = flow.velocity_from_output(out, x_t, levels, t.model.prediction, t.model.prediction_min_sigma)
        f = inputs["loss"]
        w = flow.foreground_weight_map(
            f["boxes"],
            f["box_valid"],
            f["intrinsics"],
            f["cam_to_ego"],
            map_hw=(8, 14),
            image_hw=(32, 56),
            k=4.0,
            c=0.5,
        )
        by_hand = flow.flow_loss(v, x, noise, cond_mask=cond, weight_map=w)
        no_boxes = dict(inputs, loss=dict(f, box_valid=jnp.zeros_like(f["box_valid"])))
        loss_empty = flow_step.flow_loss_fn(weighted.training, params, None, no_boxes, key)[0]
        return loss_w, loss_plain, by_hand, loss_empty, jnp.max(w)

    with jax.set_mesh(weighted.mesh):
        loss_w, loss_plain, by_hand, loss_empty, w_max = map(float, losses(micro(batch)))
    assert w_max > 1.5  # the clips have boxes in view
    assert loss_w == pytest.approx(by_hand, rel=1e-5)
    assert loss_w != pytest.approx(loss_plain, rel=1e-3)
    assert loss_empty == pytest.approx(loss_plain, rel=1e-6)  # no object: W_aux is all ones


# ------------------------------------------------------------------------- condition patterns, JDC anchors
PATTERNS = [
    "data.frames=5",
    "flow.patterns=prefix,ends,anchors",
    "flow.pattern_rates=0.25,0.25,0.5",
    "flow.anchor_every=2",
    "flow.cond_frames=2",
    "flow.jdc_anchor_rate=1.0",
    "flow.jdc_alpha1=0.1",
]


@pytest.mark.slow(seconds=5)
def test_jdc_anchors_enter_eq15_with_their_own_noise(dataset):
    """The loss is eq. 15 on x_t from jdc_training_anchors, with noise_eff as the target's noise;
    the anchor frames count (moving the target on them moves the loss)."""
    one = ["mesh.data=1", "mesh.seq=1"]
    run = Run(config(dataset, *PATTERNS, *one), devices=jax.devices()[:1])
    t = run.training
    params = t.dit.init_params(0, views=2, frames=5, height=8, width=14)
    inputs = {k: v for k, v in micro(one_batch(run)).items() if k != "loss"}

    @jax.jit
    def both(inputs, key):
        loss = flow_step.flow_loss_fn(t, params, None, inputs, key)[0]
        x = t.codec.encode(None, inputs["video"])
        k_levels, k_noise = jax.random.split(key)
        noise = jax.random.normal(k_noise, x.shape)
        _, cond, levels, anchor = flow_step.draw_levels(k_levels, x, t.flow, height=32, width=56)
        x_t, eps = flow.jdc_training_anchors(jax.random.fold_in(k_noise, 1), x, noise, levels, anchor, 0.1)
        out = t.dit.forward(params, x_t, levels, inputs["cond"].replace(cond_latents=x, cond_mask=cond))
        v = flow.velocity_from_output(out, x_t, levels, t.model.prediction, t.model.prediction_min_sigma)
        by_hand = flow.flow_loss(v, x, eps, cond_mask=cond)
        plain_noise = flow.flow_loss(v, x, noise, cond_mask=cond)
        return loss, by_hand, plain_noise, jnp.sum(anchor)

    with jax.set_mesh(run.mesh):
        found = False
        for seed in range(8):  # a key whose clips hold anchors
            loss, by_hand, plain_noise, n_anchors = map(float, both(inputs, jax.random.key(seed)))
            assert loss == pytest.approx(by_hand, rel=1e-5)
            if n_anchors > 0:
                found = True
                assert loss != pytest.approx(plain_noise, rel=1e-3)
        assert found


@pytest.mark.slow(seconds=15)
def test_a_step_with_every_pattern_and_jdc_anchors_is_finite(dataset):
    run = Run(config(dataset, *PATTERNS, "mesh.data=1", "mesh.seq=1"), devices=jax.devices()[:1])
    batch = one_batch(run)
    state, optimizer, shardings = run.init_state()
    with jax.set_mesh(run.mesh):
        _, m = run.step_fn(optimizer, shardings)(state, run.frozen_params(), batch)
    m = jax.device_get(m)
    assert np.isfinite(m["loss"]) and m["loss"] > 0 and m["skipped"] == 0


# ------------------------------------------------------------------------- LongDWM distillation
def test_segment_waypoints_match_the_pipeline_from_that_frame(dataset):
    from jaxdrive.data.tfds_io import open_source
    from jaxdrive.data.transforms import sample_clip

    clip = open_source(dataset, "train")[0]
    whole = sample_clip(clip, size=(32, 56), frames=9, stride=1)
    poses = jnp.asarray(whole["ego_to_world"])[None]
    controls = Conditions(
        waypoints=jnp.asarray(whole["waypoints"])[None], fps=jnp.ones((1,)), boxes=jnp.asarray(whole["boxes"])[None]
    )
    seg = distill_step.segment_conditions(controls, poses, 4, 5)
    want = sample_clip(clip, size=(32, 56), frames=5, stride=1, start=4)
    np.testing.assert_allclose(seg.waypoints[0], want["waypoints"], atol=1e-4)
    np.testing.assert_array_equal(seg.boxes[0], want["boxes"])
    coarse = distill_step.coarse_conditions(Conditions(waypoints=controls.waypoints, fps=jnp.full((1,), 12.0)), 5)
    np.testing.assert_array_equal(coarse.waypoints[0], whole["waypoints"][::4])
    assert float(coarse.fps[0]) == 3.0


@pytest.mark.slow(seconds=8)
def test_teacher_segments_one_at_a_time_match_the_folded_batch():
    """The step's lax.map over segments = flow.split_segments + one batched call + eq. 8's
    coarse_from_segments (the paper's description)."""
    cfg = load_config(TINY, ["model.depth=1", "model.controls.waypoints=false"]).model
    teacher = DiT(cfg)
    b, v, f, k = 2, 2, 9, 5
    params = teacher.init_params(1, views=v, frames=k, height=8, width=14)
    keys = jax.random.split(jax.random.key(0), 4)
    x = jax.random.normal(keys[0], (b, v, f, 8, 14, cfg.in_channels))
    sigma = jnp.array([0.3, 0.8])
    cond = jnp.zeros((b, 3), bool).at[:, 0].set(True)
    levels, cond_dense = distill_step.dense_levels(sigma, cond, f, k)
    assert (
        levels.shape == (b, f) and bool(jnp.all(levels[:, 0] == 0)) and bool(jnp.all(levels[:, 1:] == sigma[:, None]))
    )
    x_t = flow.add_noise(x, jax.random.normal(keys[1], x.shape), levels)
    controls = Conditions(
        text=jax.random.randint(keys[2], (b, cfg.text_len), 0, 512),
        text_mask=jnp.ones((b, cfg.text_len), bool),
        fps=jnp.array([12.0, 6.0]),
        intrinsics=jnp.tile(jnp.array([[40.0, 0, 28], [0, 40, 16], [0, 0, 1]]), (b, v, 1, 1)),
        cam_to_ego=jnp.tile(jnp.eye(4), (b, v, 1, 1)),
    )
    poses = jnp.tile(jnp.eye(4), (b, f, 1, 1))

    @jax.jit
    def both(x, x_t):  # the boundary rules themselves: tests/test_distill.py
        got = distill_step.teacher_coarse_estimate(
            teacher,
            params,
            x,
            x_t,
            levels,
            cond_dense,
            {"cond": controls, distill_step.POSES: poses},
            segment_len=k,
            boundary="mean",
        )
        n = 2
        rep = jax.tree_util.tree_map(lambda a: jnp.repeat(a, n, axis=0), controls)
        xs, ls = flow.split_segments(x_t, k), flow.split_segments(levels, k)
        out = teacher.forward(
            params,
            xs,
            ls,
            rep.replace(cond_latents=flow.split_segments(x, k), cond_mask=flow.split_segments(cond_dense, k)),
        )
        vs = flow.velocity_from_output(out, xs, ls, cfg.prediction, cfg.prediction_min_sigma)
        return got, flow.coarse_from_segments(flow.data_from_velocity(xs, vs, ls), b)

    got, want = both(x, x_t)
    assert got.shape == (b, v, 3, 8, 14, cfg.in_channels)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)


def write_teacher(dataset, workdir):
    """A fine model's run directory: its config and one checkpoint (no training needed)."""
    return save_run(config(dataset, "data.frames=5", "train.seed=7"), workdir)


@pytest.mark.slow(seconds=29)
def test_distillation_trains_the_coarse_model_against_the_fine_one(dataset, tmp_path):
    saved = write_teacher(dataset, tmp_path / "fine")
    cfg = config(
        dataset,
        "data.frames=9",
        f"flow.distill_teacher={tmp_path / 'fine'}",
        "flow.distill_segment_len=5",
        "flow.distill_weight=0.5",
    )
    run = Run(cfg)
    assert run.latent_frames == 3 and run.frame_stride == 4  # coarse frames 0, 4, 8
    assert run.tokens_per_step == 2 * 2 * 3 * 4 * 7
    restored = run.frozen_params()["teacher"]
    for a, b in zip(jax.tree_util.tree_leaves(restored), jax.tree_util.tree_leaves(saved.ema)):
        np.testing.assert_array_equal(a, b)
    batch = one_batch(run)
    assert batch["video"].shape[3] == 9 and batch["teacher"][distill_step.POSES].shape[2:] == (9, 4, 4)
    # sampling reads coarse frames: every 4th source frame, at a quarter of the frame rate
    from jaxdrive.generate.samples import dataset_inputs

    inputs = dataset_inputs(run.sampling(), frames=run.latent_frames)
    fine_fps = float(np.asarray(jax.device_get(batch["teacher"]["cond"].fps))[0, 0])
    assert inputs["video"].shape[2] == 3 and float(inputs["cond"].fps[0]) == pytest.approx(fine_fps / 4)
    state, optimizer, shardings = run.init_state()
    with jax.set_mesh(run.mesh):
        _, m = run.step_fn(optimizer, shardings)(state, run.frozen_params(), batch)
    m = jax.device_get(m)
    assert np.isfinite(m["distill_loss"]) and m["distill_loss"] > 0
    assert m["loss"] == pytest.approx(m["flow_loss"] + 0.5 * m["distill_loss"], rel=1e-5)
    assert m["skipped"] == 0


@pytest.mark.parametrize(
    "sets, match",
    [
        (["flow.tpd=true"], "flow.tpd"),
        (["flow.jdc_anchor_rate=0.5"], "flow.jdc_anchor_rate"),
        (["data.frames=8"], "data.frames"),
        (["flow.distill_teacher=/nonexistent/run"], "flow.distill_teacher"),
        (["flow.distill_segment_len=1"], "flow.distill_segment_len"),
    ],
)
def test_bad_distillation_configs_fail_before_compiling(dataset, sets, match):
    base = ["data.frames=9", "flow.distill_teacher=/nonexistent/run", "flow.distill_segment_len=5"]
    with pytest.raises(ValueError, match=match):
        Run(config(dataset, *base, *sets))
