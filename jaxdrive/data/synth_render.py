"""A numpy ray caster for the synthetic town: exact per-pixel visibility of cuboids and the ground.

Every pixel centre ``(c + 0.5, r + 0.5)`` (the pixel convention of :mod:`jaxdrive.geometry`) casts
the ray ``d = ((u - cx) / fx, (v - cy) / fy, 1)`` in the camera frame, so a ray parameter is the
camera depth z. Cuboids are intersected with the slab test in their own frame; each (view, box)
pair only tests the pixels of the box's projected screen rectangle (its corners, clipped against a
near plane), and a z-buffer (``np.minimum.at``) keeps the nearest hit. The ground z = 0 is hit
analytically. Everything is vectorised over all views and pixels of a frame.
"""

from __future__ import annotations

import numpy as np

NEAR = 0.05

# nuScenes-like rig in CAMERAS order: (x, y, z) mount in the ego frame, yaw (deg), HFOV (deg).
RIG = (
    ((1.70, 0.00, 1.51), 0.0, 70.0),
    ((1.55, -0.49, 1.50), -55.0, 70.0),
    ((1.03, -0.48, 1.52), -110.0, 70.0),
    ((0.03, 0.00, 1.53), 180.0, 110.0),
    ((1.04, 0.48, 1.52), 110.0, 70.0),
    ((1.52, 0.49, 1.51), 55.0, 70.0),
)

_CORNERS = (
    np.array(
        [[1, 1, -1], [-1, 1, -1], [-1, -1, -1], [1, -1, -1], [1, 1, 1], [-1, 1, 1], [-1, -1, 1], [1, -1, 1]], np.float64
    )
    * 0.5
)
_EDGES = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4], [0, 4], [1, 5], [2, 6], [3, 7]])


