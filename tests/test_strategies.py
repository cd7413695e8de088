"""Long-video strategies (jaxdrive.generate.strategies) on a tiny random DiT: what each pins,
corrects and calls, and device memory flat in the length."""

from __future__ import annotations

import dataclasses
import functools
import json
from types import SimpleNamespace

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdrive.generate import strategies as S
from jaxdrive.generate.long_video import sample_long
from jaxdrive.generate.windows import Tracker, WindowModel
from jaxdrive.models.dit import DiT
from jaxdrive.models.dit.presets import preset
from jaxdrive.models.latents import LatentCodec

from strategy_fixtures import C, H, W, horizon_inputs


@functools.cache
def tiny_model(window: int, **kw) -> WindowModel:
    cfg = preset(
        "tiny",
        depth=1,  # the strategies' windows, not the model's depth, are under test
        in_channels=C,
        vae_spatial=4,
        vae_temporal=1,
        text_dim=64,
        text_len=16,
        patch=(1, 2, 2),
        prediction="data",
        controls=dict(text=None, waypoints=True, fps=True, cond_frames="replace", reference_frame="residual"),
    )
    dit = DiT(cfg)
    params = jax.tree_util.tree_map(
        jnp.asarray, nn.unbox(dit.init_params(0, batch=1, views=2, frames=window, height=H, width=W))
    )
    keys = iter(jax.random.split(jax.random.key(1), len(jax.tree_util.tree_leaves(params))))
    params = jax.tree_util.tree_map(lambda p: p + 0.05 * jax.random.normal(next(keys), p.shape), params)
    return WindowModel(dit, params, window=window, cond_frames=2, steps=2, **kw)


def run(name, models, length, *, given=2, views=2, tracker=None, **options):
    first, controls = horizon_inputs(length, views, given)
    parts = list(
        S.run_strategy(name, models, controls, first, length, key=jax.random.key(0), tracker=tracker, **options)
    )
    return parts, np.concatenate(parts, axis=2), first


@pytest.mark.slow(seconds=6)
def test_rollout_pins_the_given_frames_and_yields_each_window_as_it_is_done():
    m = tiny_model(5)
    tracker = Tracker()
    parts, out, first = run("rollout", S.Models(m), 13, tracker=tracker)
    assert [p.shape[2] for p in parts] == [5, 3, 3, 2]  # windows 0, 3, 6, 8 (the last starts earlier)
    np.testing.assert_array_equal(out[:, :, :2], first)
    assert tracker.calls == 4 == S.sequential_calls("rollout", S.Models(m), 13, 2)
    assert np.isfinite(out).all() and out[:, :, 2:].std() > 0.1


@pytest.mark.slow(seconds=5)
def test_coarse_to_refine_corrects_its_anchors_and_without_anchors_is_rollout():
    m = tiny_model(5, jdc_anchor_rate=0.75, anchor_every=3)
    models = S.Models(m)
    first, controls = horizon_inputs(13)
    horizon, _ = S.coarse_anchors(models, controls, first, 13, key=jax.random.key(0), anchor_every=3)
    anchors = [4, 7, 10]  # given - 1 + j * 3
    assert horizon.known.nonzero()[0].tolist() == [0, 1] + anchors
    tracker = Tracker()
    _, out, _ = run("coarse-to-refine", models, 13, tracker=tracker, anchor_every=3)
    np.testing.assert_array_equal(out[:, :, :2], first)
    # the refine pass re-noises the anchors (JDC) and denoises them jointly: they change
    assert np.abs(out[:, :, anchors] - horizon.latents[:, :, anchors]).mean() > 1e-3
    _, rolled, _ = run("rollout", models, 13)
    assert tracker.calls == S.sequential_calls("coarse-to-refine", models, 13, 2, anchor_every=3)
    _, off, _ = run("coarse-to-refine", models, 13, anchor_every=0)
    np.testing.assert_array_equal(off, rolled)  # no anchors: exactly the rollout


