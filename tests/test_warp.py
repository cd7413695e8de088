"""LongDWM's warp-guided trajectory control: trajectory -> poses (appendix A.1), the depth-free
warp (appendix A.2, eq. 9) and its Navier-Stokes inpainting."""

import numpy as np
import pytest

from jaxdrive.warp import camera_motion, depth_free_warp, inpaint_holes, plane_homography, trajectory_poses, warp_views

K = np.asarray([[100.0, 0.0, 50.0], [0.0, 100.0, 40.0], [0.0, 0.0, 1.0]], np.float32)
H, W = 80, 100
# a front camera: camera z forward = ego x, camera x right = ego -y, camera y down = ego -z
FRONT = np.asarray([[0, 0, 1, 1.5], [-1, 0, 0, 0], [0, -1, 0, 1.6], [0, 0, 0, 1]], np.float32)


def ramp_image():
    """A smooth image whose channels read off the pixel position: (u / W, v / H, 0.5)."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    return np.stack([u / W, v / H, np.full_like(u, 0.5)], axis=-1)


def translation(x, y, z):
    m = np.eye(4, dtype=np.float32)
    m[:3, 3] = (x, y, z)
    return m


def test_the_warp_at_the_identity_pose_returns_the_first_frame():
    image = np.random.default_rng(0).uniform(-1, 1, size=(H, W, 3)).astype(np.float32)
    warped, hole = depth_free_warp(image, K, np.eye(4, dtype=np.float32)[None], 10.0)
    assert not bool(hole.any())
    np.testing.assert_allclose(warped[0], image, atol=1e-5)


def test_a_forward_move_scales_about_the_principal_point_as_eq_9_says():
    """Worked number: d = 10 m, the camera 2 m forward (T = (0, 0, -2)). P_0 = (70, 40) back-projects
    to X = 10 K^-1 P_0 = (2, 0, 10), moves to (2, 0, 8) and projects to u = 100 * 2 / 8 + 50 = 75:
    the pixel 20 right of the centre is seen 25 right of it (d / (d - 2) = 1.25)."""
    hom = np.asarray(plane_homography(K, translation(0, 0, -2), 10.0))
    p = hom @ np.asarray([70.0, 40.0, 1.0])
    np.testing.assert_allclose(p[:2] / p[2], [75.0, 40.0], atol=1e-4)
    image = ramp_image()
    warped, hole = depth_free_warp(image, K, translation(0, 0, -2)[None], 10.0)
    np.testing.assert_allclose(warped[0, 40, 75, 0], 70.0 / W, atol=1e-5)  # reads the source at u = 70
    assert not bool(hole.any())  # moving forward, every target pixel has a source
    # the same motion from the ego's 2 m forward through the front camera's extrinsics
    motion = camera_motion(translation(2, 0, 0)[None], FRONT[None])[0, 0]
    np.testing.assert_allclose(motion, translation(0, 0, -2), atol=1e-5)


def test_moving_back_opens_holes_at_the_border_and_inpainting_fills_only_them():
    image = ramp_image() * 2 - 1
    warped, hole = depth_free_warp(image, K, translation(0, 0, 3)[None], 10.0)
    hole = np.asarray(hole[0])
    assert hole[0].all() and hole[-1].all() and hole[:, 0].all() and not hole[40, 50]
    filled = inpaint_holes(np.asarray(warped[0]), hole)
    np.testing.assert_array_equal(filled[~hole], np.asarray(warped[0])[~hole])
    assert np.abs(filled[hole] - 0).max() > 0.1 and np.isfinite(filled).all()
    # filled from the border of what is known: the red channel (u / W) keeps growing to the right
    assert filled[40, -1, 0] > filled[40, 0, 0]
    with pytest.raises(ValueError, match="holes: expected the shape"):
        inpaint_holes(np.asarray(warped[0]), hole[:-1])


def test_the_plane_behind_the_camera_is_all_hole():
    _, hole = depth_free_warp(ramp_image(), K, translation(0, 0, -12)[None], 10.0)
    assert bool(hole.all())


def test_the_spline_passes_through_the_points_with_the_tangent_heading():
    points = np.asarray([[0, 0], [5, 0.5], [10, 2], [14, 5], [16, 9]], np.float32)
    poses = trajectory_poses(points, 25)
    assert poses.shape == (25, 4, 4)
    np.testing.assert_allclose(poses[[0, 6, 12, 18, 24], :2, 3], points, atol=1e-4)  # frames 0, 6, ... 24
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-6)  # starts heading along x
    yaw = np.arctan2(poses[:, 1, 0], poses[:, 0, 0])
    assert np.all(np.diff(yaw) > 0) and yaw[-1] > 1.0  # a left turn
    step = np.diff(poses[:, :2, 3], axis=0)
    np.testing.assert_allclose(np.arctan2(step[:, 1], step[:, 0]), (yaw[1:] + yaw[:-1]) / 2, atol=0.05)
    rot = poses[:, :3, :3]
    np.testing.assert_allclose(rot @ np.swapaxes(rot, 1, 2), np.broadcast_to(np.eye(3), rot.shape), atol=1e-5)


def test_a_stop_holds_its_heading():
    poses = trajectory_poses([[0, 0], [3, 3], [3, 3]], 9, degree=1)
    np.testing.assert_allclose(poses[-1, :2, 3], [3, 3], atol=1e-6)
    np.testing.assert_allclose(np.arctan2(poses[-1, 1, 0], poses[-1, 0, 0]), np.pi / 4, atol=1e-6)


@pytest.mark.parametrize(
    "points, frames, times, match",
    [
        ([[0, 0]], 5, None, "points: expected"),
        ([[0, 0], [1, np.nan]], 5, None, "points: expected finite"),
        ([[0, 0, 0], [1, 1, 1]], 5, None, "points: expected"),
        ([[0, 0], [1, 1]], 0, None, "frames: expected"),
        ([[0, 0], [1, 1]], 5, [2, 1], "times: expected 2 strictly increasing"),
    ],
)
def test_trajectory_rejects_bad_points(points, frames, times, match):
    with pytest.raises(ValueError, match=match):
        trajectory_poses(points, frames, times=times)
    with pytest.raises(ValueError, match="degree: expected 1, 2 or 3, got 4"):
        trajectory_poses([[0, 0], [1, 1]], 5, degree=4)


@pytest.mark.slow(seconds=3)
def test_every_view_warps_with_its_own_extrinsics():
    """Two cameras, front and back, the ego 2 m forward: the front view zooms in (no holes), the
    back view zooms out (holes, filled)."""
    back = FRONT.copy()
    back[:3, :3] = np.asarray([[0, 0, -1], [1, 0, 0], [0, -1, 0]], np.float32)  # z backwards, x = ego +y
    first = np.stack([ramp_image(), ramp_image()]) * 2 - 1
    poses = np.stack([np.eye(4, dtype=np.float32), translation(2, 0, 0)])
    out = warp_views(first, np.stack([K, K]), np.stack([FRONT, back]), poses, 10.0, inpaint=False)
    assert out.shape == (2, 2, H, W, 3)
    np.testing.assert_allclose(out[:, 0], first, atol=1e-5)  # frame 0: the first frame
    _, front_hole = depth_free_warp(first[0], K, camera_motion(poses, FRONT[None])[0], 10.0)
    _, back_hole = depth_free_warp(first[1], K, camera_motion(poses, back[None])[0], 10.0)
    assert not bool(front_hole[1].any()) and bool(back_hole[1].any())
    filled = warp_views(first, np.stack([K, K]), np.stack([FRONT, back]), poses, 10.0)
    assert np.isfinite(filled).all() and np.abs(filled[1, 1][np.asarray(back_hole[1])]).max() > 0.1
    with pytest.raises(ValueError, match="depth: expected a positive"):
        warp_views(first, np.stack([K, K]), np.stack([FRONT, back]), poses, 0.0)
