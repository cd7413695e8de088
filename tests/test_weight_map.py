"""STAGE's foreground-weighted loss map (jaxdrive.flow.weights)."""

import itertools
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxdrive.flow.weights import _hull_mask, foreground_weight_map

IMAGE_HW, MAP_HW = (80, 120), (8, 8)  # each map pixel covers 10 rows x 15 columns
K = np.array([[40.0, 0.0, 60.0], [0.0, 40.0, 40.0], [0.0, 0.0, 1.0]], np.float32)
# Camera axes in ego coordinates (columns): x right = -y_ego, y down = -z_ego, z forward = +x_ego.
FRONT_R = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], np.float32)


def cam(yaw=0.0, t=(0.0, 0.0, 0.0)):
    """cam_to_ego of a camera at ``t`` looking along ego heading ``yaw``."""
    rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    m = np.eye(4, dtype=np.float32)
    m[:3, :3], m[:3, 3] = rz @ FRONT_R, t
    return m


def inputs(boxes, valid=None, cams=None):
    """Boxes ``[N, 7]`` -> one batch, one frame; ``cams`` a list of views (default: front)."""
    boxes = np.asarray(boxes, np.float32).reshape(1, 1, -1, 7)
    valid = np.ones(boxes.shape[:3], bool) if valid is None else np.reshape(valid, boxes.shape[:3])
    cams = np.stack(cams or [cam()])[None]
    return boxes, valid, np.broadcast_to(K, cams.shape[:2] + (3, 3)), cams


wmap = jax.jit(partial(foreground_weight_map, map_hw=MAP_HW, image_hw=IMAGE_HW))


# ----------------------------------------------------------------------------------------------
# Independent numpy reference: corners from sign combinations, edges = corner pairs that differ
# in one sign, membership = "inside some triangle of the vertices" (Caratheodory), float64.


def ref_object_mask(box, K_, cam_to_ego, near):
    x, y, z, length, w, h, yaw = map(float, box)
    signs = np.array(list(itertools.product([-0.5, 0.5], repeat=3)))
    local = signs * [length, w, h]
    rot = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    corners = local @ rot.T + [x, y, z]
    r, t = cam_to_ego[:3, :3].astype(np.float64), cam_to_ego[:3, 3].astype(np.float64)
    pc = (corners - t) @ r
    verts = [p for p in pc if p[2] >= near]
    for a, b in itertools.combinations(range(8), 2):
        if np.sum(signs[a] != signs[b]) == 1 and (pc[a, 2] >= near) != (pc[b, 2] >= near):
            s = (near - pc[a, 2]) / (pc[b, 2] - pc[a, 2])
            verts.append(pc[a] + s * (pc[b] - pc[a]))
    mask = np.zeros(MAP_HW, bool)
    if len(verts) < 3:
        return mask
    v = np.array(verts)
    uv = (v @ K_.astype(np.float64).T)[:, :2] / v[:, 2:3]
    hh, ww = MAP_HW
    qu = (np.arange(ww) + 0.5) * IMAGE_HW[1] / ww
    qv = (np.arange(hh) + 0.5) * IMAGE_HW[0] / hh
    q = np.stack(np.meshgrid(qu, qv), -1).reshape(-1, 2)  # [h*w, 2] as (u, v)
    return in_some_triangle(uv, q).reshape(MAP_HW)


def in_some_triangle(pts, q):
    """Closed convex-hull membership of points ``q [..., 2]``: inside some triangle of ``pts``."""

    def cross(a, b):  # (a - q) x (b - q)
        return (a[0] - q[..., 0]) * (b[1] - q[..., 1]) - (a[1] - q[..., 1]) * (b[0] - q[..., 0])

    mask = np.zeros(q.shape[:-1], bool)
    for a, b, c in itertools.combinations(np.asarray(pts, np.float64), 3):
        det = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
        if abs(det) < 1e-9:
            continue
        # q is in the closed triangle iff it is on the inner side of all three edges.
        s = np.sign(det)
        mask |= (s * cross(a, b) >= 0) & (s * cross(b, c) >= 0) & (s * cross(c, a) >= 0)
    return mask