def camera_rig(views: int, height: int, width: int):
    """``(intrinsics [V, 3, 3], cam_to_ego [V, 4, 4])`` float64 for 1 (front) or 6 views."""
    intr, c2e = [], []
    for pos, yaw_deg, hfov in RIG[:views]:
        f = (width / 2) / np.tan(np.radians(hfov) / 2)
        intr.append([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
        psi = np.radians(yaw_deg)
        m = np.eye(4)
        # Columns: camera x (right), y (down), z (forward) in the ego frame.
        m[:3, 0] = (np.sin(psi), -np.cos(psi), 0.0)
        m[:3, 1] = (0.0, 0.0, -1.0)
        m[:3, 2] = (np.cos(psi), np.sin(psi), 0.0)
        m[:3, 3] = pos
        c2e.append(m)
    return np.array(intr), np.array(c2e)


def yaw_matrix(yaw):
    c, s = np.cos(yaw), np.sin(yaw)
    z, o = np.zeros_like(c), np.ones_like(c)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def pixel_rays(intrinsics, height, width):
    """Camera-frame ray directions ``[V, H, W, 3]`` (z = 1) through the pixel centres."""
    u = np.arange(width) + 0.5
    v = np.arange(height) + 0.5
    fx, fy = intrinsics[:, 0, 0], intrinsics[:, 1, 1]
    cx, cy = intrinsics[:, 0, 2], intrinsics[:, 1, 2]
    a = (u[None, :] - cx[:, None]) / fx[:, None]  # [V, W]
    b = (v[None, :] - cy[:, None]) / fy[:, None]  # [V, H]
    shape = (len(intrinsics), height, width)
    return np.stack([np.broadcast_to(a[:, None, :], shape), np.broadcast_to(b[:, :, None], shape), np.ones(shape)], -1)


def _screen_rects(corners_cam, intrinsics, height, width, max_depth):
    """Pixel index ranges ``[V, B, 4]`` (r0, r1, c0, c1 inclusive) covering each box's projection;
    r0 > r1 marks a culled pair."""
    z = corners_cam[..., 2]  # [V, B, 8]
    a, b = corners_cam[..., _EDGES[:, 0], :], corners_cam[..., _EDGES[:, 1], :]
    za, zb = a[..., 2], b[..., 2]
    cross = (za - NEAR) * (zb - NEAR) < 0
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(cross, (NEAR - za) / (zb - za), 0.0)
    clip_pts = a + w[..., None] * (b - a)  # [V, B, 12, 3] on the near plane
    pts = np.concatenate([corners_cam, clip_pts], -2)
    ok = np.concatenate([z >= NEAR, cross], -1)
    zs = np.where(ok, pts[..., 2], 1.0)
    fx, fy = intrinsics[:, 0, 0, None, None], intrinsics[:, 1, 1, None, None]
    cx, cy = intrinsics[:, 0, 2, None, None], intrinsics[:, 1, 2, None, None]
    u = fx * pts[..., 0] / zs + cx
    v = fy * pts[..., 1] / zs + cy
    big = 1e9
    umin = np.where(ok, u, big).min(-1)
    umax = np.where(ok, u, -big).max(-1)
    vmin = np.where(ok, v, big).min(-1)
    vmax = np.where(ok, v, -big).max(-1)
    c0 = np.clip(np.floor(umin - 0.5), 0, width).astype(np.int64)
    c1 = np.clip(np.ceil(umax - 0.5), -1, width - 1).astype(np.int64)
    r0 = np.clip(np.floor(vmin - 0.5), 0, height).astype(np.int64)
    r1 = np.clip(np.ceil(vmax - 0.5), -1, height - 1).astype(np.int64)
    dead = ~ok.any(-1) | (z.min(-1) > max_depth)
    r1 = np.where(dead, -1, r1)
    return np.stack([r0, r1, c0, c1], -1)


def raycast(cam_to_world, intrinsics, boxes, height, width, *, max_depth=120.0):
    """Nearest ray hits of ``boxes [B, 7]`` (world frame) for the cameras ``cam_to_world [V, 4, 4]``.

    Returns ``(depth [V, H, W], owner [V, H, W], axis [V, H, W], local [V, H, W, 3])``: camera
    depth of the nearest box hit (inf where none), the box index (-1 where none), the local axis
    (0 length, 1 width, 2 height) of the face hit and the hit point in the box's frame.
    """
    nv = len(cam_to_world)
    npx = height * width
    depth = np.full(nv * npx, np.inf)
    owner = np.full(nv * npx, -1, np.int64)
    axis = np.zeros(nv * npx, np.int64)
    local = np.zeros((nv * npx, 3))
    if len(boxes) == 0:
        return (
            depth.reshape(nv, height, width),
            owner.reshape(nv, height, width),
            axis.reshape(nv, height, width),
            local.reshape(nv, height, width, 3),
        )
    rot_c, pos_c = cam_to_world[:, :3, :3], cam_to_world[:, :3, 3]
    # Drop boxes beyond max_depth of every camera before any per-pair work.
    reach = np.linalg.norm(boxes[:, None, :3] - pos_c[None], axis=-1).min(1) - 0.5 * np.linalg.norm(
        boxes[:, 3:6], axis=1
    )
    index = np.flatnonzero(reach < max_depth)
    boxes = boxes[index]
    rot_b = yaw_matrix(boxes[:, 6])  # [B, 3, 3]
    half = boxes[:, 3:6] / 2
    corners_w = boxes[:, None, :3] + (_CORNERS * boxes[:, None, 3:6]) @ np.swapaxes(rot_b, -1, -2)
    corners_cam = (corners_w[None] - pos_c[:, None, None]) @ rot_c[:, None]
    rects = _screen_rects(corners_cam, intrinsics, height, width, max_depth)
    vi, bi = np.nonzero((rects[..., 1] >= rects[..., 0]) & (rects[..., 3] >= rects[..., 2]))
    if len(vi) == 0:
        return (
            depth.reshape(nv, height, width),
            owner.reshape(nv, height, width),
            axis.reshape(nv, height, width),
            local.reshape(nv, height, width, 3),
        )
    r0, r1, c0, c1 = rects[vi, bi].T
    rw = c1 - c0 + 1
    area = (r1 - r0 + 1) * rw
    # Per pair: camera->box-local rotation and the camera centre in the box frame.
    m = np.swapaxes(rot_b[bi], -1, -2) @ rot_c[vi]  # R_b^T R_c  [P, 3, 3]
    o = ((pos_c[vi] - boxes[bi, :3])[:, None, :] @ rot_b[bi])[:, 0]  # R_b^T (c - b)  [P, 3]
    fx, fy = intrinsics[vi, 0, 0], intrinsics[vi, 1, 1]
    cx, cy = intrinsics[vi, 0, 2], intrinsics[vi, 1, 2]
    # Ray (pixel-centre) direction in the box frame is linear in the column and row:
    # d = m @ ((c + 0.5 - cx) / fx, (r + 0.5 - cy) / fy, 1) = gc * c + gr * r + g0.
    gc = m[:, :, 0] / fx[:, None]
    gr = m[:, :, 1] / fy[:, None]
    g0 = m[:, :, 2] + m[:, :, 0] * (0.5 - cx[:, None]) / fx[:, None] + m[:, :, 1] * (0.5 - cy[:, None]) / fy[:, None]
    lo, hi = -half[bi] - o, half[bi] - o
    start = np.cumsum(area) - area
    total = int(area.sum())
    # Per-pair constants expanded to one column per tested pixel (one np.repeat each table).
    ints = np.repeat(np.stack([start, r0, c0, rw, vi * npx]), area, axis=1)
    coef = np.repeat(np.concatenate([gc.T, gr.T, g0.T, lo.T, hi.T]).astype(np.float32), area, axis=1)
    q, rem = np.divmod(np.arange(total) - ints[0], ints[3])
    row, col = ints[1] + q, ints[2] + rem
    rowf, colf = row.astype(np.float32), col.astype(np.float32)
    t_near = np.full(total, -np.inf, np.float32)
    t_far = np.full(total, np.inf, np.float32)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for k in range(3):
            inv = coef[k] * colf
            inv += coef[3 + k] * rowf
            inv += coef[6 + k]
            np.reciprocal(inv, out=inv)
            ta, tb = coef[9 + k] * inv, coef[12 + k] * inv
            np.fmax(t_near, np.fmin(ta, tb), out=t_near)
            np.fmin(t_far, np.fmax(ta, tb), out=t_far)
    pair = np.repeat(np.arange(len(vi)), area)
    hit = (t_near <= t_far) & (t_near > NEAR)
    pair, t, row, col = pair[hit], t_near[hit].astype(np.float64), row[hit], col[hit]
    key = ints[4][hit] + row * width + col
    np.minimum.at(depth, key, t)
    win = t <= depth[key]
    pair, t, key, row, col = pair[win], t[win], key[win], row[win], col[win]
    owner[key] = index[bi[pair]]
    # Hit point in the box frame and the face (axis whose slab the ray entered last).
    d = gc[pair] * col[:, None] + gr[pair] * row[:, None] + g0[pair]
    p = o[pair] + t[:, None] * d
    local[key] = p
    axis[key] = np.argmax(np.abs(p) / np.maximum(half[bi[pair]], 1e-6), -1)
    return (
        depth.reshape(nv, height, width),
        owner.reshape(nv, height, width),
        axis.reshape(nv, height, width),
        local.reshape(nv, height, width, 3),
    )
