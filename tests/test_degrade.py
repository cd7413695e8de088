import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from jaxdrive import flow


def _x(shape=(2, 3, 8, 12, 4)):
    return jax.random.normal(jax.random.PRNGKey(0), shape)


def test_keep_all_is_identity():
    x = _x()
    np.testing.assert_allclose(flow.dct_lowpass(x, 1.0), x, atol=1e-5)


def test_smooth_content_survives_and_fine_detail_goes():
    h, w = 8, 12
    r, c = jnp.arange(h)[:, None], jnp.arange(w)[None, :]
    smooth = jnp.cos(jnp.pi * (r + 0.5) / h) * jnp.ones((1, w))  # DCT-II basis k = (1, 0)
    # DCT-II basis k = (h - 1, w - 1): the finest pattern, beyond any keep ratio < 1
    fine = jnp.cos(jnp.pi * (h - 1) * (r + 0.5) / h) * jnp.cos(jnp.pi * (w - 1) * (c + 0.5) / w)
    x = (smooth + fine)[None, None, :, :, None]
    out = flow.dct_lowpass(x, 0.5)
    np.testing.assert_allclose(out[0, 0, :, :, 0], smooth, atol=1e-5)


def test_energy_never_grows_and_per_sample_ratio():
    x = _x()
    full = float(jnp.sum(x**2))
    e = [float(jnp.sum(flow.dct_lowpass(x, r) ** 2)) for r in (0.1, 0.3, 0.6, 1.0)]
    assert all(a <= b + 1e-3 for a, b in zip(e, e[1:])) and e[-1] == pytest.approx(full, rel=1e-5)
    per = flow.dct_lowpass(x, jnp.array([0.25, 1.0]))
    np.testing.assert_allclose(per[0], flow.dct_lowpass(x, 0.25)[0], atol=1e-6)
    np.testing.assert_allclose(per[1], x[1], atol=1e-5)


def test_only_masked_frames_change():
    x = _x()
    mask = jnp.array([[True, False, False], [False, False, True]])
    out = flow.degrade_frames(x, mask, 0.25)
    np.testing.assert_array_equal(out[0, 1:], x[0, 1:])
    np.testing.assert_array_equal(out[1, :2], x[1, :2])
    assert float(jnp.abs(out[0, 0] - x[0, 0]).max()) > 0.1
    np.testing.assert_allclose(jax.jit(flow.degrade_frames)(x, mask, 0.25), out, atol=1e-6)


def test_bad_inputs():
    x = _x()
    with pytest.raises(ValueError, match=r"keep_ratio: expected values in \(0.0, 1.0\], got 0"):
        flow.dct_lowpass(x, 0.0)
    with pytest.raises(ValueError, match=r"keep_ratio: expected shape \[2\], got \[3\]"):
        flow.dct_lowpass(x, jnp.ones(3) * 0.5)
    with pytest.raises(ValueError, match=r"frame_mask: expected shape \[2, 3\], got \[2, 2\]"):
        flow.degrade_frames(x, jnp.zeros((2, 2), bool), 0.5)


def test_dct_matrix_is_the_orthonormal_dct_ii():
    from jax.scipy.fft import dct

    from jaxdrive.flow.degrade import dct_matrix

    v = jax.random.normal(jax.random.PRNGKey(3), (11,))
    np.testing.assert_allclose(dct_matrix(11) @ v, dct(v, type=2, norm="ortho"), atol=1e-5)
    np.testing.assert_allclose(dct_matrix(11) @ dct_matrix(11).T, np.eye(11), atol=1e-6)


@pytest.mark.slow(seconds=3)
@given(st.floats(0.01, 1.0), st.integers(0, 1000))
def test_lowpass_is_a_projection(keep, seed):
    x = jax.random.normal(jax.random.PRNGKey(seed), (1, 2, 6, 10, 3))
    once = flow.dct_lowpass(x, keep)
    np.testing.assert_allclose(flow.dct_lowpass(once, keep), once, atol=2e-5)
    # what it removes is orthogonal to what it keeps
    assert abs(float(jnp.sum(once * (x - once)))) < 1e-3
