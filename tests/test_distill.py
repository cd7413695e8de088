import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxdrive import flow


def _clip(batch=2, frames=7):
    # frame f of sample b holds the value 100 b + f everywhere
    vals = 100.0 * jnp.arange(batch)[:, None] + jnp.arange(frames)[None, :]
    return jnp.broadcast_to(vals[:, :, None, None, None], (batch, frames, 2, 3, 1))


def test_paper_geometry():
    # LongDWM appendix: 12 x 11 + 13 = 145 frames, 13 coarse frames, segments of 13
    idx = flow.coarse_indices(145, 13)
    np.testing.assert_array_equal(idx, np.arange(13) * 12)


def test_segments_share_their_end_frames():
    x = _clip()
    seg = flow.split_segments(x, 4)
    assert seg.shape == (4, 4, 2, 3, 1)
    np.testing.assert_array_equal(
        seg[:, :, 0, 0, 0], [[0, 1, 2, 3], [3, 4, 5, 6], [100, 101, 102, 103], [103, 104, 105, 106]]
    )
    sig = jnp.arange(14.0).reshape(2, 7)
    np.testing.assert_array_equal(flow.split_segments(sig, 4)[1], [3, 4, 5, 6])


def test_coarse_from_segments_round_trip_and_boundaries():
    x = _clip()
    seg = flow.split_segments(x, 4)
    for boundary in ("mean", "start", "end"):
        np.testing.assert_array_equal(flow.coarse_from_segments(seg, 2, boundary=boundary), flow.dense_to_coarse(x, 4))
    # make the two copies of coarse frame 3 disagree: segment 0 ends with 10, segment 1 starts with 20
    seg = seg.at[0, 3].set(10.0).at[1, 0].set(20.0)
    pick = lambda b: float(flow.coarse_from_segments(seg, 2, boundary=b)[0, 1, 0, 0, 0])
    assert (pick("mean"), pick("start"), pick("end")) == (15.0, 20.0, 10.0)
    # the same from each segment's first and last frame ([B, n, ...]), as the train step gets them
    first, last = seg[:, 0].reshape(2, 2, 2, 3, 1), seg[:, -1].reshape(2, 2, 2, 3, 1)
    for b in ("mean", "start", "end"):
        np.testing.assert_array_equal(
            flow.coarse_from_ends(first, last, boundary=b), flow.coarse_from_segments(seg, 2, boundary=b)
        )


def test_multiview_layout():
    x = jnp.broadcast_to(jnp.arange(5.0)[None, None, :, None, None, None], (1, 3, 5, 2, 2, 1))
    seg = flow.split_segments(x, 3)
    assert seg.shape == (2, 3, 3, 2, 2, 1)
    np.testing.assert_array_equal(flow.coarse_from_segments(seg, 1)[0, 0, :, 0, 0, 0], [0, 2, 4])


def test_distill_loss_value_and_stop_gradient():
    s = jnp.ones((2, 3, 2, 2, 1))
    t = jnp.zeros_like(s)
    assert float(flow.distill_loss(s, t)) == 1.0
    gs, gt = jax.grad(lambda a, b: flow.distill_loss(a, b), argnums=(0, 1))(s, t)
    assert float(jnp.abs(gs).sum()) > 0 and float(jnp.abs(gt).sum()) == 0.0
    cond = jnp.array([[True, False, False], [True, False, False]])
    s = s.at[:, 0].set(50.0)
    assert float(flow.distill_loss(s, t, cond_mask=cond)) == 1.0


def test_bad_inputs():
    with pytest.raises(ValueError, match=r"x frames: expected n \* \(segment_len - 1\) \+ 1 frames .* got 6"):
        flow.split_segments(_clip(frames=6), 4)
    with pytest.raises(ValueError, match="segment_len: expected an integer >= 2, got 1"):
        flow.coarse_indices(5, 1)
    with pytest.raises(ValueError, match="boundary: expected one of"):
        flow.coarse_from_segments(flow.split_segments(_clip(), 4), 2, boundary="left")
    with pytest.raises(ValueError, match="teacher: expected the shape of student"):
        flow.distill_loss(jnp.ones((1, 2, 1, 1, 1)), jnp.ones((1, 3, 1, 1, 1)))


# Every geometry is a new shape: jitted, each function compiles one program per shape, where eagerly
# each of its jnp calls compiles one.
split_segments = jax.jit(flow.split_segments, static_argnums=1)
coarse_from_segments = jax.jit(flow.coarse_from_segments, static_argnums=1, static_argnames="boundary")
dense_to_coarse = jax.jit(flow.dense_to_coarse, static_argnums=1)


@pytest.mark.slow(seconds=3)
@settings(max_examples=20)
@given(st.integers(2, 6), st.integers(1, 5), st.sampled_from(["mean", "start", "end"]))
def test_segments_round_trip_for_any_geometry(segment_len, num_segments, boundary):
    frames = num_segments * (segment_len - 1) + 1
    x = np.random.default_rng(frames).standard_normal((2, frames, 1, 2, 1)).astype(np.float32)
    seg = np.asarray(split_segments(x, segment_len))
    assert seg.shape == (2 * num_segments, segment_len, 1, 2, 1)
    np.testing.assert_array_equal(coarse_from_segments(seg, 2, boundary=boundary), dense_to_coarse(x, segment_len))
    # every dense frame appears in a segment at its own place
    np.testing.assert_array_equal(
        seg[1, :], x[0, segment_len - 1 : 2 * segment_len - 1] if num_segments > 1 else x[1, :segment_len]
    )
