"""The ego's motion read back from the pixels of a clip: does a generated drive follow its route?

:func:`estimate_ego_motion` fits, for every pair of consecutive frames, the ego's planar motion
``(dx, dy, dyaw)`` (metres forward and left, radians left, in the earlier frame's ego frame) that
best warps the earlier frame of every camera onto the later one through the ground plane:

- a pixel whose ray meets the ground (ego ``z = 0``) between :data:`NEAR` and :data:`FAR` metres is
  a point ``X`` on the plane ``m . X = h`` of its camera (``m`` the ground's upward normal in camera
  coordinates, negated, ``h`` the camera's height); the plane-induced homography
  ``H = K (R + t m^T / h) K^-1`` (Hartley & Zisserman, *Multiple View Geometry*, result 13.1; LongDWM
  [2506.01546v1] eq. 9 is its case ``m = e3``, ``h = d``, the depth-free warp) moves it between
  the frames, so metric translation is observable (the camera height is known) where the
  depth-free warp's plane at one depth is not;
- the photometric residual of all cameras' ground pixels is minimised by Gauss-Newton with
  Geman-McClure weights (iteratively reweighted least squares: the other traffic and the
  buildings are outliers), coarse to fine over Gaussian blurs of 2, 1 and 0 pixels, starting from
  the previous pair's motion (a clip's motion is smooth, and a dashed lane line has minima one
  dash apart) and, for the first pair, from the best of four forward speeds.

:func:`route_following` composes the motions into a path and scores it against the commanded one
(ADE, FDE) and :func:`manoeuvre` names what a path does (ACT-Bench's classes: stop, slower,
faster, lane change left / right, turn left / right, keep). The estimator's own error is measured
on the renders of the synthetic world, whose poses are known (``jaxdrive eval --routes``: the
``render`` row), so that a generated clip's error can be read against it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.validate import check_trailing_shape

NEAR, FAR = 2.0, 40.0  # metres of ground used: nearer is under the car, farther is a few pixels
BLURS = (2.0, 1.0, 0.0)  # pixels, coarse to fine
STEPS_PER_BLUR = 5
ROBUST_SCALE = 0.1  # Geman-McClure scale of a residual, in [-1, 1] pixel values
FIRST_SPEEDS = (0.0, 0.5, 1.0, 1.5)  # metres a frame the first pair starts from

MANOEUVRES = ("stop", "slower", "faster", "keep", "lane-left", "lane-right", "turn-left", "turn-right")
TURN_RADIANS = 0.35  # heading change after the start that makes a turn (20 degrees)
LANE_CHANGE_METRES = 1.5  # sideways offset from the straight continuation that makes a lane change
STOP_SPEED = 0.5  # m/s at the end that makes a stop
SLOWER, FASTER = 0.8, 1.2  # end speed / speed at the start


def _pose(p):
    """``(dx, dy, dyaw)`` -> the 4x4 pose of the later ego frame in the earlier one."""
    c, s, z, o = jnp.cos(p[2]), jnp.sin(p[2]), jnp.zeros(()), jnp.ones(())
    return jnp.stack(
        [jnp.stack([c, -s, z, p[0]]), jnp.stack([s, c, z, p[1]]), jnp.stack([z, z, o, z]), jnp.stack([z, z, z, o])]
    )


def ground_points(intrinsics, cam_to_ego, height: int, width: int):
    """``(points [V, H, W, 3], mask [V, H, W])``: each pixel's ray met with the ground (ego
    ``z = 0``) in its camera's coordinates, and whether that point lies :data:`NEAR` to
    :data:`FAR` metres from the ego (0 elsewhere)."""
    k = np.asarray(intrinsics, np.float64)
    e = np.asarray(cam_to_ego, np.float64)
    v, u = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    pix = np.stack([u, v, np.ones_like(u)], -1).astype(np.float64)
    rays = np.einsum("vij,hwj->vhwi", np.linalg.inv(k), pix)  # camera coordinates, z = 1
    down = np.einsum("vij,vhwj->vhwi", e[:, :3, :3], rays)  # the same rays in the ego frame
    dz = down[..., 2]
    scale = np.where(dz < -1e-6, -e[:, None, None, 2, 3] / np.minimum(dz, -1e-6), 0.0)
    dist = np.linalg.norm(down[..., :2] * scale[..., None], axis=-1)
    mask = (dz < -1e-6) & (dist > NEAR) & (dist < FAR)
    return (rays * scale[..., None]).astype(np.float32), mask.astype(np.float32)


def _residual_view(p, earlier, later, points, mask, k, e):
    """The later frame's ground pixels minus the earlier frame read where the motion ``p`` moves them."""
    h, w = earlier.shape[:2]
    t = jnp.linalg.inv(e) @ _pose(p) @ e  # later camera -> earlier camera
    x = points @ t[:3, :3].T + t[:3, 3]
    q = x @ k.T
    z = jnp.where(q[..., 2] > 1e-3, q[..., 2], 1e-3)
    u, v = q[..., 0] / z, q[..., 1] / z
    ok = mask * (q[..., 2] > 1e-3) * (u >= 0) * (u <= w - 1) * (v >= 0) * (v <= h - 1)
    read = jnp.stack(
        [jax.scipy.ndimage.map_coordinates(earlier[..., c], [v, u], order=1, mode="nearest") for c in range(3)], -1
    )
    return ((read - later) * ok[..., None]).reshape(-1)