def ref_map(boxes, valid, intr, cams, k=1.0, c=0.5, near=0.1):
    bsz, frames, _, _ = boxes.shape
    views = cams.shape[1]
    out = np.zeros((bsz, views, frames) + MAP_HW)
    hw = MAP_HW[0] * MAP_HW[1]
    for b, v, f in itertools.product(range(bsz), range(views), range(frames)):
        w = np.full(MAP_HW, 1.0 / hw**c)
        fg = np.zeros(MAP_HW, bool)
        for n in np.flatnonzero(valid[b, f]):
            mask = ref_object_mask(boxes[b, f, n], intr[b, v], cams[b, v], near)
            if mask.any():
                wn = k / mask.sum() ** c
                w = np.where(mask & fg, np.maximum(w, wn), np.where(mask, wn, w))
                fg |= mask
        out[b, v, f] = w / w.mean()
    return out


# ----------------------------------------------------------------------------------------------


@given(st.floats(0.1, 10.0), st.floats(0.0, 2.0))
def test_worked_example_one_box_one_camera(k, c):
    # Box 10 m ahead, centred on the optical axis: its near face (x = 9, |y| <= 3, |z| <= 2)
    # spans u in 60 +- 40 * 3 / 9 = [46.7, 73.3], v in 40 +- 40 * 2 / 9 = [31.1, 48.9]; the far
    # face projects inside it. Map pixel centres are at u = 7.5, 22.5, 37.5, ... and
    # v = 5, 15, 25, ... image pixels, so the columns 3, 4 (u = 52.5, 67.5) and rows 3, 4
    # (v = 35, 45) are inside: p = 4 of h * w = 64.
    out = np.asarray(wmap(*inputs([[10, 0, 0, 2, 6, 4, 0]]), k=k, c=c))[0, 0, 0]
    fg = np.zeros(MAP_HW, bool)
    fg[3:5, 3:5] = True
    fg_w, bg_w = out[fg], out[~fg]
    np.testing.assert_allclose(fg_w, fg_w[0], rtol=1e-6)
    np.testing.assert_allclose(bg_w, bg_w[0], rtol=1e-6)
    np.testing.assert_allclose(fg_w[0] / bg_w[0], k * (64 / 4) ** c, rtol=1e-4)
    np.testing.assert_allclose(out.mean(), 1.0, rtol=1e-5)


@pytest.mark.parametrize(
    "box, valid",
    [
        ([-10, 0, 0, 4, 2, 2, 0], True),  # fully behind the camera
        ([0.05, 0, 0, 0.02, 1, 1, 0], True),  # in front of the camera but before the near plane
        ([10, 40, 0, 4, 2, 2, 0], True),  # in front, far outside the field of view
        ([10, 0, 0, 0, 0, 0, 0], True),  # zero-size box
        ([10, 0, 0, 4, 2, 0, 0.3], True),  # flat box at camera height: projects to a line
        ([10, 0, 0, 4, 2, 2, 0], False),  # visible but invalid
        ([np.nan] * 7, False),  # invalid padding with garbage
    ],
)
def test_boxes_that_contribute_nothing_give_ones(box, valid):
    boxes, _, intr, cams = inputs([box, [np.inf] * 7], valid=[valid, False])
    out = np.asarray(wmap(boxes, np.array([[[valid, False]]]), intr, cams))
    np.testing.assert_array_equal(out, np.ones_like(out))


def test_no_valid_boxes_gives_ones():
    boxes = np.random.default_rng(0).normal(size=(2, 3, 5, 7)).astype(np.float32)
    intr, cams = np.broadcast_to(K, (2, 4, 3, 3)), np.broadcast_to(cam(), (2, 4, 4, 4))
    fn = jax.jit(partial(foreground_weight_map, map_hw=(4, 6), image_hw=IMAGE_HW))
    out = np.asarray(fn(boxes, np.zeros((2, 3, 5), bool), intr, cams))
    assert out.shape == (2, 4, 3, 4, 6) and out.dtype == np.float32
    np.testing.assert_array_equal(out, 1.0)


