"""Training windows whose given frames are the model's own output (``flow.self_rollout_rate``):
the pipeline cuts a rollout's two windows, the step samples the first with the sampler's own code
and trains the second on its last frames, warping from its own generated frame on the device."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdrive.config import load_config
from jaxdrive.train.run import Run

from train_fixtures import write_synthetic

ROOT = Path(__file__).resolve().parents[1]
SETS = [
    "model.controls.warp=true",
    "model.controls.reference_frame=warp",
    "model.depth=1",
    "model.final_conv=0",
    "data.views=2",
    "data.batch_size=2",
    "data.frames=5",
    "data.warp_frame=1",
    "data.warp_depth=15",
    "flow.cond_frames=2",
    "flow.self_rollout_steps=2",
    "mesh.data=2",
    "mesh.seq=4",
    "optim.warmup_steps=1",
]


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_synthetic(tmp_path_factory.mktemp("self_rollout") / "data", train=2, frames=9)


def config(data, *sets):
    return load_config(str(ROOT / "configs" / "tiny.py"), [f"data.path={data}", *SETS, *sets])


def _perturbed(run):
    state, _, _ = run.init_state()
    rng = np.random.default_rng(0)  # off the zero init, so the correction is not the warp itself
    return jax.tree_util.tree_map(lambda p: p + 0.05 * rng.standard_normal(p.shape).astype(p.dtype), state.params)


def test_fill_holes_keeps_known_pixels_and_fills_from_neighbours():
    from jaxdrive.train.self_rollout import fill_holes

    img = jnp.arange(5 * 6 * 3, dtype=jnp.float32).reshape(5, 6, 3)
    holes = jnp.zeros((5, 6), bool).at[2, 3].set(True).at[:, 0].set(True)
    out = np.asarray(fill_holes(img, holes))
    np.testing.assert_array_equal(out[~np.asarray(holes)], np.asarray(img)[~np.asarray(holes)])
    # the isolated hole: the mean of its 8 known neighbours
    nb = [(1, 2), (1, 3), (1, 4), (2, 2), (2, 4), (3, 2), (3, 3), (3, 4)]
    np.testing.assert_allclose(out[2, 3], np.mean([np.asarray(img)[i, j] for i, j in nb], axis=0), rtol=1e-6)
    assert np.isfinite(out).all()
    np.testing.assert_array_equal(np.asarray(fill_holes(img, jnp.ones((5, 6), bool))), 0.0)  # nothing to fill from


def test_the_device_warp_is_the_host_warp_where_it_has_a_source_pixel():
    from jaxdrive.data.synthetic import generate_clip
    from jaxdrive.train.self_rollout import device_warp
    from jaxdrive.warp import camera_motion, depth_free_warp, warp_views

    c = generate_clip(3, views=6, frames=4, height=32, width=48)
    clip = {k: c[k][:2] for k in ("video", "intrinsics", "cam_to_ego")} | {"ego_to_world": c["ego_to_world"]}
    video = clip["video"].astype(np.float32) / 127.5 - 1  # [V, F, H, W, 3]
    e2w = clip["ego_to_world"].astype(np.float64)
    rel = (np.linalg.inv(e2w[1]) @ e2w).astype(np.float32)
    got = np.asarray(
        device_warp(video[None, :, 1], rel[None], clip["intrinsics"][None], clip["cam_to_ego"][None], 12.0)
    )
    host = warp_views(video[:, 1], clip["intrinsics"], clip["cam_to_ego"], rel, 12.0, inpaint=False)
    motion = camera_motion(rel, clip["cam_to_ego"])
    holes = np.stack(
        [np.asarray(depth_free_warp(video[v, 1], clip["intrinsics"][v], motion[v], 12.0)[1]) for v in range(2)]
    )
    assert got.shape == (1,) + host.shape and holes.any() and not holes.all()
    np.testing.assert_allclose(got[0][~holes], host[~holes], atol=1e-5)
    np.testing.assert_allclose(got[0, :, 1], video[:, 1], atol=1e-5)  # the source frame, unmoved


@pytest.mark.slow(seconds=9)
def test_the_second_window_is_given_the_models_own_frames_and_warps_from_them(data):
    from jaxdrive.generate.windows import sample_window
    from jaxdrive.train import self_rollout

    run = Run(config(data, "flow.self_rollout_rate=1.0"))
    batch = next(iter(run.dataset()))
    assert batch["video"].shape[2] == 2 * 5 - 2  # the two windows of a rollout
    inputs = jax.tree_util.tree_map(lambda a: a[0], run.global_batch([batch]))
    assert set(inputs["warp"]) == {"poses", "intrinsics", "cam_to_ego"} and "warp_video" in inputs
    params = _perturbed(run)
    t, codec = run.training, run.training.codec
    assert (t.warp_frame, t.warp_depth) == (1, 15.0)  # data.warp_frame / data.warp_depth reach the step
    key = jax.random.key(3)

    def window(training, params, inputs):
        x = codec.encode(None, inputs["video"])
        cond = inputs["cond"].replace(warp=codec.encode(None, inputs["warp_video"]))
        return self_rollout.training_window(training, params, None, x, cond, inputs, key)

    with jax.set_mesh(run.mesh):
        xw, cw, _ = jax.jit(window, static_argnums=0)(t, params, inputs)
        x = np.asarray(codec.encode(None, inputs["video"]))
        cond = inputs["cond"].replace(warp=codec.encode(None, inputs["warp_video"]))
        given = jnp.broadcast_to(jnp.arange(5) < 2, (2, 5))
        ctrl = cond.per_frame(lambda n, v: v[:, :5]).replace(warp=cond.warp[:, :, :5], drop=None)
        model = self_rollout._sampler_model(t, 5, 32, 56)
        made = np.asarray(jax.jit(sample_window, static_argnums=0)(model, params, x[:, :, :5], given, ctrl, key))
        plain = dataclasses.replace(t, flow=dataclasses.replace(t.flow, self_rollout_rate=0.0))
        first, cfirst, _ = jax.jit(window, static_argnums=0)(plain, params, inputs)
    xw, made = np.asarray(xw), made
    np.testing.assert_allclose(xw[:, :, :2], made[:, :, 3:5], atol=1e-5)  # the model's last two frames given
    assert np.abs(xw[:, :, :2] - x[:, :, 3:5]).mean() > 1e-2  # ... not the recorded ones
    np.testing.assert_array_equal(xw[:, :, 2:], x[:, :, 5:])  # the recorded frames after them: the targets
    np.testing.assert_array_equal(np.asarray(cw.waypoints), np.asarray(cond.waypoints)[:, 3:8])
    # the warp from the window's own frame 1, a generated one: that frame warped to itself is itself
    np.testing.assert_allclose(np.asarray(cw.warp)[:, :, 1], xw[:, :, 1], atol=1e-4)
    assert np.abs(np.asarray(cw.warp)[:, :, 3] - np.asarray(cond.warp)[:, :, 6]).mean() > 1e-3
    # a step that does not roll out trains the first window, the recorded given frames
    np.testing.assert_array_equal(np.asarray(first), x[:, :, :5])
    np.testing.assert_array_equal(np.asarray(cfirst.warp), np.asarray(cond.warp)[:, :, :5])


@pytest.mark.slow(seconds=8)
def test_the_step_with_self_rollout_trains(data):
    from jaxdrive.train import flow_step

    run = Run(config(data, "flow.self_rollout_rate=1.0"))
    params = _perturbed(run)
    inputs = jax.tree_util.tree_map(lambda a: a[0], run.global_batch([next(iter(run.dataset()))]))
    with jax.set_mesh(run.mesh):
        grad = jax.jit(
            jax.value_and_grad(lambda p, i: flow_step.flow_loss_fn(run.training, p, None, i, jax.random.key(0))[0])
        )
        loss, g = grad(params, inputs)
    assert np.isfinite(float(loss))
    norms = [float(jnp.abs(v).max()) for v in jax.tree_util.tree_leaves(g)]
    assert all(np.isfinite(norms)) and max(norms) > 0


@pytest.mark.parametrize(
    "sets, match",
    [
        (["flow.self_rollout_rate=1.5"], "flow.self_rollout_rate"),
        (["flow.self_rollout_rate=0.5", "flow.self_rollout_steps=0"], "flow.self_rollout_steps"),
        (["flow.self_rollout_rate=0.5", "flow.cond_frames_random=true"], "flow.cond_frames_random: expected false"),
        (["flow.self_rollout_rate=0.5", "data.stride=2"], "data.stride: expected 1"),
        (
            ["flow.self_rollout_rate=0.5", "flow.cond_frames=0", "model.controls.warp=false"],
            "flow.cond_frames: expected at least 1",
        ),
    ],
)
def test_what_rules_self_rollout_out_is_refused(data, sets, match):
    with pytest.raises(ValueError, match=match):
        Run(config(data, *sets))


def test_a_temporal_codec_is_refused():
    from jaxdrive.train.self_rollout import clip_frames

    assert clip_frames(9, 2, 1) == 16
    with pytest.raises(ValueError, match="flow.self_rollout_rate: expected a frame-wise codec"):
        clip_frames(9, 2, 4)