def _residual(p, earlier, later, points, mask, k, e):
    return jax.vmap(_residual_view, in_axes=(None, 0, 0, 0, 0, 0, 0))(p, earlier, later, points, mask, k, e).reshape(-1)


def _gauss_newton(p, earlier, later, points, mask, k, e):
    """One reweighted Gauss-Newton step on the motion ``p`` (Geman-McClure weights)."""
    r = _residual(p, earlier, later, points, mask, k, e)
    jac = jax.jacfwd(_residual)(p, earlier, later, points, mask, k, e)
    w = 1.0 / (1.0 + (r / ROBUST_SCALE) ** 2) ** 2
    a = (jac * w[:, None]).T @ jac + 1e-4 * jnp.eye(3)
    return p - jnp.linalg.solve(a, (jac * w[:, None]).T @ r)


@jax.jit
def _fit_pair(starts, earlier, later, points, mask, k, e):
    """The motion between one pair of frames (``earlier`` / ``later``: ``{blur: [V, H, W, 3]}``)
    from each of ``starts [S, 3]``, coarse to fine; the fit with the lowest L1 residual on the
    sharp frames wins. One program a pair: every step of every start in it."""

    def fit(p):
        for s in BLURS:
            step = lambda _, q, s=s: _gauss_newton(q, earlier[s], later[s], points, mask, k, e)
            p = jax.lax.fori_loop(0, STEPS_PER_BLUR, step, p)
        return p, jnp.sum(jnp.abs(_residual(p, earlier[0.0], later[0.0], points, mask, k, e)))

    fits, costs = jax.vmap(fit)(starts)
    return fits[jnp.argmin(costs)]


def _blurred(video, sigma: float):
    from scipy.ndimage import gaussian_filter1d

    if sigma == 0:
        return video
    return gaussian_filter1d(gaussian_filter1d(video, sigma, axis=-3, mode="nearest"), sigma, axis=-2, mode="nearest")


def estimate_ego_motion(video, intrinsics, cam_to_ego) -> np.ndarray:
    """The ego's motion between consecutive frames of ``video [V, F, H, W, 3]`` (uint8, or float in
    [-1, 1]) seen by cameras ``intrinsics [V, 3, 3]`` (pixels of H x W) and ``cam_to_ego [V, 4,
    4]``: ``[F - 1, 3]`` float64 of ``(dx, dy, dyaw)``, frame ``t + 1``'s ego in frame ``t``'s
    (module docstring)."""
    video = np.asarray(video)
    check_trailing_shape("video", video, (None, None, None, None, 3), "[V, F, H, W, 3]")
    views, frames, h, w = video.shape[:4]
    if frames < 2:
        raise ValueError(f"video: expected at least 2 frames to read a motion from, got {frames}")
    check_trailing_shape("intrinsics", intrinsics, (views, 3, 3), f"[{views}, 3, 3] (one per view of video)")
    check_trailing_shape("cam_to_ego", cam_to_ego, (views, 4, 4), f"[{views}, 4, 4] (one per view of video)")
    frames01 = video.astype(np.float32) / 127.5 - 1.0 if video.dtype == np.uint8 else video.astype(np.float32)
    points, mask = ground_points(intrinsics, cam_to_ego, h, w)
    if not mask.any():
        raise ValueError("cam_to_ego: expected cameras that see the ground within 40 m, got none that do")
    geometry = tuple(
        map(jnp.asarray, (points, mask, np.asarray(intrinsics, np.float32), np.asarray(cam_to_ego, np.float32)))
    )
    pyramid = {s: jnp.asarray(_blurred(frames01, s)) for s in BLURS}

    out, p = [], None
    for t in range(frames - 1):
        starts = p[None] if p is not None else jnp.asarray([[v, 0.0, 0.0] for v in FIRST_SPEEDS], jnp.float32)
        pair = [{s: pyramid[s][:, t + i] for s in BLURS} for i in (0, 1)]
        p = _fit_pair(starts, *pair, *geometry)
        out.append(np.asarray(p, np.float64))
    return np.stack(out)


