"""Boxes, ego -> camera and projection (jaxdrive.geometry)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from jaxdrive.geometry import BOX_EDGES, box_corners, ego_to_camera, project_to_image

# Front camera at (1.5, 0, 1.6) in the ego frame: camera x (right) = ego -y, camera y (down) =
# ego -z, camera z (forward) = ego +x. Columns of R are the camera axes in ego coordinates.
FRONT_R = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], np.float32)
FRONT = np.eye(4, dtype=np.float32)
FRONT[:3, :3], FRONT[:3, 3] = FRONT_R, [1.5, 0.0, 1.6]

finite = st.floats(-50, 50, allow_nan=False, width=32)
size = st.floats(0.125, 20, allow_nan=False, width=32)
angle = st.floats(-6.25, 6.25, allow_nan=False, width=32)


def test_corners_of_a_known_box():
    box = np.array([1.0, 2.0, 3.0, 4.0, 2.0, 1.0, 0.0], np.float32)  # l=4 along x, w=2, h=1
    want = np.array(
        [
            [3, 3, 2.5],
            [-1, 3, 2.5],
            [-1, 1, 2.5],
            [3, 1, 2.5],  # bottom: FL, RL, RR, FR
            [3, 3, 3.5],
            [-1, 3, 3.5],
            [-1, 1, 3.5],
            [3, 1, 3.5],  # top
        ],
        np.float32,
    )
    np.testing.assert_allclose(box_corners(box), want, atol=1e-6)
    # yaw = 90 deg: the heading is +y, so "front-left" (+l/2 ahead, +w/2 left) is (-1, +2).
    box[6] = np.pi / 2
    got = np.asarray(box_corners(box))
    np.testing.assert_allclose(got[0], [0, 4, 2.5], atol=1e-5)
    np.testing.assert_allclose(got[2], [2, 0, 2.5], atol=1e-5)  # rear-right: (+1, -2)
    np.testing.assert_allclose(got[7], [2, 4, 3.5], atol=1e-5)  # front-right top: (+1, +2)


def test_box_edges_table():
    assert BOX_EDGES.shape == (12, 2)
    assert not BOX_EDGES.flags.writeable
    assert len({tuple(sorted(e)) for e in BOX_EDGES.tolist()}) == 12  # no edge twice
    # Every edge joins corners that differ along exactly one box axis; 4 edges per axis.
    corners = np.asarray(box_corners(np.array([0, 0, 0, 4.0, 2.0, 1.0, 0.3], np.float32)))
    lengths = np.linalg.norm(corners[BOX_EDGES[:, 0]] - corners[BOX_EDGES[:, 1]], axis=-1)
    np.testing.assert_allclose(np.sort(lengths), [1] * 4 + [2] * 4 + [4] * 4, rtol=1e-5)


_corners_jit = jax.jit(box_corners)


@given(finite, finite, finite, size, size, size, angle)
def test_yaw_is_a_rotation_about_the_centre(x, y, z, length, w, h, yaw):
    boxes = np.array([[x, y, z, length, w, h, 0.0], [x, y, z, length, w, h, yaw]], np.float32)
    flat, turned = np.asarray(_corners_jit(boxes), np.float64)
    cos, sin = np.cos(np.float32(yaw)), np.sin(np.float32(yaw))
    rot = np.array([[cos, -sin, 0], [sin, cos, 0], [0, 0, 1]])
    centre = np.array([x, y, z])
    atol = 1e-4 * (1 + np.abs(centre).max())
    np.testing.assert_allclose(turned, (flat - centre) @ rot.T + centre, atol=atol)
    np.testing.assert_allclose(turned.mean(axis=0), centre, atol=atol)


def test_corners_batch_and_jit():
    boxes = jnp.asarray(np.random.default_rng(0).normal(size=(2, 3, 5, 7)), jnp.float32)
    out = box_corners(boxes)
    assert out.shape == (2, 3, 5, 8, 3)
    np.testing.assert_allclose(out, jax.jit(box_corners)(boxes), atol=1e-6)


def test_ego_to_camera_front_camera():
    # 10 m ahead of the camera, 2 m to the left and 1 m above it (ego frame).
    point = np.array([[1.5 + 10, 2.0, 1.6 + 1.0]], np.float32)
    np.testing.assert_allclose(ego_to_camera(point, FRONT), [[-2.0, -1.0, 10.0]], atol=1e-5)


_rot_strategy = st.tuples(angle, angle, angle)


def _rotation(a, b, g):
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    rx = np.array([[1, 0, 0], [0, np.cos(g), -np.sin(g)], [0, np.sin(g), np.cos(g)]])
    return rz @ ry @ rx


_to_cam_jit = jax.jit(ego_to_camera)


@given(_rot_strategy, st.tuples(finite, finite, finite), st.integers(0, 2**31 - 1))
def test_ego_to_camera_inverts_cam_to_ego(angles, trans, seed):
    t = np.eye(4)
    t[:3, :3], t[:3, 3] = _rotation(*angles), trans
    cam_pts = np.random.default_rng(seed).uniform(-30, 30, size=(6, 3))
    ego_pts = cam_pts @ t[:3, :3].T + t[:3, 3]
    got = _to_cam_jit(jnp.asarray(ego_pts, jnp.float32), jnp.asarray(t, jnp.float32))
    np.testing.assert_allclose(got, cam_pts, atol=1e-3)


def test_ego_to_camera_broadcasts_batch_dims():
    pts = np.random.default_rng(1).normal(size=(2, 1, 4, 3)).astype(np.float32)
    mats = np.stack([np.eye(4, dtype=np.float32), FRONT, FRONT])[None]  # [1, 3, 4, 4]
    out = np.asarray(ego_to_camera(pts, mats))
    assert out.shape == (2, 3, 4, 3)
    np.testing.assert_allclose(out[1, 2], ego_to_camera(pts[1, 0], FRONT), atol=1e-6)
    np.testing.assert_allclose(out[0, 0], pts[0, 0], atol=1e-6)


K = np.array([[100.0, 0.0, 50.0], [0.0, 200.0, 60.0], [0.0, 0.0, 1.0]], np.float32)


def test_optical_axis_lands_on_principal_point():
    pts = np.array([[0.0, 0.0, 3.0], [0.0, 0.0, 70.0]], np.float32)
    pix, depth = project_to_image(pts, K)
    np.testing.assert_allclose(pix, [[50.0, 60.0], [50.0, 60.0]], atol=1e-5)
    np.testing.assert_allclose(depth, [3.0, 70.0])


def test_projection_worked_example():
    pix, depth = project_to_image(np.array([[1.0, 2.0, 4.0]], np.float32), K)
    # u = fx x / z + cx = 100 / 4 + 50 = 75 (column); v = fy y / z + cy = 400 / 4 + 60 = 160 (row)
    np.testing.assert_allclose(pix, [[75.0, 160.0]], atol=1e-5)
    np.testing.assert_allclose(depth, [4.0])


def test_projection_finite_values_and_grads_at_zero_depth():
    pts = jnp.array([[1.0, 2.0, 0.0], [1.0, 2.0, 5.0], [0.0, 0.0, -2.0]])

    def total(p):
        pix, depth = project_to_image(p, K)
        return jnp.sum(pix) + jnp.sum(depth)

    assert np.isfinite(np.asarray(project_to_image(pts, K)[0])).all()
    grad = jax.grad(total)(pts)
    assert np.isfinite(np.asarray(grad)).all()
    # d u / d x = fx / z at the regular point
    np.testing.assert_allclose(grad[1, 0], 100.0 / 5.0, rtol=1e-5)


@pytest.mark.parametrize(
    "call, name",
    [
        (lambda: box_corners(np.zeros((3, 6))), "boxes"),
        (lambda: box_corners(np.float32(1.0)), "boxes"),
        (lambda: ego_to_camera(np.zeros((4, 2)), np.eye(4)), "points"),
        (lambda: ego_to_camera(np.zeros(3), np.eye(4)), "points"),
        (lambda: ego_to_camera(np.zeros((4, 3)), np.eye(3)), "cam_to_ego"),
        (lambda: ego_to_camera(np.zeros((2, 4, 3)), np.zeros((3, 4, 4))), "cam_to_ego"),
        (lambda: project_to_image(np.zeros((4, 4)), K), "points_cam"),
        (lambda: project_to_image(np.zeros((4, 3)), np.eye(4)), "intrinsics"),
        (lambda: project_to_image(np.zeros((2, 4, 3)), np.zeros((5, 3, 3))), "intrinsics"),
    ],
)
def test_bad_inputs_name_the_argument(call, name):
    with pytest.raises(ValueError, match=rf"^{name}: expected"):
        call()
