"""3D boxes, ego -> camera transforms and pinhole projection (nuScenes conventions).

Frames (docs/concepts/conventions.md): ego x forward, y left, z up; camera x right, y down, z forward.
Boxes are ``(x, y, z, length, width, height, yaw)`` with (x, y, z) the box *centre*, length along
the heading, width across it, height along +z, yaw about +z counter-clockwise from +x.

Pixel convention: continuous image coordinates ``(u, v)`` with u the column and v the row; the
image covers ``[0, W] x [0, H]`` and pixel (row r, col c) is the unit square whose centre is
``(c + 0.5, r + 0.5)``. Intrinsics ``K`` are read as mapping camera points to these coordinates
(so a principal point at the image centre is ``(W / 2, H / 2)``). Calibrations made with OpenCV's
integer-centre convention differ by half a pixel: add 0.5 to their ``c_x, c_y`` to convert.

Everything is pure ``jax.numpy`` and runs under jit / vmap / grad.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.validate import check_trailing_shape

# Corner order of :func:`box_corners`, in the box's own frame (f = front = +length/2 along the
# heading, l = left = +width/2): indices 0-3 are the bottom face (z - height/2), 4-7 the top face
# (z + height/2); each face goes front-left, rear-left, rear-right, front-right, i.e.
# counter-clockwise seen from above. Corner i + 4 is directly above corner i.
_CORNER_SIGNS = (
    np.array(
        [
            [+1, +1, -1],
            [-1, +1, -1],
            [-1, -1, -1],
            [+1, -1, -1],
            [+1, +1, +1],
            [-1, +1, +1],
            [-1, -1, +1],
            [+1, -1, +1],
        ],
        dtype=np.float32,
    )
    * 0.5
)

# The 12 edges as corner-index pairs: bottom ring, top ring, then the 4 verticals.
BOX_EDGES = np.array(
    [
        [0, 1],
        [1, 2],
        [2, 3],
        [3, 0],
        [4, 5],
        [5, 6],
        [6, 7],
        [7, 4],
        [0, 4],
        [1, 5],
        [2, 6],
        [3, 7],
    ],
    dtype=np.int32,
)
BOX_EDGES.setflags(write=False)

# |depth| below this is treated as this (finite placeholder pixels, no NaN in values or grads).
_MIN_ABS_DEPTH = 1e-6


def _broadcast_batch(name_a: str, shape_a, name_b: str, shape_b) -> None:
    try:
        np.broadcast_shapes(tuple(shape_a), tuple(shape_b))
    except ValueError:
        raise ValueError(
            f"{name_b}: expected leading (batch) dimensions that broadcast against "
            f"{name_a}'s {list(shape_a)}, got {list(shape_b)}"
        ) from None


def box_corners(boxes):
    """Corners ``[..., 8, 3]`` of boxes ``[..., 7]`` = (x, y, z, length, width, height, yaw).

    The order is fixed (see ``_CORNER_SIGNS``): 0-3 bottom face front-left, rear-left, rear-right,
    front-right; 4-7 the same on the top face. :data:`BOX_EDGES` ``[12, 2]`` indexes the edges.
    Corners are in the same frame as the box centres.
    """
    check_trailing_shape("boxes", boxes, (7,), "[..., 7]")
    boxes = jnp.asarray(boxes, jnp.float32)
    centre, size, yaw = boxes[..., None, 0:3], boxes[..., None, 3:6], boxes[..., None, 6]
    local = jnp.asarray(_CORNER_SIGNS) * size  # [..., 8, 3] offsets before the yaw rotation
    cos, sin = jnp.cos(yaw), jnp.sin(yaw)
    x = cos * local[..., 0] - sin * local[..., 1]
    y = sin * local[..., 0] + cos * local[..., 1]
    return centre + jnp.stack([x, y, local[..., 2]], axis=-1)


@jax.named_scope("geometry")  # float32 on purpose: train.program.F32_DOTS_ALLOWED
def ego_to_camera(points, cam_to_ego):
    """Ego-frame points ``[..., P, 3]`` -> camera-frame points ``[..., P, 3]``.

    ``cam_to_ego [..., 4, 4]`` maps camera coordinates to ego coordinates (nuScenes calibrated
    sensor: rotation R, translation t of the camera in the ego frame). It must be rigid: the
    inverse is applied as ``R^T (p - t)`` (exact and cheap, no matrix inversion). The leading
    dimensions of the two arguments broadcast against each other (numpy rules).
    """
    check_trailing_shape("points", points, (None, 3), "[..., P, 3]")
    check_trailing_shape("cam_to_ego", cam_to_ego, (4, 4), "[..., 4, 4]")
    _broadcast_batch("points", np.shape(points)[:-2], "cam_to_ego", np.shape(cam_to_ego)[:-2])
    points = jnp.asarray(points, jnp.float32)
    cam_to_ego = jnp.asarray(cam_to_ego, jnp.float32)
    rot, trans = cam_to_ego[..., :3, :3], cam_to_ego[..., None, :3, 3]
    # Row vectors: (R^T (p - t))^T = (p - t)^T R.
    return jnp.matmul(points - trans, rot)


@jax.named_scope("geometry")  # float32 on purpose: train.program.F32_DOTS_ALLOWED
def project_to_image(points_cam, intrinsics):
    """Pinhole projection of camera-frame points ``[..., P, 3]`` with ``intrinsics [..., 3, 3]``.

    Returns ``(pixels [..., P, 2], depth [..., P])``: ``pixels = (u, v)`` = (column, row) in the
    continuous convention of this module (pixel centres at integer + 0.5), ``depth`` = camera z.
    The last row of K is taken to be (0, 0, 1). Pixels are only meaningful where depth > 0; the
    caller masks the rest (points behind the camera project mirrored, and |depth| < 1e-6 gives
    finite placeholders so that values and gradients never hold NaN or inf).
    """
    check_trailing_shape("points_cam", points_cam, (None, 3), "[..., P, 3]")
    check_trailing_shape("intrinsics", intrinsics, (3, 3), "[..., 3, 3]")
    _broadcast_batch("points_cam", np.shape(points_cam)[:-2], "intrinsics", np.shape(intrinsics)[:-2])
    points_cam = jnp.asarray(points_cam, jnp.float32)
    intrinsics = jnp.asarray(intrinsics, jnp.float32)
    depth = points_cam[..., 2]
    safe = jnp.abs(depth) > _MIN_ABS_DEPTH
    # Double where: the unused branch must not produce inf (it would poison gradients).
    z = jnp.where(safe, depth, _MIN_ABS_DEPTH)
    uvw = jnp.matmul(points_cam, jnp.swapaxes(intrinsics[..., :2, :], -1, -2))  # [..., P, 2]
    return uvw / z[..., None], depth


@jax.named_scope("geometry")  # float32 on purpose: train.program.F32_DOTS_ALLOWED
def relative_to_first(poses):
    """Rigid poses ``[..., F, 4, 4]`` (e.g. ego-to-world) -> each frame's pose in the frame of the
    first: ``inv(P_0) @ P_f``, with the rigid inverse ``[R^T, -R^T t]``. Frame 0 becomes the
    identity (MagicDrive-V2's ego trajectory, "the transformation from each frame to the first")."""
    check_trailing_shape("poses", poses, (None, 4, 4), "[..., F, 4, 4]")
    poses = jnp.asarray(poses, jnp.float32)
    rot0, t0 = poses[..., :1, :3, :3], poses[..., :1, :3, 3:]
    rot = jnp.matmul(jnp.swapaxes(rot0, -1, -2), poses[..., :3, :3])
    trans = jnp.matmul(jnp.swapaxes(rot0, -1, -2), poses[..., :3, 3:] - t0)
    top = jnp.concatenate([rot, trans], axis=-1)
    # zeros_like: the bottom row takes top's sharding (a batch-sharded trajectory under an explicit
    # mesh cannot be concatenated with a replicated constant)
    bottom = jnp.zeros_like(top[..., :1, :]) + jnp.asarray([0.0, 0.0, 0.0, 1.0], jnp.float32)
    return jnp.concatenate([top, bottom], axis=-2)


def wrap(angle):
    """Angles (radians) into [-pi, pi) (NumPy or JAX arrays alike)."""
    return (angle + np.pi) % (2 * np.pi) - np.pi