def motion_from_poses(ego_to_world) -> np.ndarray:
    """The true ``[F - 1, 3]`` motions of :func:`estimate_ego_motion` from ego poses ``[F, 4, 4]``."""
    e = np.asarray(ego_to_world, np.float64)
    check_trailing_shape("ego_to_world", e, (None, 4, 4), "[F, 4, 4]")
    rel = np.linalg.inv(e[:-1]) @ e[1:]
    return np.stack([rel[:, 0, 3], rel[:, 1, 3], np.arctan2(rel[:, 1, 0], rel[:, 0, 0])], 1)


def path(motions) -> tuple[np.ndarray, np.ndarray]:
    """``(xy [F, 2], yaw [F])`` of the ego in its first frame's ego frame, the motions composed."""
    m = np.asarray(motions, np.float64)
    xy, yaw = [np.zeros(2)], [0.0]
    for dx, dy, dyaw in m:
        c, s = np.cos(yaw[-1]), np.sin(yaw[-1])
        xy.append(xy[-1] + np.array([c * dx - s * dy, s * dx + c * dy]))
        yaw.append(yaw[-1] + dyaw)
    return np.stack(xy), np.asarray(yaw)


def manoeuvre(motions, start: int, fps: float) -> str:
    """What the drive of ``motions [F - 1, 3]`` does from frame ``start`` on, one of
    :data:`MANOEUVRES`: a heading change of :data:`TURN_RADIANS` is a turn; else a sideways offset
    of :data:`LANE_CHANGE_METRES` from the straight continuation of the ego at ``start`` is a lane
    change; else the speed over the last quarter of the clip against that before ``start``: below
    :data:`STOP_SPEED` a stop, below :data:`SLOWER` x slower, above :data:`FASTER` x faster, else keep."""
    m = np.asarray(motions, np.float64)
    if not 1 <= start < len(m):
        raise ValueError(f"start: expected a frame in [1, {len(m) - 1}] of a clip of {len(m) + 1} frames, got {start}")
    xy, yaw = path(m)
    turn = yaw[-1] - yaw[start]
    if abs(turn) >= TURN_RADIANS:
        return "turn-left" if turn > 0 else "turn-right"
    c, s = np.cos(yaw[start]), np.sin(yaw[start])
    side = -s * (xy[-1, 0] - xy[start, 0]) + c * (xy[-1, 1] - xy[start, 1])
    if abs(side) >= LANE_CHANGE_METRES:
        return "lane-left" if side > 0 else "lane-right"
    speed = np.hypot(m[:, 0], m[:, 1]) * fps
    before, end = speed[:start].mean(), speed[-max(1, len(m) // 4) :].mean()
    if end < STOP_SPEED:
        return "stop"
    if end < SLOWER * before:
        return "slower"
    return "faster" if end > FASTER * before else "keep"


def route_following(estimated, commanded, start: int, fps: float) -> dict:
    """How well a clip's estimated motions ``[F - 1, 3]`` follow the ``commanded`` ones (same
    shape): ``ade`` and ``fde`` (metres, the mean and last distance between the two paths over the
    frames from ``start`` on, both paths from the same first frame), the ``manoeuvre`` each shows
    and whether they agree (``recognised``)."""
    est, cmd = np.asarray(estimated, np.float64), np.asarray(commanded, np.float64)
    if est.shape != cmd.shape or est.ndim != 2 or est.shape[1] != 3:
        raise ValueError(
            f"estimated: expected the commanded motions' shape {list(cmd.shape)} [F - 1, 3], got {list(est.shape)}"
        )
    (a, _), (b, _) = path(est), path(cmd)
    d = np.linalg.norm(a[start:] - b[start:], axis=-1)
    got, want = manoeuvre(est, start, fps), manoeuvre(cmd, start, fps)
    return {"ade": float(d.mean()), "fde": float(d[-1]), "manoeuvre": got, "commanded": want, "recognised": got == want}