def test_box_straddling_the_near_plane():
    # x in [-1, 3]: the rear half is behind the camera, the front half is visible on the left.
    box = [1, 3, 0, 4, 2, 2, 0]
    out = np.asarray(wmap(*inputs([box])))[0, 0, 0]
    assert np.isfinite(out).all()
    fg = out > out.min() * 1.5
    assert 0 < fg.sum() < fg.size
    assert fg[:, :4].sum() == fg.sum()  # left half of the image (ego +y is camera -x)
    np.testing.assert_allclose(out, ref_map(*inputs([box]))[0, 0, 0], rtol=1e-5)


@pytest.mark.parametrize(
    "box, t",
    [
        ([10, 0, -1, 3, 2, 2, 0.0], (0, 0, 0)),  # top face exactly at camera height: edge-on
        ([10, 0, 0, 3, 2, 2, 0.0], (0, 0, 1.0)),  # top face edge-on from a raised camera
        ([0.5, 0, 0, 4, 4, 4, 0.2], (0, 0, 0)),  # camera inside the box: everything is fg
        ([0.2, 0.5, 0.3, 0.25, 30, 1, 0.0], (0, 0, 0)),  # thin wall near the near plane: huge uv
        ([6, 2, 0.5, 4, 2, 1.5, 2.0], (1.5, 0, 1.6)),
    ],
)
def test_special_cases_match_reference(box, t):
    args = inputs([box], cams=[cam(0.0, t)])
    np.testing.assert_allclose(wmap(*args), ref_map(*args), rtol=1e-5)


# Two batches, two views (front and a left-looking camera), two frames, three boxes each.
_box = st.tuples(
    st.floats(-5, 30),
    st.floats(-12, 12),
    st.floats(-1.5, 2.5),
    st.floats(0.3, 8),
    st.floats(0.3, 4),
    st.floats(0.3, 3),
    st.floats(-3.2, 3.2),
)


@settings(max_examples=25)
@given(
    st.lists(_box, min_size=12, max_size=12),
    st.lists(st.booleans(), min_size=12, max_size=12),
    st.floats(0.5, 4.0),
    st.floats(0.0, 1.5),
)
def test_matches_reference_on_random_scenes(boxes, valid, k, c):
    boxes = np.array(boxes, np.float32).reshape(2, 2, 3, 7)
    valid = np.array(valid).reshape(2, 2, 3)
    cams = np.stack(
        [[cam(0.0, (1.5, 0, 1.6)), cam(1.0, (1.0, 0.5, 1.6))], [cam(-0.5, (0, 0, 1.0)), cam(3.0, (-1.0, 0, 1.8))]]
    )
    intr = np.broadcast_to(K, (2, 2, 3, 3))
    got = np.asarray(wmap(boxes, valid, intr, cams, k=k, c=c))
    np.testing.assert_allclose(got, ref_map(boxes, valid, intr, cams, k=k, c=c), rtol=2e-5)
    np.testing.assert_allclose(got.mean(axis=(-2, -1)), 1.0, rtol=1e-5)


NEAR_BIG = [8, 4, 0, 2, 6, 4, 0]  # 7 m to its face: 3 x 2 map pixels, left
FAR_SMALL = [14, -6, 0, 2, 4, 4, 0]  # 13 m to its face: 1 x 2 map pixels, right
BEHIND_BIG = [25, -6, 0, 4, 20, 10, 0]  # 2 x 2 map pixels, covering FAR_SMALL's


