"""GameNGen's noise on the given frames: in training a level per clip, at sampling a small one,
and each reaches the model as those frames' noise level."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdrive import flow
from jaxdrive.config import load_config

from train_fixtures import MACHINERY, write_synthetic

ROOT = Path(__file__).resolve().parents[1]


def test_noise_given_frames_worked_number_and_the_others_untouched():
    x = jnp.ones((2, 1, 3, 2, 2, 1))
    noise = jnp.full(x.shape, 3.0)
    mask = jnp.asarray([[True, False, False], [True, True, False]])
    out, level = flow.noise_given_frames(x, noise, mask, jnp.asarray([0.5, 0.25]))
    # (1 - s) * 1 + s * 3 = 1 + 2 s on the given frames
    np.testing.assert_allclose(np.asarray(out)[0, 0, :, 0, 0, 0], [2.0, 1.0, 1.0])
    np.testing.assert_allclose(np.asarray(out)[1, 0, :, 0, 0, 0], [1.5, 1.5, 1.0])
    np.testing.assert_array_equal(np.asarray(level), [[0.5, 0.0, 0.0], [0.25, 0.25, 0.0]])
    same, zero = flow.noise_given_frames(x, noise, mask, jnp.zeros(2))
    np.testing.assert_array_equal(same, x)
    np.testing.assert_array_equal(zero, 0.0)


def test_the_given_level_reaches_the_model_as_the_frames_sigma():
    from jaxdrive.models.dit.conditions import Conditions
    from jaxdrive.models.dit.model import _with_given_frames
    from jaxdrive.models.dit.presets import preset

    cfg = preset("tiny", in_channels=4, prediction="data", controls=dict(cond_frames="replace"))
    x = jnp.zeros((1, 1, 3, 4, 4, 4))
    mask = jnp.asarray([[True, False, False]])
    given = jnp.full(x.shape, 2.0)
    cond = Conditions(cond_latents=given, cond_mask=mask, cond_sigma=jnp.asarray([[0.3, 0.0, 0.0]]))
    xs, sig = _with_given_frames(cfg, x, jnp.asarray([[0.9, 0.9, 0.9]]), cond)
    np.testing.assert_allclose(np.asarray(sig), [[0.3, 0.9, 0.9]])
    np.testing.assert_array_equal(np.asarray(xs)[:, :, 0], 2.0)
    _, plain = _with_given_frames(cfg, x, jnp.asarray([[0.9, 0.9, 0.9]]), cond.replace(cond_sigma=None))
    np.testing.assert_allclose(np.asarray(plain), [[0.0, 0.9, 0.9]])
    with pytest.raises(ValueError, match="cond_sigma: the given frames' noise level needs cond_latents"):
        Conditions(cond_sigma=jnp.zeros((1, 3))).check(cfg, x, jnp.zeros((1, 3)))


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_synthetic(tmp_path_factory.mktemp("given") / "data", train=2, frames=9)


def test_the_train_step_noises_the_given_frames_and_tells_the_model(data, monkeypatch):
    from jaxdrive.train import flow_step
    from jaxdrive.train.run import Run

    sets = [
        f"data.path={data}",
        *MACHINERY,
        "model.depth=1",
        "flow.cond_frames=2",
        "flow.cond_frames_random=false",
        "flow.given_noise_max=0.7",
    ]
    run = Run(load_config(str(ROOT / "configs" / "tiny.py"), sets), devices=jax.devices()[:1])
    seen = {}
    forward = type(run.training.dit).forward

    def spy(self, params, x, sigma, cond, **kw):
        seen.update(x=x, sigma=sigma, cond=cond)
        return forward(self, params, x, sigma, cond, **kw)

    monkeypatch.setattr(type(run.training.dit), "forward", spy)
    state, _, _ = run.init_state()
    inputs = jax.tree_util.tree_map(lambda a: a[0], run.global_batch([next(iter(run.dataset()))]))
    with jax.set_mesh(run.mesh):
        flow_step.flow_loss_fn(run.training, state.params, None, inputs, jax.random.key(3))
    cond = seen["cond"]
    mask, level = np.asarray(cond.cond_mask), np.asarray(cond.cond_sigma)
    assert mask[:, :2].all() and not mask[:, 2:].any()
    assert np.all(level[:, 2:] == 0) and np.all((level[:, :2] > 0) & (level[:, :2] < 0.7))
    assert np.all(level[:, 0] == level[:, 1])  # one level a clip
    clean = np.asarray(run.training.codec.encode(None, np.asarray(inputs["video"])))
    noisy = np.asarray(cond.cond_latents)
    assert np.abs(noisy[:, :, :2] - clean[:, :, :2]).max() > 0.05  # the given frames noised
    np.testing.assert_array_equal(noisy[:, :, 2:], clean[:, :, 2:])


def test_the_sampler_noises_its_given_frames_to_the_sampling_level(monkeypatch):
    import flax.linen as nn

    from jaxdrive.generate.windows import WindowModel, sample_window
    from jaxdrive.models.dit import DiT
    from jaxdrive.models.dit.presets import preset

    from strategy_fixtures import C, H, W, horizon_inputs

    cfg = preset(
        "tiny",
        in_channels=C,
        vae_spatial=4,
        vae_temporal=1,
        patch=(1, 2, 2),
        prediction="data",
        controls=dict(waypoints=True, fps=True, cond_frames="replace"),
    )
    dit = DiT(cfg)
    params = jax.tree_util.tree_map(
        jnp.asarray, nn.unbox(dit.init_params(0, batch=1, views=2, frames=4, height=H, width=W))
    )
    m = WindowModel(dit, params, window=4, cond_frames=2, steps=2, given_noise=0.1)
    first, controls = horizon_inputs(4, given=2)
    seen = []
    forward = DiT.forward
    monkeypatch.setattr(
        DiT, "forward", lambda self, p, x, s, c, **kw: seen.append(c) or forward(self, p, x, s, c, **kw)
    )
    x_cond = np.zeros(first.shape[:2] + (4,) + first.shape[3:], np.float32)
    x_cond[:, :, :2] = first
    mask = jnp.asarray([[True, True, False, False]])
    out = sample_window(m, params, jnp.asarray(x_cond), mask, controls, jax.random.key(0))
    assert seen and all(np.allclose(np.asarray(c.cond_sigma), [[0.1, 0.1, 0.0, 0.0]]) for c in seen)
    assert all(np.abs(np.asarray(c.cond_latents)[:, :, :2] - first).max() > 0.01 for c in seen)  # noised
    np.testing.assert_array_equal(np.asarray(out)[:, :, :2], first)  # the given frames come back clean


@pytest.mark.parametrize(
    "sets, match",
    [
        (["flow.given_noise_max=1.0"], r"flow.given_noise_max: expected a noise level in \[0, 1\), got 1.0"),
        (
            ["flow.given_noise_max=0.2", "flow.given_noise_sample=0.3"],
            "flow.given_noise_sample: expected a level the model trained with",
        ),
        (
            ["flow.given_noise_max=0.5", "model.controls.cond_frames=concat"],
            "flow.given_noise_max: the given frames' noise level reaches",
        ),
    ],
)
def test_bad_levels_name_the_option(sets, match):
    from jaxdrive.config_checks import check_sections

    with pytest.raises(ValueError, match=match):
        check_sections(load_config(str(ROOT / "configs" / "tiny.py"), sets))