class StillModel:
    """A stand-in DiT whose velocity is 0: the sampler returns its start state, so a window's
    output shows how the strategy initialised it (hashable: a static jit argument)."""

    config = SimpleNamespace(
        controls=SimpleNamespace(cond_frames=None, warp=False), prediction="velocity", prediction_min_sigma=0.05
    )

    @staticmethod
    def forward(params, x, sigma, cond):
        return jnp.zeros_like(x)


def test_refine_windows_start_their_anchors_at_the_jdc_level():
    """MiLA eq. 9-12 at g = 0.5 (slope 0.5 at sigma = 1), alpha1 = 0.1: a2 = 0.4 / 0.9, the
    anchor becomes (1 - a2) z + N(0, a2 (a2 + 2 a1 (1 - a2))), the other frames pure noise."""
    still = WindowModel(StillModel(), None, window=5, cond_frames=2, steps=2, jdc_anchor_rate=0.75, anchor_every=3)
    first, controls = horizon_inputs(13)
    horizon, key = S.coarse_anchors(S.Models(still), controls, first, 13, key=jax.random.key(0), anchor_every=3)
    z = horizon.latents[:, :, [4, 7, 10]]
    out = np.concatenate(
        list(S.coarse_to_refine(S.Models(still), controls, first, 13, key=jax.random.key(0), anchor_every=3)), axis=2
    )
    a1, a2 = 0.1, 0.4 / 0.9
    resid = out[:, :, [4, 7, 10]] - (1 - a2) * z
    assert abs(resid.mean()) < 0.02
    np.testing.assert_allclose(resid.std(), np.sqrt(a2 * (a2 + 2 * a1 * (1 - a2))), rtol=0.03)
    np.testing.assert_allclose(out[:, :, [2, 3, 5, 6, 8, 9, 11, 12]].std(), 1.0, rtol=0.03)  # noise
    np.testing.assert_array_equal(out[:, :, :2], first)


@pytest.mark.slow(seconds=9)
def test_coarse_fine_keeps_the_coarse_keyframes_bit_for_bit_in_one_fine_call():
    coarse = tiny_model(4, stride=6)
    fine = dataclasses.replace(tiny_model(7), patterns=("prefix", "ends"))
    models = S.Models(coarse, fine)
    first, controls = horizon_inputs(25, given=1)
    keyframes = [0, 6, 12, 18, 24]
    horizon, _ = S.coarse_anchors(
        S.Models(coarse, dataclasses.replace(fine, anchor_every=6)),
        controls,
        first,
        25,
        key=jax.random.key(0),
        anchor_every=6,
    )
    tracker = Tracker()
    parts, out, _ = run("coarse-fine", models, 25, given=1, tracker=tracker, segment_batch=4)
    np.testing.assert_array_equal(out[:, :, keyframes], horizon.latents[:, :, keyframes])
    coarse_windows = len(S.window_starts(5, 4, 1))
    assert tracker.calls == coarse_windows + 1 == S.sequential_calls("coarse-fine", models, 25, 1, segment_batch=4)
    between = [f for f in range(25) if f not in keyframes]
    assert np.abs(out[:, :, between]).mean() > 0.1  # the segments were filled
    tracker = Tracker()
    _, capped, _ = run("coarse-fine", models, 25, given=1, tracker=tracker, segment_batch=3)
    assert tracker.calls == coarse_windows + 2  # 4 segments, 3 per call
    np.testing.assert_array_equal(capped[:, :, keyframes], out[:, :, keyframes])
    tracker = Tracker()  # the default on a CPU: one segment a call
    _, auto, _ = run("coarse-fine", models, 25, given=1, tracker=tracker)
    assert tracker.calls == coarse_windows + 4 and tracker.notes["segment_batch"]["segment_batch"] == 1
    np.testing.assert_array_equal(auto[:, :, keyframes], out[:, :, keyframes])


