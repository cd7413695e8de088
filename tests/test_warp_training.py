"""LongDWM's warp-guided control in training: the pipeline warps each clip's first frame along the
clip's own poses (host, inpainted), the step encodes the warped clip into the DiT's ``warp``
input, and what rules it out is refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from jaxdrive.config import load_config
from jaxdrive.train.run import Run

from train_fixtures import write_synthetic

ROOT = Path(__file__).resolve().parents[1]
WARP = [
    "model.controls.warp=true",
    "data.views=2",
    "data.batch_size=2",
    "data.frames=5",
    "mesh.data=2",
    "mesh.seq=4",
    "optim.warmup_steps=1",
    "train.log_every=1",
    "train.checkpoint_every=2",
]


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_synthetic(tmp_path_factory.mktemp("warp") / "data", train=2, frames=9)


def config(data, *sets):
    return load_config(str(ROOT / "configs" / "tiny.py"), [f"data.path={data}", *WARP, *sets])


def test_the_pipeline_warps_each_clip_from_its_first_frame_along_its_own_poses(data):
    from jaxdrive.data.transforms import clip_warp
    from jaxdrive.warp import warp_views

    run = Run(config(data, "data.warp_depth=15"))
    batch = next(iter(run.dataset()))
    video, warp = batch["video"], batch["warp_video"]
    assert warp.shape == video.shape and warp.dtype == np.float32
    np.testing.assert_allclose(warp[:, :, 0], video[:, :, 0], atol=1e-5)  # frame 0: the first frame itself
    # the clip's own poses relative to its first frame, at data.warp_depth
    i = 1
    e2w = batch["ego_to_world"][i].astype(np.float64)
    poses = (np.linalg.inv(e2w[0]) @ e2w).astype(np.float32)
    want = warp_views(video[i, :, 0], batch["intrinsics"][i], batch["cam_to_ego"][i], poses, 15.0)
    np.testing.assert_allclose(warp[i], want, atol=1e-5)
    sample = {k: batch[k][i] for k in ("video", "ego_to_world", "intrinsics", "cam_to_ego")}
    np.testing.assert_allclose(clip_warp(sample, 15.0), want, atol=1e-5)
    assert np.abs(warp[:, :, -1] - video[:, :, 0]).max() > 0.05  # the ego moved: later frames are warped
    inputs = run.global_batch([batch])
    assert inputs["warp_video"].shape == (1,) + video.shape
    # classifier-free guidance drops the warp with the trajectory, the control it carries
    from jaxdrive.data.batches import conditions

    cond = conditions(dict(batch, drop=dict(batch["drop"], trajectory=np.asarray([True, False]))), run.training.model)
    np.testing.assert_array_equal(cond.drop["warp"], [True, False])


@pytest.mark.slow(seconds=16)
def test_the_step_encodes_the_warped_clip_into_the_dit_and_learns_its_embedding(data):
    """The loss of a batch from the run's own pipeline depends on its warped clip, and the
    gradient reaches the warp embedding (the step: loss, gradients, optimizer)."""
    import jax

    from jaxdrive.train import flow_step

    run = Run(config(data))
    state, _, _ = run.init_state()
    # every layer off its zero init, at random: a constant offset made the zero-initialised warp
    # projection add the same number to every channel, which the next LayerNorm removes
    rng = np.random.default_rng(0)
    params = jax.tree_util.tree_map(lambda p: p + 0.02 * rng.standard_normal(p.shape).astype(p.dtype), state.params)
    inputs = jax.tree_util.tree_map(lambda a: a[0], run.global_batch([next(iter(run.dataset()))]))
    key = jax.random.key(0)
    with jax.set_mesh(run.mesh):
        grad = jax.jit(jax.value_and_grad(lambda p, i: flow_step.flow_loss_fn(run.training, p, None, i, key)[0]))
        (same, g), (other, _) = grad(params, inputs), grad(params, dict(inputs, warp_video=-inputs["warp_video"]))
    assert np.isfinite(float(same)) and abs(float(same) - float(other)) > 1e-6
    warp_grads = {
        jax.tree_util.keystr(k): float(np.abs(np.asarray(v)).max())
        for k, v in jax.tree_util.tree_leaves_with_path(g)
        if "warp" in jax.tree_util.keystr(k)
    }
    assert warp_grads and max(warp_grads.values()) > 0, warp_grads


@pytest.mark.parametrize(
    "sets, match",
    [
        (["data.warp_depth=0"], "data.warp_depth: expected a positive depth"),
        (["stream.enabled=true", "stream.taps=()"], "stream.enabled: expected False with model.controls.warp"),
    ],
)
def test_what_rules_the_warp_out_is_refused(data, sets, match):
    with pytest.raises(ValueError, match=match):
        Run(config(data, *sets))


# ------------------------------------------------------------------ sampling
def _warp_model():
    import flax.linen as nn
    import jax
    import jax.numpy as jnp

    from jaxdrive.generate.windows import WindowModel
    from jaxdrive.models.dit import DiT
    from jaxdrive.models.dit.presets import preset

    from strategy_fixtures import C, H, W

    cfg = preset(
        "tiny",
        in_channels=C,
        vae_spatial=4,
        vae_temporal=1,
        patch=(1, 2, 2),
        prediction="data",
        controls=dict(waypoints=True, fps=True, warp=True, cond_frames="replace"),
    )
    dit = DiT(cfg)
    params = jax.tree_util.tree_map(
        jnp.asarray, nn.unbox(dit.init_params(0, batch=1, views=2, frames=4, height=H, width=W))
    )
    keys = iter(jax.random.split(jax.random.key(1), len(jax.tree_util.tree_leaves(params))))
    # every parameter off its initialisation (the warp embedding and the output layer start at zero)
    params = jax.tree_util.tree_map(lambda p: p + 0.05 * jax.random.normal(next(keys), p.shape), params)
    return WindowModel(dit, params, window=4, cond_frames=2, steps=2)


class _Spy:
    """A warp guide that records what each window asks for and answers a constant per call."""

    def __init__(self, scale=1.0, frame=0):
        self.calls, self.scale, self.frame = [], scale, frame

    def window(self, first, frames):
        self.calls.append((np.asarray(first).copy(), np.asarray(frames)))
        return np.full(first.shape[:2] + (len(frames),) + first.shape[3:], self.scale * len(self.calls), np.float32)


@pytest.mark.slow(seconds=3)
def test_every_window_warps_its_own_first_frame_and_the_warp_steers_it():
    import jax

    from jaxdrive.generate import strategies as S

    from strategy_fixtures import horizon_inputs

    m = _warp_model()
    first, controls = horizon_inputs(10, given=2)
    spy = _Spy()
    out = np.concatenate(
        list(S.run_strategy("rollout", S.Models(m), controls, first, 10, key=jax.random.key(0), warp=spy)), axis=2
    )
    assert [list(f) for _, f in spy.calls] == [list(range(s, s + 4)) for s in (0, 2, 4, 6)]
    for got_first, frames in spy.calls:  # the horizon's frame at the window's start, as it was then
        np.testing.assert_array_equal(got_first, out[:, :, frames[:1]])
    other = np.concatenate(
        list(S.run_strategy("rollout", S.Models(m), controls, first, 10, key=jax.random.key(0), warp=_Spy(scale=-1.0))),
        axis=2,
    )
    assert np.abs(other[:, :, 2:] - out[:, :, 2:]).max() > 1e-4
    with pytest.raises(ValueError, match="warp: a model trained with warped frames"):
        list(S.run_strategy("rollout", S.Models(m), controls, first, 10, key=jax.random.key(0)))
    # data.warp_frame=1: each window warps from its second frame, its newest given one
    spy = _Spy(frame=1)
    out = np.concatenate(
        list(S.run_strategy("rollout", S.Models(m), controls, first, 10, key=jax.random.key(0), warp=spy)), axis=2
    )
    for got_first, frames in spy.calls:
        np.testing.assert_array_equal(got_first, out[:, :, frames[1:2]])


@pytest.mark.parametrize("start", [1.0, 0.4])
def test_warp_start_samples_from_the_warp_noised_to_its_level(start):
    """``sample.warp_start`` (SDEdit from the warp): one Euler step from level ``s`` lands on the
    model's data estimate there, so the window equals the DiT's output for the input
    ``(1 - s) warp + s noise`` at level ``s``; the shift (3) does not move the start."""
    import flax.linen as nn
    import jax
    import jax.numpy as jnp

    from jaxdrive.generate.windows import WindowModel, jitted_sample_window
    from jaxdrive.models.dit import DiT
    from jaxdrive.models.dit.conditions import Conditions
    from jaxdrive.models.dit.presets import preset

    controls = dict(warp=True, cond_frames="replace", reference_frame="warp")
    cfg = preset("tiny", in_channels=8, vae_spatial=4, vae_temporal=1, prediction="data", controls=controls)
    dit = DiT(cfg)
    params = nn.unbox(dit.init_params(0, batch=1, views=2, frames=4, height=8, width=8))
    keys = iter(jax.random.split(jax.random.key(3), len(jax.tree_util.tree_leaves(params)) + 2))
    params = jax.tree_util.tree_map(lambda p: p + 0.05 * jax.random.normal(next(keys), p.shape), params)
    given, warp = (jax.random.normal(next(keys), (1, 2, 4, 8, 8, 8)) for _ in range(2))
    mask = jnp.asarray([[True, False, False, False]])
    model = WindowModel(dit, params, window=4, steps=1, shift=3.0, warp_start=start)
    key = jax.random.key(7)
    out = np.asarray(jitted_sample_window(model, params, given, mask, Conditions(warp=warp), key))
    noise = jax.random.normal(key, given.shape)  # the window's noise: from the key itself
    x_s = jnp.where(mask[:, None, :, None, None, None], given, (1 - start) * warp + start * noise)
    cond = Conditions(cond_latents=given, cond_mask=mask, warp=warp)
    want = dit.apply({"params": params}, x_s, jnp.where(mask, 0.0, start), cond)
    np.testing.assert_allclose(out[:, :, 1:], np.asarray(want)[:, :, 1:], rtol=1e-4, atol=1e-4)
    np.testing.assert_array_equal(out[:, :, 0], np.asarray(given)[:, :, 0])


def test_warp_start_is_refused_out_of_range_and_for_a_model_without_the_warp(data):
    from jaxdrive.generate.windows import WindowModel
    from jaxdrive.models.dit import DiT
    from jaxdrive.models.dit.presets import preset

    for bad in ("0", "1.5", "-0.2"):
        with pytest.raises(ValueError, match=rf"sample.warp_start: expected a noise level in \(0, 1\], got {bad}"):
            Run(config(data, f"sample.warp_start={bad}"))
    without = [f"data.path={data}", *(s for s in WARP if s != "model.controls.warp=true"), "sample.warp_start=0.5"]
    with pytest.raises(ValueError, match=r"sample.warp_start: expected 1 \(pure noise\) for a model without the warp"):
        Run(load_config(str(ROOT / "configs" / "tiny.py"), without))
    plain = DiT(preset("tiny", in_channels=8, prediction="data", controls=dict(cond_frames="replace")))
    with pytest.raises(ValueError, match=r"sample.warp_start: expected 1 \(pure noise\) for a model without the warp"):
        WindowModel(plain, None, warp_start=0.5)
    with pytest.raises(ValueError, match="sample.warp_start: expected a noise level in"):
        WindowModel(plain, None, warp_start=True)


def test_warp_path_noises_the_chosen_frames_from_the_warp_and_keeps_the_loss_that_of_x():
    import jax
    import jax.numpy as jnp

    from jaxdrive import flow

    # worked number: x = 0, warp = 1, noise = 0 at level 0.25: the input 0.75, the implied noise
    # 0 + 0.75 / 0.25 * (1 - 0) = 3, and (1 - 0.25) * 0 + 0.25 * 3 = 0.75 again
    one = jnp.ones((1, 1, 2, 1, 1, 1))
    x_t, implied = flow.warp_path(0 * one, 0 * one, one, jnp.asarray([[0.25, 0.25]]), jnp.asarray([[False, True]]))
    np.testing.assert_allclose(np.asarray(x_t).ravel(), [0.0, 0.75])
    np.testing.assert_allclose(np.asarray(implied).ravel(), [0.0, 3.0])
    k = jax.random.split(jax.random.key(0), 4)
    x, noise, warp = (jax.random.normal(kk, (2, 3, 4, 2, 2, 5)) for kk in k[:3])
    levels = jax.random.uniform(k[3], (2, 4), minval=0.05, maxval=1.0)
    on = jnp.asarray([[False, True, True, False], [False, False, False, False]])
    x_t, implied = flow.warp_path(x, noise, warp, levels, on)
    m = on[:, None, :, None, None, None]
    np.testing.assert_allclose(x_t, jnp.where(m, flow.add_noise(warp, noise, levels), flow.add_noise(x, noise, levels)))
    np.testing.assert_allclose(flow.add_noise(x, implied, levels), x_t, rtol=1e-5, atol=1e-5)  # on x's path
    np.testing.assert_array_equal(np.where(m, 0.0, implied), np.where(m, 0.0, noise))  # the others untouched
    # the velocity loss against (x, implied) is the data estimate's error over the level
    out = jax.random.normal(jax.random.key(9), x.shape)
    v = flow.velocity_from_output(out, x_t, levels, "data")
    s = flow.expand_per_frame(levels, x)
    np.testing.assert_allclose(v - flow.velocity_target(x, implied), (x - out) / s, rtol=1e-4, atol=1e-4)
    with pytest.raises(ValueError, match=r"warp: expected the shape of x"):
        flow.warp_path(x, noise, warp[:, :, :2], levels, on)
    with pytest.raises(ValueError, match="on: expected shape"):
        flow.warp_path(x, noise, warp, levels, on[:, :2])


@pytest.mark.slow(seconds=12)
def test_the_step_feeds_the_warp_path_to_the_dit_and_scores_it_against_the_future(data, monkeypatch):
    """``flow.warp_path_rate=1``: the DiT's input at the generated frames is the encoded warp
    noised with the same noise as the plain step's input from the future, the given frames
    untouched, and the loss is the velocity loss of the future from that input."""
    import jax

    from jaxdrive import flow
    from jaxdrive.train import flow_step

    seen = []
    inputs = None
    for rate in ("0", "1"):
        run = Run(config(data, f"flow.warp_path_rate={rate}", "data.warp_depth=15"))
        forward = type(run.training.dit).forward

        def spy(self, params, x, sigma, cond, **kw):
            out = forward(self, params, x, sigma, cond, **kw)
            seen.append(dict(x=np.asarray(x), sigma=np.asarray(sigma), cond=cond, out=out))
            return out

        monkeypatch.setattr(type(run.training.dit), "forward", spy)
        state, _, _ = run.init_state()
        if inputs is None:
            inputs = jax.tree_util.tree_map(lambda a: a[0], run.global_batch([next(iter(run.dataset()))]))
        with jax.set_mesh(run.mesh):
            _, metrics = flow_step.flow_loss_fn(run.training, state.params, None, inputs, jax.random.key(3))
        seen[-1]["loss"] = float(metrics["flow_loss"])
        monkeypatch.undo()
    plain, warped = seen
    codec = run.training.codec
    x, warp = (np.asarray(codec.encode(None, np.asarray(inputs[k]))) for k in ("video", "warp_video"))
    mask = np.asarray(warped["cond"].cond_mask)
    assert mask[:, :2].all() and not mask[:, 2:].any()
    s = np.asarray(flow.expand_per_frame(warped["sigma"], x))[:, :, 2:]
    np.testing.assert_array_equal(warped["sigma"], plain["sigma"])
    noise_plain = (plain["x"][:, :, 2:] - (1 - s) * x[:, :, 2:]) / s
    noise_warped = (warped["x"][:, :, 2:] - (1 - s) * warp[:, :, 2:]) / s
    np.testing.assert_allclose(noise_warped, noise_plain, rtol=1e-3, atol=1e-3)  # one noise, two paths
    assert np.abs(warped["x"][:, :, 2:] - plain["x"][:, :, 2:]).max() > 0.05  # the warp differs from the future
    # the loss: the future's velocity from the warp's input, (x_t - x) / s, as the noise that gives it
    x_t = warped["x"]
    v = flow.velocity_from_output(warped["out"], x_t, warped["sigma"], "data")
    s_all = np.maximum(np.asarray(flow.expand_per_frame(warped["sigma"], x)), 1e-6)
    want = flow.flow_loss(v, x, (x_t - (1 - s_all) * x) / s_all, cond_mask=mask)
    np.testing.assert_allclose(warped["loss"], float(want), rtol=1e-4)


@pytest.mark.parametrize(
    "sets, match",
    [
        (["flow.warp_path_rate=1.5"], r"flow.warp_path_rate: expected values in \[0.0, 1.0\], got 1.5"),
        (
            ["flow.warp_path_rate=0.5", "flow.jdc_anchor_rate=0.5"],
            "flow.jdc_anchor_rate: expected 0 with flow.warp_path_rate",
        ),
        (["flow.warp_path_rate=0.5", "model.controls.warp=false"], r"model.controls.warp: expected true \(the warp"),
    ],
)
def test_bad_warp_path_rates_are_refused(data, sets, match):
    with pytest.raises(ValueError, match=match):
        Run(config(data, *sets))


def test_the_pipeline_warps_from_the_last_given_frame_when_told(data):
    run = Run(config(data, "data.warp_depth=15", "data.warp_frame=1", "flow.cond_frames=2"))
    batch = next(iter(run.dataset()))
    video, warp = batch["video"], batch["warp_video"]
    np.testing.assert_allclose(warp[:, :, 1], video[:, :, 1], atol=1e-5)  # the source frame itself
    from jaxdrive.warp import warp_views

    e2w = batch["ego_to_world"][0].astype(np.float64)
    poses = (np.linalg.inv(e2w[1]) @ e2w).astype(np.float32)
    want = warp_views(video[0, :, 1], batch["intrinsics"][0], batch["cam_to_ego"][0], poses, 15.0)
    np.testing.assert_allclose(warp[0], want, atol=1e-5)
    with pytest.raises(ValueError, match=r"data.warp_frame: expected a given frame to warp from, 0 to 1 .* got 2"):
        Run(config(data, "data.warp_frame=2", "flow.cond_frames=2"))


def test_a_warp_correction_at_zero_is_the_warp_bit_for_bit():
    """``reference_frame="warp"``: the output is the warp plus a correction, which starts at zero,
    so an untrained model gives the warp baseline exactly; where the warp is dropped (guidance)
    the base is the newest given frame."""
    import flax.linen as nn
    import jax
    import jax.numpy as jnp

    from jaxdrive.models.dit import DiT
    from jaxdrive.models.dit.conditions import Conditions
    from jaxdrive.models.dit.presets import preset

    cfg = preset(
        "tiny",
        in_channels=8,
        vae_spatial=4,
        vae_temporal=1,
        patch=(1, 2, 2),
        prediction="data",
        controls=dict(warp=True, cond_frames="replace", reference_frame="warp"),
    )
    dit = DiT(cfg)
    params = nn.unbox(dit.init_params(0, batch=2, views=2, frames=4, height=8, width=8))
    k = iter(jax.random.split(jax.random.key(0), 3))
    x = jax.random.normal(next(k), (2, 2, 4, 8, 8, 8))
    warp = jax.random.normal(next(k), x.shape)
    given = jax.random.normal(next(k), x.shape)
    mask = jnp.asarray([[True, True, False, False]] * 2)
    sigma = jnp.asarray([[0.0, 0.0, 0.7, 0.7]] * 2)
    cond = Conditions(cond_latents=given, cond_mask=mask, warp=warp, drop={"warp": jnp.asarray([False, True])})
    out = np.asarray(dit.apply({"params": params}, x, sigma, cond))
    np.testing.assert_array_equal(out[0, :, 2:], np.asarray(warp)[0, :, 2:])  # the warp itself
    np.testing.assert_array_equal(out[1, :, 2:], np.broadcast_to(np.asarray(given)[1, :, 1:2], out[1, :, 2:].shape))
    with pytest.raises(ValueError, match="controls.reference_frame: 'warp' corrects the warped frames"):
        preset("tiny", in_channels=8, prediction="data", controls=dict(cond_frames="replace", reference_frame="warp"))


def test_the_skip_makes_an_untrained_warp_correction_edms_linear_estimate_around_the_warp():
    """``sigma_data`` (EDM's preconditioning around the warp): with a zero head the output is
    ``warp + c_skip (x_t - (1 - sigma) warp)``: the warp bit for bit from pure noise, the input
    itself at level 0 (a clean input passes through, not redrawn by the per-token head)."""
    import flax.linen as nn
    import jax
    import jax.numpy as jnp

    from jaxdrive import flow
    from jaxdrive.models.dit import DiT
    from jaxdrive.models.dit.conditions import Conditions
    from jaxdrive.models.dit.presets import preset

    def tiny(**kw):
        controls = dict(warp=True, cond_frames="replace", reference_frame="warp")
        return preset("tiny", in_channels=8, vae_spatial=4, vae_temporal=1, controls=controls, **kw)

    dit = DiT(tiny(prediction="data", sigma_data=0.2))
    params = nn.unbox(dit.init_params(0, batch=1, views=2, frames=4, height=8, width=8))
    k = iter(jax.random.split(jax.random.key(1), 3))
    x = jax.random.normal(next(k), (1, 2, 4, 8, 8, 8))
    warp = jax.random.normal(next(k), x.shape)
    given = jax.random.normal(next(k), x.shape)
    cond = Conditions(cond_latents=given, cond_mask=jnp.asarray([[True, False, False, False]]), warp=warp)
    out = np.asarray(dit.apply({"params": params}, x, jnp.asarray([[0.0, 1.0, 0.7, 0.0]]), cond))
    np.testing.assert_array_equal(out[:, :, 1], np.asarray(warp)[:, :, 1])  # level 1: the warp
    c_skip, _ = flow.skip_coefficients(0.7, 0.2)
    want = warp[:, :, 2] + c_skip * (x[:, :, 2] - 0.3 * warp[:, :, 2])
    np.testing.assert_allclose(out[:, :, 2], want, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(out[:, :, 3], x[:, :, 3], rtol=1e-5, atol=1e-5)  # level 0: the input
    np.testing.assert_allclose(out[:, :, 0], given[:, :, 0], rtol=1e-5, atol=1e-5)  # the given frame
    with pytest.raises(ValueError, match="sigma_data: expected 0 with prediction 'velocity'"):
        tiny(prediction="velocity", sigma_data=0.2)
    with pytest.raises(ValueError, match=r"sigma_data: expected a standard deviation >= 0 \(0: off\), got -0.1"):
        tiny(prediction="data", sigma_data=-0.1)


def test_the_guide_warps_the_decoded_first_frame_along_the_window_poses_and_encodes_it():
    from jaxdrive.data.synthetic import generate_clip
    from jaxdrive.generate.warps import WarpGuide
    from jaxdrive.models.latents import LatentCodec
    from jaxdrive.warp import warp_views

    clip = generate_clip(1, views=6, frames=6, height=32, width=48)
    video = clip["video"][None, :2].astype(np.float32) / 127.5 - 1  # [1, 2, 6, H, W, 3]
    codec = LatentCodec("space_to_depth", 4)
    guide = WarpGuide(
        codec, None, clip["ego_to_world"][None], clip["intrinsics"][None, :2], clip["cam_to_ego"][None, :2], 12.0
    )
    z = np.asarray(codec.encode(None, video))
    got = guide.window(z[:, :, 2:3], [2, 3, 4, 5])
    e2w = clip["ego_to_world"].astype(np.float64)
    rel = (np.linalg.inv(e2w[2]) @ e2w[2:6]).astype(np.float32)
    want = codec.encode(
        None, warp_views(video[0, :, 2], clip["intrinsics"][:2], clip["cam_to_ego"][:2], rel, 12.0)[None]
    )
    np.testing.assert_allclose(got, want, atol=1e-5)
    np.testing.assert_allclose(got[:, :, 0], z[:, :, 2], atol=1e-5)  # the first frame unmoved
    with pytest.raises(ValueError, match="poses: expected a pose for pixel frame 6"):
        guide.window(z[:, :, 2:3], [4, 5, 6])


@pytest.mark.slow(seconds=46)
def test_a_warp_run_trains_and_samples_through_the_cli(data, tmp_path, capsys, monkeypatch):
    """``jaxdrive train`` with the warp control, then ``jaxdrive sample --strategy rollout``: its
    windows warp along the validation clip's recorded poses at the run's data.warp_depth."""
    import json

    from jaxdrive.cli import main as cli

    args = [
        "train",
        "--config",
        str(ROOT / "configs" / "tiny.py"),
        "--workdir",
        str(tmp_path / "run"),
        "--steps",
        "1",
        "--no-progress",
    ]
    # one layer, no final convolutions: the warp's path through the CLI is tested, not the model
    for s in [f"data.path={data}", *WARP, "data.warp_depth=18", "model.depth=1", "model.final_conv=0"]:
        args += ["--set", s]
    assert cli(args) == 0
    out = tmp_path / "sample"
    assert (
        cli(
            [
                "sample",
                "--workdir",
                str(tmp_path / "run"),
                "--strategy",
                "rollout",
                "--frames",
                "9",
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
    assert report["warp"] == {"depth": 18.0, "frame": 0} and report["frames"] == 9
    recorded = np.load(out / "latents.npy")
    assert np.isfinite(recorded).all()
    # --route: the same clip driven through a left turn; the windows warp along the route's poses
    from jaxdrive.generate.route import load_route
    from jaxdrive.generate.warps import WarpGuide

    seen, window = [], WarpGuide.window
    monkeypatch.setattr(
        WarpGuide,
        "window",
        lambda self, first, frames: seen.append((list(frames), self.poses)) or window(self, first, frames),
    )
    turned = tmp_path / "turn"
    assert (
        cli(
            [
                "sample",
                "--workdir",
                str(tmp_path / "run"),
                "--strategy",
                "rollout",
                "--frames",
                "9",
                "--steps",
                "2",
                "--route",
                "left turn",
                "--out",
                str(turned),
                "--no-progress",
            ]
        )
        == 0
    )
    report = json.loads((turned / "report.json").read_text())
    assert report["route"] == "manoeuvre 'left turn'"
    # no intersection within the 5 m the 9 frames drive: the turn starts where the clip is (the poses below)
    assert report["route_drive"]["start"] == {"frame": 0, "time": 0.0, "x": 0.0, "y": 0.0}
    assert report["route_drive"]["start_at"] == "clip" and report["route_drive"]["map_checked"] is True
    want = load_route("left turn", duration=8 / 12).poses(9, 12.0).astype(np.float64)
    for frames, poses in seen:  # each window's poses relative to its first: the route's
        p = poses[:, frames].astype(np.float64)
        np.testing.assert_allclose(
            np.linalg.inv(p[:, :1]) @ p,
            np.broadcast_to(np.linalg.inv(want[frames[0]]) @ want[frames], p.shape),
            atol=1e-3,
        )
    assert len(seen) == 3 and np.isfinite(np.load(turned / "latents.npy")).all()
    bad = tmp_path / "bad.csv"
    bad.write_text("x,y\n0,0\n1,nan\n")
    capsys.readouterr()
    assert (
        cli(
            [
                "sample",
                "--workdir",
                str(tmp_path / "run"),
                "--strategy",
                "rollout",
                "--frames",
                "9",
                "--route",
                str(bad),
                "--out",
                str(tmp_path / "no"),
            ]
        )
        == 2
    )
    assert f"route {bad} row 3: expected finite values" in capsys.readouterr().err
