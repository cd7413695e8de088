"""STAGE's streaming: the HTFT ring buffer against a plain re-run of the model, streaming without
taps against a frame-by-frame rollout, flat memory, the training step's feature pass and rollout
against the sampler's, and the bad inputs."""

from __future__ import annotations

import dataclasses
import functools

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdrive import flow
from jaxdrive.config import FlowConfig, StreamConfig
from jaxdrive.generate import strategies as S
from jaxdrive.generate import streaming as ST
from jaxdrive.generate.long_video import sample_long
from jaxdrive.generate.windows import Tracker, WindowModel, sample_window
from jaxdrive.models.dit import DiT
from jaxdrive.models.dit.presets import preset
from jaxdrive.models.latents import LatentCodec

from strategy_fixtures import C, H, W, horizon_inputs

TAPS, BUFFER = (-1, -2, -4), 4


@functools.cache
def model(htft: bool = True, steps: int = 3) -> WindowModel:
    cfg = preset(
        "tiny",
        in_channels=C,
        vae_spatial=4,
        vae_temporal=1,
        patch=(1, 2, 2),
        prediction="data",
        htft_layers=(0,) if htft else (),
        controls=dict(waypoints=True, fps=True, cond_frames="replace", reference_frame="residual"),
    )
    dit = DiT(cfg)
    params = jax.tree_util.tree_map(
        jnp.asarray, nn.unbox(dit.init_params(0, batch=1, views=2, frames=3, height=H, width=W))
    )
    keys = iter(jax.random.split(jax.random.key(1), len(jax.tree_util.tree_leaves(params))))
    # every parameter moved off its initialisation: HTFT's zero output layer too, so the past matters
    params = jax.tree_util.tree_map(lambda p: p + 0.05 * jax.random.normal(next(keys), p.shape), params)
    return WindowModel(
        dit,
        params,
        window=3,
        cond_frames=1,
        steps=steps,
        streaming=True,
        stream_buffer=BUFFER,
        stream_taps=TAPS if htft else (),
    )