@pytest.mark.slow(seconds=8)
@pytest.mark.parametrize("name", ["rollout", "coarse-fine"])
def test_every_window_strategy_keeps_its_sampled_frames_in_the_latents_range(name):
    """As streaming does: a sampled frame that becomes a later call's condition frame is clipped to
    the codec's range (``WindowModel.value_range``) first, so the next window samples from the
    clipped frame; the given frames come through unchanged even where they lie outside it. Every
    window strategy samples through ``sample_window``: the rollout and the coarse-fine (one
    window-by-window pass, one stacked pass) stand for the others."""
    r = 0.05
    if name == "coarse-fine":
        length, given = 13, 1
        models = S.Models(tiny_model(4, stride=4), dataclasses.replace(tiny_model(5), patterns=("prefix", "ends")))
    else:
        length, given = 9, 2
        models = S.Models(tiny_model(5))
    ranged = S.Models(
        *(None if m is None else dataclasses.replace(m, value_range=(-r, r)) for m in (models.main, models.fine))
    )
    _, free, first = run(name, models, length, given=given)
    _, got, _ = run(name, ranged, length, given=given)
    assert np.abs(free[:, :, given:]).max() > 2 * r  # the model leaves the range
    assert np.abs(got[:, :, given:]).max() <= r
    np.testing.assert_array_equal(got[:, :, :given], first)
    assert np.abs(first).max() > r  # given frames are not clipped
    if name == "rollout":
        # the later windows (new frames 5-8) are conditioned on window 1's clipped frames 3-4
        np.testing.assert_allclose(
            got[:, :, :5],
            np.where(np.arange(5)[:, None, None, None] < given, free[:, :, :5], np.clip(free[:, :, :5], -r, r)),
            atol=1e-6,
        )
        assert np.abs(got[:, :, 5:] - np.clip(free[:, :, 5:], -r, r)).max() > 1e-3


def test_strategies_reject_what_they_cannot_do_before_compiling():
    m = tiny_model(5)
    with pytest.raises(ValueError, match=r"^models.fine: strategy 'coarse-fine' needs a fine model run"):
        S.check_strategy("coarse-fine", S.Models(m), 25, 1)
    with pytest.raises(ValueError, match=r"^models.fine: expected a model trained for interpolation"):
        S.check_strategy("coarse-fine", S.Models(m, tiny_model(7)), 25, 1)
    fine = dataclasses.replace(tiny_model(7), patterns=("prefix", "ends"))
    with pytest.raises(
        ValueError,
        match=r"frames: coarse-fine reaches 1 \+ n \* 6 latent frames .* got 24; "
        r"e.g. 19 or 25",
    ):
        S.check_strategy("coarse-fine", S.Models(m, fine), 24, 1)
    with pytest.raises(
        ValueError,
        match=r"^models.main: coarse-to-refine needs a model trained to correct JDC "
        r"anchors",
    ):
        S.check_strategy("coarse-to-refine", S.Models(m), 25, 2)
    with pytest.raises(
        ValueError,
        match=r"^models.main: coarse-to-refine draws spaced anchors, which needs "
        r"frame-wise",
    ):
        S.check_strategy("coarse-to-refine", S.Models(dataclasses.replace(m, temporal=4, jdc_anchor_rate=0.5)), 25, 2)
    with pytest.raises(ValueError, match=r"strategy: expected one of"):
        S.check_strategy("one-shot", S.Models(m), 25, 2)
    with pytest.raises(
        ValueError,
        match=r"^strategy: 'window' samples the whole length at once, which needs a model "
        r"trained on several lengths \(data.buckets, MagicDrive-V2\), got one trained "
        r"on \[5\] latent frames only",
    ):
        S.check_strategy("window", S.Models(m), 25, 2)
    with pytest.raises(ValueError, match=r"frames: expected more latent frames than the 2 given ones, got 2"):
        S.check_strategy("rollout", S.Models(m), 2, 2)


