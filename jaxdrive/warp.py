"""LongDWM's warp-guided trajectory control (LongDWM [2506.01546v1] sec. 3.4, appendix A).

- :func:`trajectory_poses` (appendix A.1): a few 2D trajectory points become a dense ego pose
  per frame, by an interpolating B-spline (scipy's) through the points, with the heading taken
  from the curve's tangent ("the camera plane is always perpendicular to the trajectory curve").
- :func:`camera_motion`: each camera's own motion ``[R_t, T_t]`` (camera 0 -> camera at t) from
  the ego poses and its extrinsics: ``inv(E) inv(M_t) E`` for camera-to-ego ``E`` and the ego
  pose ``M_t`` (ego at t -> ego at 0).
- :func:`depth_free_warp` (appendix A.2, eq. 9): every pixel of the first frame at one depth
  ``d``, back-projected with ``K^-1``, moved by ``[R_t, T_t]`` and projected with ``K``. All
  pixels on the plane ``z = d`` of camera 0 make eq. 9 the homography
  ``H_t = K (R_t + T_t e3^T / d) K^-1``, so the warp is a jitted *gather*: each target pixel
  reads the first frame at ``H_t^-1 p`` (bilinear), over a batch of poses. Target pixels with no
  source (outside the first frame, or the plane behind the camera) are holes.
- :func:`inpaint_holes`: the holes filled by Navier-Stokes inpainting (OpenCV's ``cv2.inpaint``
  with ``INPAINT_NS``, Bertalmio et al. 2001, the paper's choice), on the host.

Conventions (``DESIGN.md``): ego frame x forward, y left, z up; camera frame x right, y down, z
forward; pixel ``(u, v)`` = (column, row), with pixel centres at integers (OpenCV's).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.validate import check_trailing_shape


def trajectory_poses(points, frames: int, *, times=None, degree: int = 3) -> np.ndarray:
    """Ego poses ``[frames, 4, 4]`` (each frame's ego in the first frame's ego frame) along the
    trajectory ``points [K, 2]`` ((x forward, y left) metres in the first frame's ego frame, the
    first usually (0, 0)), which the ego passes at frames ``times [K]`` (default evenly from 0
    to ``frames - 1``). LongDWM [2506.01546v1] appendix A.1: an interpolating B-spline of degree
    ``min(degree, K - 1)`` (``scipy.interpolate.make_interp_spline``) through the points, leaving
    the first along the ego's x axis (frame 0's pose is the identity); the heading is the
    tangent's direction, held where the ego stands still (under 1 cm a frame: a stop)."""
    from scipy.interpolate import make_interp_spline

    pts = np.asarray(points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2 or pts.shape[0] < 2:
        raise ValueError(f"points: expected [K, 2] trajectory points with K >= 2, got shape {list(pts.shape)}")
    if not np.all(np.isfinite(pts)):
        raise ValueError(f"points: expected finite values, got {pts.tolist()}")
    if int(frames) < 1:
        raise ValueError(f"frames: expected at least 1, got {frames}")
    t = np.linspace(0.0, frames - 1, len(pts)) if times is None else np.asarray(times, np.float64)
    if t.shape != (len(pts),) or not np.all(np.diff(t) > 0):
        raise ValueError(
            f"times: expected {len(pts)} strictly increasing frame times, got {np.asarray(times).tolist()}"
        )
    if degree not in (1, 2, 3):
        raise ValueError(f"degree: expected 1, 2 or 3, got {degree}")
    k = min(degree, len(pts) - 1)
    # the points are in the first frame's ego frame, so the ego heads along x at the start: the
    # spline leaves the first point along x (at the first segment's forward speed); natural end
    start = [(1, np.asarray([(pts[1, 0] - pts[0, 0]) / (t[1] - t[0]), 0.0]))]
    bc = None if k == 1 else (start, None) if k == 2 else (start, [(2, np.zeros(2))])
    spline = make_interp_spline(t, pts, k=k, bc_type=bc)
    s = np.clip(np.arange(frames, dtype=np.float64), t[0], t[-1])
    xy, dxy = spline(s), spline.derivative()(s)
    speed = np.hypot(dxy[:, 0], dxy[:, 1])
    yaw = np.arctan2(dxy[:, 1], dxy[:, 0])
    # below 1 cm a frame the tangent is the spline's ringing about a standstill, not a heading
    moving = speed > 1e-2
    if not moving.any():
        yaw[:] = 0.0
    else:  # standing still: keep the last heading (the first one before the ego moves)
        idx = np.where(moving, np.arange(frames), -1)
        idx = np.maximum.accumulate(idx)
        idx = np.where(idx < 0, np.argmax(moving), idx)
        yaw = yaw[idx]
    poses = np.tile(np.eye(4), (frames, 1, 1))
    c, sn = np.cos(yaw), np.sin(yaw)
    poses[:, 0, 0], poses[:, 0, 1], poses[:, 1, 0], poses[:, 1, 1] = c, -sn, sn, c
    poses[:, :2, 3] = xy
    return poses.astype(np.float32)


def camera_motion(ego_poses, cam_to_ego):
    """``[R_t, T_t]`` of each camera: ``[..., V, F, 4, 4]`` mapping camera-0 coordinates to
    camera-t coordinates, ``inv(E) inv(M_t) E`` for ``cam_to_ego [..., V, 4, 4]`` (``E``) and
    ``ego_poses [..., F, 4, 4]`` (``M_t``: ego at t -> ego at frame 0)."""
    check_trailing_shape("ego_poses", ego_poses, (None, 4, 4), "[..., F, 4, 4]")
    check_trailing_shape("cam_to_ego", cam_to_ego, (None, 4, 4), "[..., V, 4, 4]")
    e = jnp.asarray(cam_to_ego, jnp.float32)[..., :, None, :, :]  # [..., V, 1, 4, 4]
    m = jnp.asarray(ego_poses, jnp.float32)[..., None, :, :, :]  # [..., 1, F, 4, 4]
    return jnp.linalg.inv(e) @ jnp.linalg.inv(m) @ e


def plane_homography(intrinsics, motion, depth):
    """LongDWM [2506.01546v1] eq. 9 for the plane ``z = depth`` of camera 0: ``H = K (R + T e3^T / d) K^-1``
    (``[..., 3, 3]``), so that ``P_t ~ H P_0`` for homogeneous pixels ``P_0 = (u, v, 1)``
    (``e3^T K^-1 P_0 = 1`` for intrinsics whose last row is (0, 0, 1))."""
    k = jnp.asarray(intrinsics, jnp.float32)
    motion = jnp.asarray(motion, jnp.float32)
    r, t = motion[..., :3, :3], motion[..., :3, 3]
    e3 = jnp.asarray([0.0, 0.0, 1.0], jnp.float32)
    return k @ (r + t[..., :, None] * e3 / depth) @ jnp.linalg.inv(k)


@jax.jit
def depth_free_warp(image, intrinsics, motion, depth):
    """The first frame ``image [H, W, C]`` warped to each pose of ``motion [..., 4, 4]`` (camera 0
    -> camera t, :func:`camera_motion`) with every pixel at ``depth`` (LongDWM [2506.01546v1] appendix A.2, eq.
    9): ``(warped [..., H, W, C], hole [..., H, W])``; holes (no source pixel) are 0. Each target
    pixel ``p`` reads ``image`` at ``H^-1 p`` (:func:`plane_homography`) bilinearly."""
    image = jnp.asarray(image, jnp.float32)
    h, w = image.shape[:2]
    v, u = jnp.meshgrid(jnp.arange(h, dtype=jnp.float32), jnp.arange(w, dtype=jnp.float32), indexing="ij")
    target = jnp.stack([u, v, jnp.ones_like(u)], axis=-1)  # [H, W, 3]
    k = jnp.asarray(intrinsics, jnp.float32)
    motion = jnp.asarray(motion, jnp.float32)
    hom = plane_homography(k, motion, depth)  # [..., 3, 3]
    src = jnp.einsum("...ij,hwj->...hwi", jnp.linalg.inv(hom), target)
    src = src[..., :2] / jnp.where(jnp.abs(src[..., 2:]) > 1e-9, src[..., 2:], 1e-9)
    # the source point's 3D position after the motion must lie in front of camera t
    ray = (
        jnp.einsum("ij,...hwj->...hwi", jnp.linalg.inv(k), jnp.concatenate([src, jnp.ones_like(src[..., :1])], axis=-1))
        * depth
    )
    z_t = jnp.einsum("...j,...hwj->...hw", motion[..., 2, :3], ray) + motion[..., None, None, 2, 3]
    su, sv = src[..., 0], src[..., 1]
    eps = 1e-3  # round-off at the border is not a hole
    hole = (su < -eps) | (su > w - 1 + eps) | (sv < -eps) | (sv > h - 1 + eps) | (z_t <= 0)

    def sample(su, sv):
        return jnp.stack(
            [
                jax.scipy.ndimage.map_coordinates(image[..., c], [sv, su], order=1, mode="nearest")
                for c in range(image.shape[-1])
            ],
            axis=-1,
        )

    flat_u, flat_v = su.reshape((-1, h, w)), sv.reshape((-1, h, w))
    warped = jax.vmap(sample)(flat_u, flat_v).reshape(su.shape + (image.shape[-1],))
    return jnp.where(hole[..., None], 0.0, warped), hole


def inpaint_holes(frames, holes, *, radius: float = 3.0) -> np.ndarray:
    """``frames [..., H, W, 3]`` in [-1, 1] with ``holes [..., H, W]`` filled by Navier-Stokes
    inpainting (``cv2.inpaint(..., cv2.INPAINT_NS)``, LongDWM [2506.01546v1] appendix A.2), frame by frame on
    the host; pixels outside the holes are returned unchanged. A frame that is all hole stays 0
    (nothing to fill from)."""
    import cv2

    frames = np.asarray(frames, np.float32)
    holes = np.asarray(holes, bool)
    if frames.shape[:-1] != holes.shape or frames.shape[-1] != 3:
        raise ValueError(
            f"holes: expected the shape of frames without channels {list(frames.shape[:-1])} "
            f"(frames [..., H, W, 3]), got {list(holes.shape)}"
        )
    out = frames.copy()
    flat, mask = out.reshape((-1,) + frames.shape[-3:]), holes.reshape((-1,) + holes.shape[-2:])
    for i in range(flat.shape[0]):
        if not mask[i].any() or mask[i].all():
            continue
        img = np.clip((flat[i] + 1.0) * 127.5, 0, 255).round().astype(np.uint8)
        filled = cv2.inpaint(img, mask[i].astype(np.uint8), radius, cv2.INPAINT_NS)
        flat[i] = np.where(mask[i][..., None], filled.astype(np.float32) / 127.5 - 1.0, flat[i])
    return out


def warp_views(first, intrinsics, cam_to_ego, ego_poses, depth: float, *, inpaint: bool = True) -> np.ndarray:
    """The warped frames of every view: ``first [V, H, W, 3]`` (in [-1, 1]) along ``ego_poses
    [F, 4, 4]`` with each camera's ``intrinsics [V, 3, 3]`` and ``cam_to_ego [V, 4, 4]``:
    ``[V, F, H, W, 3]``, holes inpainted (``inpaint``) on the host."""
    first = np.asarray(first, np.float32)
    check_trailing_shape("first", first, (None, None, 3), "[V, H, W, 3]")
    if not float(depth) > 0:
        raise ValueError(f"depth: expected a positive plane depth in metres, got {depth}")
    motion = camera_motion(ego_poses, cam_to_ego)  # [V, F, 4, 4]
    # every view in one program: the views are a batch axis of the gather
    out, holes = jax.vmap(depth_free_warp, in_axes=(0, 0, 0, None))(
        first, jnp.asarray(intrinsics, jnp.float32), motion, float(depth)
    )
    out, holes = np.asarray(out), np.asarray(holes)
    return inpaint_holes(out, holes) if inpaint else out