def reference_stream(m: WindowModel, first, controls, length, key, taps):
    """Streaming written out plainly: Python loops over frames and steps, every feature kept in a
    list (no ring), the model re-run on each state."""
    sig = np.asarray(flow.sampling_sigmas(m.steps, shift=m.shift))
    forward = jax.jit(functools.partial(m.dit.forward, return_features=True))
    frames, feats = [first[:, :, :1]], []  # feats[p - 1][i]: frame p at step i
    mask3 = jnp.asarray([[True, True, False]])
    for j in range(1, length):
        ctrl = ST.window_controls(controls, j, 1)
        x_cond = jnp.concatenate([frames[0], frames[-1], jnp.zeros_like(frames[0])], axis=2)
        x = jnp.where(
            mask3[:, None, :, None, None, None], x_cond, jax.random.normal(jax.random.fold_in(key, j), x_cond.shape)
        )
        cond = ctrl.replace(cond_latents=x_cond, cond_mask=mask3)
        mine = []
        for i in range(m.steps):
            levels = jnp.where(mask3, 0.0, float(sig[i]))
            c = cond
            if taps:
                past = [j + o for o in taps]
                empty = jnp.zeros((1, (H // 2) * (W // 2), 2, m.dit.config.width))
                c = cond.replace(
                    features={0: jnp.stack([feats[p - 1][i] if p >= 1 else empty for p in past], axis=1)},
                    features_mask=jnp.asarray([[p >= 1 for p in past]]),
                )
            out, f = forward(m.params, x, levels, c)
            mine.append(f[0][:, ST.NEW])
            v = flow.velocity_from_output(out, x, levels, m.dit.config.prediction, m.dit.config.prediction_min_sigma)
            x = jnp.where(mask3[:, None, :, None, None, None], x_cond, x + (sig[i + 1] - sig[i]) * v)
        feats.append(mine)
        frames.append(x[:, :, ST.NEW :])
    return jnp.concatenate(frames, axis=2), feats


@pytest.mark.slow(seconds=9)
def test_the_buffer_holds_the_last_frames_features_at_every_step():
    m = model()
    length = 7
    first, controls = horizon_inputs(length, given=1)
    key = jax.random.key(3)
    want, feats = reference_stream(m, first, controls, length, key, TAPS)
    buf = ST.new_buffer(m, 1, 2, (H, W))
    prev = jnp.asarray(first[:, :, :1])
    got = [prev]
    for j in range(1, length):
        prev, buf = ST._STREAM(
            m, TAPS, m.params, got[0], prev, ST.window_controls(controls, j, 1), jax.random.fold_in(key, j), buf
        )
        got.append(prev)
        # after frame j the ring holds frames j .. j - 3 (those that exist) at every step
        past, mask = ST.buffer_select(buf, tuple(range(-1, -BUFFER - 1, -1)))
        for k in range(BUFFER):
            p = j - k
            assert bool(mask[0, k]) == (p >= 1)
            if p >= 1:
                np.testing.assert_allclose(past[0][:, :, k], jnp.stack(feats[p - 1]), atol=2e-5, err_msg=(j, k))
    np.testing.assert_allclose(jnp.concatenate(got, axis=2), want, atol=2e-5)
    # the past matters: the same frames without HTFT differ
    plain, _ = reference_stream(m, first, controls, length, key, ())
    assert float(jnp.abs(plain[:, :, 2:] - want[:, :, 2:]).max()) > 1e-3


@pytest.mark.slow(seconds=6)
def test_streaming_without_taps_is_frame_by_frame_rollout_of_the_window_sampler():
    m = model()
    length = 5
    first, controls = horizon_inputs(length, given=1)
    key = jax.random.key(0)
    tracker = Tracker()
    parts = list(S.run_strategy("streaming", S.Models(m), controls, first, length, key=key, tracker=tracker, taps=()))
    assert [p.shape[2] for p in parts] == [1, 1, 1, 1, 1]  # each frame as it is done
    out = np.concatenate(parts, axis=2)
    np.testing.assert_array_equal(out[:, :, :1], first)
    prev = first[:, :, :1]
    for j in range(1, length):
        x_cond = np.concatenate([first[:, :, :1], prev, np.zeros_like(prev)], axis=2)
        z = sample_window(
            m,
            m.params,
            jnp.asarray(x_cond),
            jnp.asarray([[True, True, False]]),
            ST.window_controls(controls, j, 1),
            jax.random.fold_in(key, j),
        )
        np.testing.assert_allclose(out[:, :, j], z[:, :, 2], atol=1e-5, err_msg=str(j))
        prev = out[:, :, j : j + 1]
    assert tracker.calls == length - 1 == S.sequential_calls("streaming", S.Models(m), length, 1, taps=())
    assert tracker.notes["stream"]["buffer_bytes"] == 0


@pytest.mark.slow(seconds=6)
def test_streamed_frames_are_kept_in_the_latents_range():
    """Each streamed frame is the next one's condition frame: a value no encoded frame can have is
    clipped to the codec's range before it is fed back (and the next frames are sampled from it)."""
    m = model(htft=False)
    length, r = 4, 0.5
    first, controls = horizon_inputs(length, given=1)
    key = jax.random.key(2)

    def stream(wm):
        return np.concatenate(
            list(S.run_strategy("streaming", S.Models(wm), controls, first, length, key=key, taps=())), axis=2
        )

    free = stream(m)
    assert m.value_range is None and np.abs(free[:, :, 1:]).max() > 2 * r  # unbounded without a range
    got = stream(dataclasses.replace(m, value_range=(-r, r)))
    assert np.abs(got[:, :, 1:]).max() <= r
    np.testing.assert_allclose(got[:, :, 1], np.clip(free[:, :, 1], -r, r), atol=1e-6)
    # frame 2 is sampled from the clipped frame 1, not merely clipped itself
    assert np.abs(got[:, :, 2] - np.clip(free[:, :, 2], -r, r)).max() > 1e-3
    # the codecs' ranges: space-to-depth latents of [-1, 1] pixels, scaled; a VAE's are unbounded
    codec = LatentCodec("space_to_depth", 4, 0.5)
    video = np.random.default_rng(0).choice([-1.0, 1.0], size=(1, 1, 1, 16, 32, 3)).astype(np.float32)
    z = np.asarray(codec.encode(None, video))
    assert codec.value_range == (-0.5, 0.5) == (z.min(), z.max())
    assert LatentCodec("vae", vae=object()).value_range is None


def test_given_frames_are_observed_into_the_buffer_and_kept():
    m = model()
    first, controls = horizon_inputs(6, given=3)
    tracker = Tracker()
    out = np.concatenate(
        list(S.run_strategy("streaming", S.Models(m), controls, first, 6, key=jax.random.key(0), tracker=tracker)),
        axis=2,
    )
    np.testing.assert_array_equal(out[:, :, :3], first)
    assert tracker.calls == 2 + 3 == S.sequential_calls("streaming", S.Models(m), 6, 3)
    assert tracker.programs == 2  # one observing, one sampling program


@pytest.mark.optimized_xla
@pytest.mark.slow(seconds=59)
def test_streaming_memory_is_flat_and_it_compiles_once(tmp_path):
    """33 and 721 frames (a minute at 12 fps): the same device memory, one compiled program."""
    m = model(steps=1)
    codec = LatentCodec("space_to_depth", 4)
    reports = {}
    for length in (33, 721):
        first, controls = horizon_inputs(length, views=2, given=1)
        reports[length] = sample_long(
            "streaming",
            S.Models(m),
            codec,
            controls,
            first,
            length,
            tmp_path / str(length),
            key=jax.random.key(0),
            fps=12.0,
        )
    small, big = reports[33], reports[721]
    assert small["compiled_programs"] == big["compiled_programs"] == 1
    assert big["sequential_sampler_calls"] == 720
    assert big["stream"]["buffer_bytes"] == small["stream"]["buffer_bytes"] > 0
    assert big["stream"]["taps"] == list(TAPS) and big["stream"]["buffer_frames"] == BUFFER
    assert small["peak_device_bytes"] > 0 and abs(big["peak_device_bytes"] / small["peak_device_bytes"] - 1) < 0.10


def _training(m: WindowModel, stream: StreamConfig):
    from jaxdrive.train.flow_step import FlowTraining

    return FlowTraining(m.dit.config, FlowConfig(shift=m.shift), LatentCodec("space_to_depth", 4), stream=stream)


def test_condition_frame_augmentation_degrades_its_share_then_adds_noise():
    from jaxdrive.train.stream_step import _augment

    prev = jnp.asarray(np.random.default_rng(2).normal(size=(64, 2, 1, H, W, C)), jnp.float32)
    key = jax.random.key(5)
    every = _augment(key, prev, StreamConfig(degrade_rate=1.0, degrade_keep=0.5, cond_noise=0.0))
    np.testing.assert_allclose(every, flow.degrade_frames(prev, jnp.ones((64, 1), bool), 0.5), atol=1e-6)
    assert float(jnp.abs(every - prev).max()) > 0.1
    none = _augment(key, prev, StreamConfig(degrade_rate=0.0, cond_noise=0.0))
    np.testing.assert_array_equal(none, prev)
    noisy = np.asarray(_augment(key, prev, StreamConfig(degrade_rate=0.0, cond_noise=0.1)) - prev)
    assert abs(noisy.std() - 0.1) < 0.005 and abs(noisy.mean()) < 0.005
    # a share: about 30% of the clips degraded (each clip all or nothing)
    some = np.asarray(_augment(key, prev, StreamConfig(degrade_rate=0.3, degrade_keep=0.5, cond_noise=0.0)))
    changed = np.abs(some - np.asarray(prev)).reshape(64, -1).max(axis=1) > 1e-6
    assert 8 <= changed.sum() <= 32


@pytest.mark.slow(seconds=61)
def test_training_sees_what_the_sampler_buffer_holds_and_stage_3_conditions_on_its_own_rollout():
    from jaxdrive.train import stream_step

    m = model()
    stream = StreamConfig(enabled=True, buffer=BUFFER, taps=TAPS, self_rollout=True, rollout_steps=m.steps)
    training = _training(m, stream)
    nf = 6
    first, controls = horizon_inputs(nf, given=1)
    x = jnp.asarray(np.random.default_rng(1).normal(size=(1, 2, nf, H, W, C)), jnp.float32)
    key, sigma = jax.random.key(7), jnp.asarray([0.6])
    # jitted, as the train step runs them (op by op they compile hundreds of small programs)
    store = jax.jit(functools.partial(stream_step.past_features, training))(m.params, x, x, controls, sigma, key)
    buf = ST.new_buffer(dataclasses.replace(m, steps=1), 1, 2, (H, W))
    for p in range(1, nf - 1):  # the sampler's observation of recorded frames at the one level
        buf = ST.observe_frame(
            m,
            TAPS,
            m.params,
            x[:, :, :1],
            x[:, :, p - 1 : p],
            x[:, :, p : p + 1],
            ST.window_controls(controls, p, 1),
            jax.random.fold_in(key, p),
            buf,
            sigmas=sigma,
        )
        np.testing.assert_allclose(store[0][:, p], buf["data"][0][0, :, (p - 1) % BUFFER], atol=2e-5, err_msg=str(p))
    # stage 3: the condition frames are the model's own streaming rollout, not the recording
    rolled = jax.jit(functools.partial(stream_step.self_rollout, training))(m.params, x, controls, key)
    assert rolled.shape == (1, 2, nf - 1, H, W, C)
    np.testing.assert_array_equal(rolled[:, :, 0], x[:, :, 0])
    # (the training codec's latents lie in [-1, 1]: its rollout clips as the sampler of that codec does)
    sampler = dataclasses.replace(m, value_range=(-1.0, 1.0))
    want = np.concatenate(
        list(S.run_strategy("streaming", S.Models(sampler), controls, np.asarray(x[:, :, :1]), nf - 1, key=key)), axis=2
    )
    np.testing.assert_allclose(rolled, want, atol=2e-5)
    assert np.abs(rolled[:, :, 1:]).max() <= 1.0
    assert float(jnp.abs(rolled[:, :, 1:] - x[:, :, 1 : nf - 1]).min()) > 0
    # and the loss of a window is finite and has gradients for HTFT
    loss, grads = jax.jit(
        jax.value_and_grad(
            lambda p: stream_step.stream_loss_fn(training, p, x, {"cond": controls}, jax.random.key(0))[0]
        )
    )(m.params)
    assert np.isfinite(float(loss)) and float(jnp.abs(grads["htft_0"]["linear_out"]["kernel"]).max()) > 0


def test_streaming_rejects_what_it_cannot_do():
    first, controls = horizon_inputs(6, given=1)
    with pytest.raises(ValueError, match=r"^taps: expected offsets in \[-4, -1\]"):
        list(S.run_strategy("streaming", S.Models(model()), controls, first, 6, key=jax.random.key(0), taps=(-1, -5)))
    with pytest.raises(ValueError, match=r"^taps: HTFT streaming needs a model with HTFT layers"):
        S.check_taps(S.Models(model(htft=False)), (-1,))
    assert S.check_taps(S.Models(model(htft=False)), ()) == ()
    windowed = dataclasses.replace(model(), streaming=False)
    with pytest.raises(ValueError, match=r"^models.main: 'streaming' needs a model trained frame by frame"):
        S.check_strategy("streaming", S.Models(windowed), 6, 1)
    with pytest.raises(ValueError, match=r"^strategy: a model trained frame by frame"):
        S.check_strategy("rollout", S.Models(model()), 6, 1)


@pytest.mark.slow(seconds=7)
def test_guidance_evaluates_both_variants_with_the_same_past():
    m = dataclasses.replace(model(), guidance=3.0)
    first, controls = horizon_inputs(5, given=1)
    controls = controls.replace(drop={"waypoints": np.zeros((1,), bool)})
    key = jax.random.key(0)
    guided = np.concatenate(list(S.run_strategy("streaming", S.Models(m), controls, first, 5, key=key)), axis=2)
    plain = np.concatenate(
        list(S.run_strategy("streaming", S.Models(dataclasses.replace(m, guidance=1.0)), controls, first, 5, key=key)),
        axis=2,
    )
    assert np.isfinite(guided).all() and float(np.abs(guided[:, :, 1:] - plain[:, :, 1:]).max()) > 1e-3


@pytest.mark.slow(seconds=32)
def test_a_scanned_stage_1_model_loads_into_stage_2_with_its_outputs_unchanged():
    """``configs/stage.py`` scans its layers (28 + 13 unrolled ones in each of the step's model
    passes made its compile take over 15 minutes): stage 2's HTFT layer splits stage 1's scanned run
    in two, and ``train.init_from`` moves the layers across; HTFT's zero output layer then leaves
    the stage-1 outputs as they were, past features or not."""
    from jaxdrive.models.dit.inputs import example_inputs
    from jaxdrive.train.init_from import merge_params

    from dit_fixtures import perturb

    cfg = preset(
        "tiny",
        depth=4,
        in_channels=C,
        vae_spatial=4,
        vae_temporal=1,
        patch=(1, 2, 2),
        prediction="data",
        scan_layers=True,
    )
    stage1, stage2 = DiT(cfg), DiT(cfg.replace(htft_layers=(1,)))
    init = lambda dit: jax.tree_util.tree_map(
        jnp.asarray, nn.unbox(dit.init_params(0, batch=1, views=2, frames=3, height=H, width=W))
    )
    p1 = perturb(init(stage1))
    p2, report = merge_params(init(stage2), p1)
    assert "layers_0_4" in p1
    assert {"layers_0_2", "layers_2_4"} <= set(p2) and all(k.startswith("htft_") for k in report.kept)
    assert report.unused == ()
    ex = example_inputs(cfg, batch=1, views=2, frames=3, height=H, width=W)
    # jitted: eagerly, every op of the forward compiles on its own
    want = jax.jit(stage1.forward)(p1, ex["latents"], ex["sigma"], ex["cond"])
    past = np.ones((1, 2, (H // 2) * (W // 2), 2, cfg.width), np.float32)
    forward2 = jax.jit(stage2.forward)
    for cond in (ex["cond"], ex["cond"].replace(features={1: past}, features_mask=np.ones((1, 2), bool))):
        np.testing.assert_allclose(forward2(p2, ex["latents"], ex["sigma"], cond), want, rtol=1e-6, atol=1e-6)


@pytest.mark.optimized_xla
@pytest.mark.slow(seconds=15)
def test_the_stage_3_step_holds_each_model_pass_once_whatever_the_depth():
    """The step's passes (self-rollout, feature pass, gradient window) loop in ``lax.scan`` and,
    with scanned layers (``configs/stage.py`` at paper size), hold each layer run once: the
    lowered program's matmuls do not grow with the depth (unrolled, each pass held every layer's)."""
    from pathlib import Path

    from jaxdrive.config import load_config
    from jaxdrive.train import stream_step

    config = Path(__file__).resolve().parents[1] / "configs" / "stage.py"
    assert all(load_config(f"{config}:stage={s}").model.scan_layers for s in (1, 2, 3))
    stream = StreamConfig(enabled=True, buffer=BUFFER, taps=TAPS, self_rollout=True, rollout_steps=2)
    nf = 6
    _, controls = horizon_inputs(nf, given=1)
    x = jax.ShapeDtypeStruct((1, 2, nf, H, W, C), jnp.float32)

    def size(depth):
        cfg = preset(
            "tiny",
            depth=depth,
            in_channels=C,
            vae_spatial=4,
            vae_temporal=1,
            patch=(1, 2, 2),
            prediction="data",
            htft_layers=(0,),
            scan_layers=True,
            controls=dict(waypoints=True, fps=True, cond_frames="replace", reference_frame="residual"),
        )
        dit = DiT(cfg)
        params = nn.unbox(dit.init_params(0, batch=1, views=2, frames=3, height=H, width=W))
        training = _training(
            WindowModel(
                dit, None, window=3, cond_frames=1, steps=2, streaming=True, stream_buffer=BUFFER, stream_taps=TAPS
            ),
            stream,
        )
        grad = jax.grad(
            lambda p, x: stream_step.stream_loss_fn(training, p, x, {"cond": controls}, jax.random.key(0))[0]
        )
        return jax.jit(grad).lower(params, x).as_text().count("stablehlo.dot_general")

    assert size(5) == size(3)


def test_the_stream_buffer_is_sharded_like_the_batch_it_stores():
    """The HTFT ring (``[steps, B, slots, S, V, D]`` per layer) of the stage-3 self-rollout and the
    sampler: batch over data x fsdp, tokens over seq. Zeros alone came replicated, and STAGE's
    paper step held the ring of its whole batch of 32 on every device (126 GiB at fsdp 32)."""
    from jaxdrive.parallel import make_mesh

    cfg = preset(
        "tiny",
        depth=2,
        in_channels=C,
        vae_spatial=4,
        vae_temporal=1,
        patch=(1, 2, 2),
        htft_layers=(0,),
        prediction="data",
    )
    model = WindowModel(
        DiT(cfg), None, window=3, cond_frames=1, steps=2, streaming=True, stream_buffer=BUFFER, stream_taps=TAPS
    )
    with jax.set_mesh(make_mesh(data=2, fsdp=2, seq=2)):
        buf = jax.jit(lambda: ST.new_buffer(model, 4, 2, (H, W)))()
    ring = buf["data"][0]
    assert ring.shape == (2, 4, BUFFER, (H // 2) * (W // 2), 2, cfg.width)
    spec = tuple(ring.sharding.spec) + (None,) * (ring.ndim - len(ring.sharding.spec))
    assert spec[1] == ("data", "fsdp") and spec[3] == "seq" and spec[0] is None and spec[2] is None
    assert ring.addressable_shards[0].data.shape == (2, 1, BUFFER, (H // 2) * (W // 2) // 2, 2, cfg.width)