@pytest.mark.optimized_xla
@pytest.mark.slow(seconds=119)
def test_device_memory_is_flat_in_the_length_at_the_defaults(tmp_path):
    """721 frames (a minute at 12 fps) on 6 views need the device memory of 145 (within 10%), with
    no option: coarse-fine groups its segments (``segment_batch="auto"``) by the budget."""
    cases = {
        "rollout": S.Models(tiny_model(5)),
        "coarse-to-refine": S.Models(tiny_model(5, jdc_anchor_rate=0.75, anchor_every=3)),
        "coarse-fine": S.Models(tiny_model(4, stride=6), dataclasses.replace(tiny_model(7), patterns=("ends",))),
    }
    codec = LatentCodec("space_to_depth", 4)
    for name, models in cases.items():
        given = 1 if name == "coarse-fine" else 2
        peaks, reports = {}, {}
        for length in (145, 721):
            first, controls = horizon_inputs(length, views=6, given=given)
            report = sample_long(
                name,
                models,
                codec,
                controls,
                first,
                length,
                tmp_path / f"{name}{length}",
                key=jax.random.key(0),
                fps=12.0,
            )
            peaks[length], reports[length] = report["peak_device_bytes"], report
            options = {"segment_batch": report["segment_batch"]["segment_batch"]} if name == "coarse-fine" else {}
            assert report["sequential_sampler_calls"] == S.sequential_calls(name, models, length, given, **options)
        assert peaks[145] > 0 and abs(peaks[721] / peaks[145] - 1) < 0.10, (name, peaks)
    auto = {n: reports[n]["segment_batch"] for n in (145, 721)}
    assert auto[145]["segments"] == 24 and auto[721]["segments"] == 120
    assert auto[145]["segment_batch"] == auto[721]["segment_batch"] == 1  # a CPU: one by one
    assert auto[721]["budget_source"].startswith("CPU") and auto[721]["footprint_bytes"] == auto[721]["probed"]["1"]
    report = json.loads((tmp_path / "coarse-fine721" / "report.json").read_text())
    assert {
        "strategy",
        "frames",
        "views",
        "sequential_sampler_calls",
        "seconds",
        "peak_device_bytes",
        "segment_batch",
    } <= set(report)
    assert (report["strategy"], report["frames"], report["views"]) == ("coarse-fine", 721, 6)
    assert np.load(tmp_path / "coarse-fine721" / "latents.npy").shape == (1, 6, 721, H, W, C)
    assert (tmp_path / "coarse-fine721" / "sample.mp4").stat().st_size > 0


@pytest.mark.slow(seconds=6)
def test_window_is_one_call_over_the_whole_length_and_seq_sharding_changes_nothing():
    """MagicDrive-V2's one-shot window: 13 latent frames (past the 5 it trained on) in one sampler
    call, the given frames pinned; the same numbers with its tokens over seq = 4 as on one device."""
    from jaxdrive.parallel import make_mesh

    m = dataclasses.replace(tiny_model(5), lengths=(1, 5))  # trained on images and 5-frame clips
    first, controls = horizon_inputs(13)
    out = {}
    for seq in (1, 4):
        mesh, tracker = make_mesh(seq=seq, devices=jax.devices()[:seq]), Tracker()
        with jax.set_mesh(mesh):
            parts = list(
                S.run_strategy(
                    "window", S.Models(m), controls, first, 13, key=jax.random.key(0), tracker=tracker, mesh=mesh
                )
            )
        assert len(parts) == 1 and tracker.calls == 1 == S.sequential_calls("window", S.Models(m), 13, 2)
        out[seq] = parts[0]
    assert out[1].shape == (1, 2, 13, H, W, C) and out[1][:, :, 2:].std() > 0.1
    np.testing.assert_array_equal(out[1][:, :, :2], first)
    np.testing.assert_allclose(out[4], out[1], rtol=1e-4, atol=1e-4)


