import jax.numpy as jnp
import numpy as np
import pytest

from jaxdrive import flow


def test_conditions_anchors_and_generated_frames():
    sigma = jnp.array([0.8, 0.4])
    cond = jnp.array([[True, False, False, False], [True, True, False, False]])
    anchor = jnp.array([[False, False, False, True], [True, False, False, True]])  # [1, 0] is also a condition
    out = flow.frame_sigmas(sigma, cond, anchor_mask=anchor, anchor_slope=0.5)
    np.testing.assert_allclose(out, [[0.0, 0.8, 0.8, 0.4], [0.0, 0.0, 0.4, 0.2]], atol=1e-7)


def test_tpd_ranks_generated_frames_only():
    sigma = jnp.array([0.6])
    cond = jnp.array([[True, False, False, False, False]])
    anchor = jnp.array([[False, False, False, False, True]])
    out = flow.frame_sigmas(sigma, cond, anchor_mask=anchor, tpd=True)
    np.testing.assert_allclose(out[0, 1:4], flow.tpd_sigmas(0.6, 3), atol=1e-7)
    assert float(out[0, 4]) == pytest.approx(0.6 * 0.5)


def test_schedule_per_step():
    base = flow.sampling_sigmas(4)
    cond = jnp.array([[True, False, False]])
    sched = flow.frame_schedule(base, cond, tpd=True)
    assert sched.shape == (5, 1, 3)
    np.testing.assert_array_equal(sched[:, 0, 0], 0.0)
    np.testing.assert_array_equal(sched[0, 0, 1:], 1.0)
    np.testing.assert_array_equal(sched[-1], 0.0)
    assert bool(jnp.all(jnp.diff(sched, axis=0) <= 0))
    for i in range(5):
        np.testing.assert_allclose(sched[i, 0, 1:], flow.tpd_sigmas(base[i], 2), atol=1e-7)


def test_bad_inputs():
    with pytest.raises(ValueError, match=r"anchor_mask: expected shape \[2, 3\], got \[2, 4\]"):
        flow.frame_sigmas(jnp.ones(2), jnp.zeros((2, 3), bool), anchor_mask=jnp.zeros((2, 4), bool))
    with pytest.raises(ValueError, match=r"cond_mask: expected shape \[2, \*\], got \[3, 3\]"):
        flow.frame_sigmas(jnp.ones(2), jnp.zeros((3, 3), bool))
    with pytest.raises(ValueError, match="base_sigmas: expected values in"):
        flow.frame_schedule(jnp.array([1.5, 0.0]), jnp.zeros((1, 2), bool))