def test_smaller_object_gets_larger_weight():
    out = np.asarray(wmap(*inputs([NEAR_BIG, FAR_SMALL])))[0, 0, 0]
    near_mask = ref_object_mask(NEAR_BIG, K, cam(), 0.1)
    far_mask = ref_object_mask(FAR_SMALL, K, cam(), 0.1)
    assert 0 < far_mask.sum() < near_mask.sum() and not (near_mask & far_mask).any()
    bg = out[~(near_mask | far_mask)]
    assert out[far_mask].min() > out[near_mask].max() > bg.max()


def test_overlap_takes_the_weight_of_the_smallest_object():
    both = np.asarray(wmap(*inputs([FAR_SMALL, BEHIND_BIG])))[0, 0, 0]
    a = np.asarray(wmap(*inputs([FAR_SMALL])))[0, 0, 0]
    b = np.asarray(wmap(*inputs([BEHIND_BIG])))[0, 0, 0]
    small = ref_object_mask(FAR_SMALL, K, cam(), 0.1)
    big = ref_object_mask(BEHIND_BIG, K, cam(), 0.1)
    assert (small & big).any() and (big & ~small).any()
    # Relative to the background (the minimum of each map), the union is the pointwise max.
    np.testing.assert_allclose(both / both.min(), np.maximum(a / a.min(), b / b.min()), rtol=1e-5)
    assert (both[small] / both.min() > both[big & ~small].max() / both.min()).all()


@given(st.permutations(range(4)))
def test_invariant_to_box_order(perm):
    boxes = np.array([NEAR_BIG, FAR_SMALL, BEHIND_BIG, [12, 1, 0.5, 3, 2, 2, 0.7]], np.float32)
    valid = np.array([True, True, True, False])
    ref = np.asarray(wmap(*inputs(boxes, valid)))
    got = np.asarray(wmap(*inputs(boxes[list(perm)], valid[list(perm)])))
    np.testing.assert_array_equal(got, ref)


@pytest.mark.slow(seconds=11)
def test_jit_matches_eager_and_gradient_is_stopped():
    boxes, valid, intr, cams = inputs([NEAR_BIG, FAR_SMALL, BEHIND_BIG], cams=[cam(), cam(0.8)])
    eager = foreground_weight_map(boxes, valid, intr, cams, map_hw=MAP_HW, image_hw=IMAGE_HW, k=2.0, c=0.7)
    jitted = wmap(boxes, valid, intr, cams, k=2.0, c=0.7)
    np.testing.assert_allclose(eager, jitted, rtol=1e-6)
    grad = jax.grad(lambda bx: jnp.sum(wmap(bx, valid, intr, cams) ** 2))(jnp.asarray(boxes))
    np.testing.assert_array_equal(grad, 0.0)


def _good():
    return dict(
        boxes=np.zeros((2, 3, 4, 7), np.float32),
        box_valid=np.ones((2, 3, 4), bool),
        intrinsics=np.broadcast_to(K, (2, 5, 3, 3)),
        cam_to_ego=np.broadcast_to(cam(), (2, 5, 4, 4)),
        map_hw=(4, 6),
        image_hw=(80, 120),
    )


@pytest.mark.parametrize(
    "name, value",
    [
        ("boxes", np.zeros((2, 3, 4, 6))),
        ("boxes", np.zeros((3, 4, 7))),
        ("box_valid", np.ones((2, 3, 5), bool)),
        ("box_valid", np.ones((2, 3, 4), np.float32)),
        ("intrinsics", np.zeros((1, 5, 3, 3))),
        ("intrinsics", np.zeros((2, 5, 4, 4))),
        ("cam_to_ego", np.zeros((2, 4, 4, 4))),
        ("cam_to_ego", np.zeros((2, 5, 3, 4))),
        ("map_hw", (0, 6)),
        ("map_hw", (4.0, 6)),
        ("map_hw", 4),
        ("image_hw", (80, 120, 3)),
        ("image_hw", (80, -1)),
        ("k", 0.0),
        ("k", -1.0),
        ("c", -0.5),
        ("near", 0.0),
    ],
)
def test_bad_inputs_name_the_argument(name, value):
    args = _good()
    args[name] = value
    kwargs = {key: args.pop(key) for key in ("map_hw", "image_hw", "k", "c", "near") if key in args}
    with pytest.raises(ValueError, match=rf"^{name}(\[\d\])?: expected"):
        foreground_weight_map(*args.values(), **kwargs)


