import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from jaxdrive import flow


def test_shift_worked_numbers():
    # r = 3, s = 0.5: 1.5 / 2 = 0.75
    assert float(flow.shift_sigmas(0.5, 3.0)) == pytest.approx(0.75)
    # r = 0.5, s = 0.5: 0.25 / 0.75 = 1/3
    assert float(flow.shift_sigmas(0.5, 0.5)) == pytest.approx(1 / 3)


@given(st.floats(0.0, 1.0), st.floats(0.0, 1.0), st.floats(0.05, 20.0))
def test_shift_is_a_monotone_bijection_of_the_unit_interval(a, b, r):
    lo, hi = min(a, b), max(a, b)
    s = flow.shift_sigmas(jnp.array([0.0, lo, hi, 1.0]), r)
    assert float(s[0]) == 0.0 and float(s[3]) == pytest.approx(1.0, abs=1e-6)
    assert float(s[1]) <= float(s[2]) + 1e-6
    if r > 1:  # towards noise
        assert float(s[1]) >= lo - 1e-6


def test_shift_identity_at_ratio_one():
    s = jnp.linspace(0, 1, 11)
    np.testing.assert_allclose(flow.shift_sigmas(s, 1.0), s, atol=1e-7)


def test_resolution_shift_matches_open_sora_rule():
    assert flow.resolution_shift(512, 512, 1) == pytest.approx(1.0)
    # sqrt(4 * 512^2 / 512^2) * sqrt(4 / 1) = 4
    assert flow.resolution_shift(1024, 1024, 4) == pytest.approx(4.0)
    # MagicDrive-V2-like clip: 424x800 pixels, 9 latent frames, base 512^2
    assert flow.resolution_shift(424, 800, 9) == pytest.approx(math.sqrt(424 * 800 / 512**2) * 3.0)
    assert flow.resolution_shift(256, 256, 2, base_pixels=256 * 256, base_latent_frames=2, scale=2.0) == 2.0


def test_logit_normal_statistics():
    s = flow.sample_sigmas(jax.random.PRNGKey(0), (20000,), loc=0.5, scale=1.0)
    assert s.shape == (20000,) and float(s.min()) > 0 and float(s.max()) < 1
    # median of sigmoid(N(0.5, 1)) is sigmoid(0.5)
    assert float(jnp.median(s)) == pytest.approx(1 / (1 + math.exp(-0.5)), abs=0.01)


def test_uniform_and_shifted_sampling():
    key = jax.random.PRNGKey(1)
    u = flow.sample_sigmas(key, (4, 6), distribution="uniform")
    assert u.shape == (4, 6) and float(u.min()) >= 0 and float(u.max()) <= 1
    shifted = flow.sample_sigmas(key, (4, 6), distribution="uniform", shift=3.0)
    np.testing.assert_allclose(shifted, flow.shift_sigmas(u, 3.0), atol=1e-6)
    assert bool(jnp.all(shifted >= u - 1e-6))


def test_sampling_schedule():
    s = flow.sampling_sigmas(5)
    np.testing.assert_allclose(s, [1.0, 0.8, 0.6, 0.4, 0.2, 0.0], atol=1e-6)
    s = flow.sampling_sigmas(30, shift=3.0)
    assert s.shape == (31,) and float(s[-1]) == 0.0 and float(s[0]) == pytest.approx(1.0)
    assert bool(jnp.all(jnp.diff(s) < 0))


def test_a_sampling_schedule_below_1_starts_at_its_level_on_the_shifted_path():
    """``sigma_max`` < 1 (SDEdit's start): the first level is ``sigma_max`` itself, whatever the
    shift, and the others are the shift of evenly spaced levels below its unshifted one."""
    s = flow.sampling_sigmas(4, shift=3.0, sigma_max=0.6)
    # the shift 3 maps 1/3 to 0.6: the even levels 1/3, 1/4, 1/6, 1/12, 0, shifted (3 t / (1 + 2 t))
    np.testing.assert_allclose(s, [0.6, 0.5, 0.375, 0.25 / (7 / 6), 0.0], atol=1e-6)
    np.testing.assert_allclose(s, flow.shift_sigmas(np.linspace(1 / 3, 0, 5), 3.0), atol=1e-6)
    np.testing.assert_allclose(flow.sampling_sigmas(4, sigma_max=0.6), [0.6, 0.45, 0.3, 0.15, 0.0], atol=1e-6)


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: flow.sample_sigmas(jax.random.PRNGKey(0), (2,), distribution="beta"), "distribution: expected one of"),
        (lambda: flow.sample_sigmas(jax.random.PRNGKey(0), 2), "shape: expected a tuple"),
        (lambda: flow.sample_sigmas(jax.random.PRNGKey(0), (2,), scale=0.0), r"scale: expected values in \(0.0, inf\]"),
        (lambda: flow.shift_sigmas(0.5, -1.0), "ratio: expected values in"),
        (lambda: flow.shift_sigmas(1.5, 2.0), "sigma: expected values in"),
        (lambda: flow.resolution_shift(0, 10, 1), "height: expected an integer >= 1, got 0"),
        (lambda: flow.sampling_sigmas(0), "num_steps: expected an integer >= 1, got 0"),
    ],
)
def test_bad_inputs(call, match):
    with pytest.raises(ValueError, match=match):
        call()
