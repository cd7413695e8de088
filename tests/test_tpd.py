import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from jaxdrive import flow


def test_worked_numbers_at_half_noise():
    # S = 4, omega = pi/2, sigma = 0.5: closed forms 1 - sqrt(2)/2, sqrt(2) - 1, 1/2, 2 - sqrt(2)
    got = flow.tpd_sigmas(0.5, 4)
    want = [1 - math.sqrt(2) / 2, math.sqrt(2) - 1, 0.5, 2 - math.sqrt(2)]
    np.testing.assert_allclose(got, want, atol=1e-6)


def test_matches_mila_eq13_in_progress_convention():
    sigma, s_count, omega = 0.37, 6, 1.2
    t = 1 - sigma
    for s in range(s_count):
        phi = 0.5 * math.pi * s / s_count
        f = 1 - (math.cos((1 - t) * omega + phi) - math.cos(phi)) / (math.cos(omega + phi) - math.cos(phi))
        assert float(flow.tpd_sigmas(sigma, s_count, omega)[s]) == pytest.approx(1 - f, abs=1e-6)


@pytest.mark.parametrize("frames", [1, 3, 12, 60])
@pytest.mark.parametrize("omega", [0.05, 1.0, math.pi / 2])
def test_endpoints_exact(frames, omega):
    out = flow.tpd_sigmas(jnp.array([0.0, 1.0]), frames, omega)
    np.testing.assert_array_equal(out[0], np.zeros(frames))
    np.testing.assert_array_equal(out[1], np.ones(frames))


# The property tests draw many frame counts: jitted, each count is one program to compile, where
# eagerly each of the function's jnp calls is one (as the train step calls it, inside jit).
jitted_tpd_sigmas = jax.jit(flow.tpd_sigmas, static_argnums=1)


@given(st.floats(0.0, 1.0), st.floats(0.0, 1.0), st.integers(1, 48), st.floats(0.01, math.pi / 2))
def test_each_frame_is_monotone_in_sigma(a, b, frames, omega):
    lo, hi = min(a, b), max(a, b)
    out = np.asarray(jitted_tpd_sigmas(np.array([lo, hi], np.float32), frames, omega))
    assert np.all(out[0] <= out[1] + 1e-6)
    assert np.all((out >= 0) & (out <= 1))


@given(st.floats(1e-4, 1 - 1e-4), st.integers(2, 48), st.floats(0.01, math.pi / 2))
def test_earlier_frames_never_noisier(sigma, frames, omega):
    out = np.asarray(jitted_tpd_sigmas(sigma, frames, omega))
    assert np.all(np.diff(out) >= -1e-6), out
    assert float(out[0]) <= sigma + 1e-6  # frame 0 is ahead of the base level


def test_any_leading_shape():
    sigma = jnp.linspace(0, 1, 12).reshape(3, 4)
    out = flow.tpd_sigmas(sigma, 5)
    assert out.shape == (3, 4, 5)
    np.testing.assert_allclose(out[1, 2], flow.tpd_sigmas(sigma[1, 2], 5), atol=0)


def test_frame_sigmas_with_prefix_conditions_equal_tpd_on_the_rest():
    sigma = jnp.array([0.3, 0.8])
    cond = jnp.array([[True, True, False, False, False], [True, False, False, False, False]])
    out = flow.tpd_frame_sigmas(sigma, cond)
    np.testing.assert_array_equal(out[0, :2], 0.0)
    np.testing.assert_allclose(out[0, 2:], flow.tpd_sigmas(0.3, 3), atol=1e-7)
    np.testing.assert_allclose(out[1, 1:], flow.tpd_sigmas(0.8, 4), atol=1e-7)


def test_frame_sigmas_rank_noisy_frames_around_interior_conditions():
    # first and last frame given (interpolation): the 3 middle frames are s = 0, 1, 2
    cond = jnp.array([[True, False, False, False, True]])
    out = flow.tpd_frame_sigmas(jnp.array([0.6]), cond)
    np.testing.assert_allclose(out[0, 1:4], flow.tpd_sigmas(0.6, 3), atol=1e-7)
    assert float(out[0, 0]) == 0.0 and float(out[0, 4]) == 0.0


def test_jit_and_grad():
    f = jax.jit(lambda s: flow.tpd_sigmas(s, 8))
    np.testing.assert_allclose(f(jnp.array([0.2, 0.9])), flow.tpd_sigmas(jnp.array([0.2, 0.9]), 8), atol=1e-7)
    g = jax.grad(lambda s: flow.tpd_sigmas(s, 8).sum())(0.5)
    assert float(g) > 0


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(sigma=1.2, num_frames=4), "sigma: expected values in"),
        (dict(sigma=0.5, num_frames=0), "num_frames: expected an integer >= 1, got 0"),
        (dict(sigma=0.5, num_frames=4, omega=0.0), r"omega: expected values in \(0.0, 1.5707"),
        (dict(sigma=0.5, num_frames=4, omega=2.0), "omega: expected values in"),
    ],
)
def test_bad_inputs(kwargs, match):
    with pytest.raises(ValueError, match=match):
        flow.tpd_sigmas(**kwargs)


def test_frame_sigmas_bad_shapes():
    with pytest.raises(ValueError, match=r"cond_mask: expected shape \[B, F\] with B = 2"):
        flow.tpd_frame_sigmas(jnp.array([0.1, 0.2]), jnp.zeros((3, 4), bool))
