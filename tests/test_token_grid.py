"""The grid contrast of jaxdrive.eval.token_grid: 1 without a grid, more with one, on its lines only."""

import numpy as np
import pytest

from jaxdrive.eval.token_grid import grid_contrast


def _ramp(frames=3, h=32, w=48):
    """A smooth image: every neighbour step the same, so any grid's contrast is exactly 1."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    img = np.repeat(((x + y) / (h + w))[..., None], 3, axis=-1)
    return np.broadcast_to(img, (frames, h, w, 3)).copy()


def test_a_smooth_image_has_no_grid():
    np.testing.assert_allclose(grid_contrast(_ramp(), 8), 1.0, rtol=1e-12)


def test_blocks_of_the_period_show_on_their_edges_and_not_between():
    # a ramp plus a jump of 0.1 at every 8th column and row: the steps on the edges are
    # 1/80 + 0.1 (the ramp's step is 1/80), elsewhere 1/80, a worked contrast of 9
    video = _ramp(h=32, w=48)
    rows, cols = np.mgrid[0:32, 0:48]
    video += (0.1 * (rows // 8 + cols // 8))[None, :, :, None]
    got = grid_contrast(video, 8)
    np.testing.assert_allclose(got, (1 / 80 + 0.1) / (1 / 80), rtol=1e-9)
    # the same grid read at the codec's 4-pixel edges between the blocks' edges: no contrast
    # there but the ramp's (the jumps now count among the other steps, which lowers it below 1)
    assert np.all(grid_contrast(video, 8, offset=3) < 1.0)
    # frames are scored one by one: a clean frame beside a blocky one stays at 1
    mixed = np.stack([_ramp(1)[0], video[0]])
    c = grid_contrast(mixed[None], 8)
    assert c.shape == (2,) and c[0] == pytest.approx(1.0) and c[1] == pytest.approx(9.0)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"video": np.zeros((4, 4, 3))}, "video: expected shape [..., F, H, W, C]"),
        ({"period": 1}, "period: expected"),
        ({"offset": 8}, "offset: expected a pixel step inside the period, 0 to 7, got 8"),
        ({"video": np.zeros((1, 8, 8, 3))}, "video: expected frames of more than period = 8 pixels a side"),
    ],
)
def test_bad_input_names_the_argument(kwargs, message):
    args = {"video": _ramp(), "period": 8, **kwargs}
    with pytest.raises(ValueError) as e:
        grid_contrast(**args)
    assert message in str(e.value)