def test_collinear_projection_covers_no_pixel():
    # Flat boxes at camera height project onto the row v = c_y = 40 (exactly, in float32, for
    # these depths); with 5 map rows the centres of row 2 lie exactly on that line, so a hull
    # test that let degenerate (zero-area) sets through would mark pixels of that row.
    boxes, valid, intr, cams = inputs([[10, 0, 0, 4, 2, 0, 0], [12, 3, 0, 2, 2, 0, 0]])
    fn = jax.jit(partial(foreground_weight_map, map_hw=(5, 12), image_hw=IMAGE_HW))
    out = fn(boxes, valid, intr, cams)
    np.testing.assert_array_equal(out, 1.0)


# The hull test on its own, on point sets harder than projected boxes: many duplicates,
# exactly collinear points (integer coordinates, exact in float32) and random validity.
_hull_jit = jax.jit(_hull_mask)


def ref_hull_mask(pts, valid, qu, qv):
    return in_some_triangle(pts[valid], np.stack(np.meshgrid(qu, qv), -1).astype(np.float64))


@given(st.integers(0, 2**31 - 1), st.integers(1, 4), st.sampled_from(["plane", "row", "diagonal"]))
def test_hull_mask_exact_on_integer_points(seed, spread, layout):
    rng = np.random.default_rng(seed)
    pts = rng.integers(-spread, spread + 1, size=(12, 2)).astype(np.float32)
    if layout == "row":  # all on one grid row: a zero-area hull, which covers nothing
        pts[:, 1] = 1.0
    elif layout == "diagonal":
        pts[:, 1] = pts[:, 0]
    valid = rng.random(12) < 0.7
    grid = np.arange(-10, 11, dtype=np.float32) / 2  # integers and half-integers: on the edges
    got = np.asarray(_hull_jit(pts, valid, grid, grid))
    np.testing.assert_array_equal(got, ref_hull_mask(pts, valid, grid, grid))


@given(st.integers(0, 2**31 - 1))
def test_hull_mask_with_near_duplicates_and_points_on_edges(seed):
    rng = np.random.default_rng(seed)
    base = rng.uniform(-50, 50, size=(6, 2))
    t = rng.uniform(0, 1, size=(3, 1))
    on_edges = base[[0, 1, 2]] + t * (base[[1, 2, 3]] - base[[0, 1, 2]])  # on segments
    near_dup = base[[0, 1, 3, 4]] + rng.normal(scale=1e-6, size=(4, 2))
    pts = np.concatenate([base, on_edges, near_dup, base[:1]]).astype(np.float32)
    pts = pts[rng.permutation(14)]
    qu, qv = rng.uniform(-60, 60, size=16), rng.uniform(-60, 60, size=12)
    ones = np.ones(14, bool)
    got = np.asarray(_hull_jit(pts, ones, qu.astype(np.float32), qv.astype(np.float32)))
    np.testing.assert_array_equal(got, ref_hull_mask(pts, ones, qu, qv))


@pytest.mark.parametrize(
    "pts",
    [
        [[0, 0], [1, 0], [3, 0]],  # collinear, grid points on the line
        [[1, 1], [1, 1], [1, 1]],  # one point repeated
        [[0, 0], [2, 2]],  # two points
        [[1, 0]],
    ],
)
def test_hull_mask_degenerate_sets_are_empty(pts):
    pts = np.asarray(pts, np.float32)
    grid = np.arange(-2, 4, dtype=np.float32)
    assert not np.asarray(_hull_jit(pts, np.ones(len(pts), bool), grid, grid)).any()