@pytest.mark.slow(seconds=9)
def test_the_automatic_segment_batch_is_the_largest_group_that_fits_the_budget():
    from jaxdrive.generate.segments import choose_segment_batch
    from jaxdrive.generate.windows import Horizon

    fine = dataclasses.replace(tiny_model(7), patterns=("ends",))
    first, controls = horizon_inputs(61, views=2, given=1)
    horizon = Horizon.start(first, 61)

    def choose(budget, tracker=None):
        return choose_segment_batch(
            fine,
            horizon,
            controls,
            10,
            given=1,
            key=jax.random.key(0),
            tracker=tracker or Tracker(),
            device_memory=budget,
        )

    every = {n: choose(2**40)["probed"] for n in (0,)}[0]  # all ten in one call: 1 and 10 probed
    one, ten = every["1"], every["10"]
    assert choose(2**40)["segment_batch"] == 10
    for budget in (one, (one + ten) // 2, ten - 1):
        tracker = Tracker()
        got = choose(budget, tracker)
        n = got["segment_batch"]
        assert got["footprint_bytes"] == got["probed"][str(n)] <= budget and got["budget_source"] == "device_memory"
        assert got["probed"][str(n + 1)] > budget  # the next group would not fit
        assert tracker.programs == 0  # probes are not the run's programs
    with pytest.raises(
        ValueError,
        match=r"^device_memory: expected a budget that holds one fine call of 1 "
        r"segment\(s\) \(\d+ bytes per device\), got 1000 bytes",
    ):
        choose(1000)


@pytest.mark.parametrize(
    "value, message",
    [
        ("0", "^segment_batch: expected 'auto' or a positive number"),
        ("many", "^segment_batch: expected 'auto' or a positive number"),
        (-2, "^segment_batch: expected 'auto' or a positive number"),
    ],
)
def test_segment_batch_rejects_what_is_not_a_group(value, message):
    from jaxdrive.generate.segments import check_segment_batch

    with pytest.raises(ValueError, match=message):
        check_segment_batch(value)
    assert check_segment_batch("auto") == check_segment_batch(None) == "auto" and check_segment_batch("3") == 3


def test_device_memory_budgets_parse_and_reject_what_is_no_size():
    from jaxdrive.parallel.memory import device_budget, host_memory_bytes, parse_bytes

    assert parse_bytes("16GiB") == 16 * 2**30 and parse_bytes("512 MiB") == 512 * 2**20
    assert parse_bytes("8e9") == 8 * 10**9 == parse_bytes("8GB") and parse_bytes(4096) == 4096
    for bad in ("lots", "12 parsecs", "0", -5, True):
        with pytest.raises(ValueError, match=r"^device_memory: expected a positive size"):
            parse_bytes(bad)
    assert device_budget("1GiB") == (2**30, "device_memory", True)
    budget, source, strict = device_budget()  # a CPU: its share, a preference
    assert 0 < budget <= host_memory_bytes() / 4 and source.startswith("CPU") and not strict


def test_live_device_bytes_count_each_replica_once_and_create_no_array():
    """A CPU reports no device memory, so the trackers add up the live arrays: a sharded array's
    shards, a replicated one's full copy on every device. A count makes no new array (reading
    ``addressable_shards`` did, which doubled every later count)."""
    from jax.sharding import NamedSharding
    from jax.sharding import PartitionSpec as P

    from jaxdrive.parallel.memory import live_device_bytes, shard_bytes
    from jaxdrive.parallel.mesh import make_mesh

    mesh = make_mesh(data=2, seq=4)
    before = live_device_bytes()
    sharded = jax.device_put(np.ones((8, 16), np.float32), NamedSharding(mesh, P("data", "seq")))
    replicated = jax.device_put(np.ones((8, 16), np.float32), NamedSharding(mesh, P()))
    half = jax.device_put(np.ones((6, 10), jnp.bfloat16), NamedSharding(mesh, P("data")))
    one = jax.device_put(np.ones(5, np.int32), jax.devices()[3])
    assert (shard_bytes(sharded), shard_bytes(replicated), shard_bytes(half), shard_bytes(one)) == (64, 512, 60, 20)
    arrays = len(jax.live_arrays())
    added = live_device_bytes() - before
    assert added == 8 * 16 * 4 + 8 * 8 * 16 * 4 + 8 * 3 * 10 * 2 + 5 * 4
    assert live_device_bytes() - before == added and len(jax.live_arrays()) == arrays
    del sharded, replicated, half, one
