"""STAGE's foreground-weighted loss map W_aux (STAGE, sec. "Loss Function").

STAGE weighs the per-pixel diffusion loss ``L = E[|| W_aux * (x0 - eps_theta(x_t, t)) ||^2]`` with

    w'_ij = k / p_ij^c          if pixel (i, j) lies in the foreground polygon of an object,
    w'_ij = 1 / (H * W)^c       on the background,

then normalises the weights. The foreground polygon of an object is the convex hull of its
projected 3D box, and p_ij is the size (pixel area) of the object the pixel belongs to, so small
objects get large weights.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.geometry import BOX_EDGES, box_corners, ego_to_camera, project_to_image
from jaxdrive.validate import check_positive_int, check_range, check_shape

# Relative tolerance of the hull-edge test, in units of the object's coordinate magnitude.
# float32 rounding in projection and cross products is ~1e-6 of it; exactly collinear points
# (box faces seen edge-on) must still count as "on the edge", else a hull edge is missed.
_HULL_RTOL = 1e-5


def _hw_pair(name: str, value) -> tuple[int, int]:
    if not isinstance(value, (tuple, list)) or len(value) != 2:
        raise ValueError(f"{name}: expected a pair of positive ints (height, width), got {value!r}")
    return (check_positive_int(f"{name}[0]", value[0]), check_positive_int(f"{name}[1]", value[1]))


def _clip_near(corners_cam, near):
    """Candidate vertices of (box ∩ {z >= near}) ``[..., 20, 3]`` and their mask ``[..., 20]``.

    The 8 corners in front of the plane plus the crossing point of each of the 12 edges whose
    ends lie on opposite sides: these are exactly the vertices of the clipped (convex) polytope,
    so the hull of their projections is the image of the visible part of the box.
    """
    z = corners_cam[..., 2]
    front = z >= near
    a, b = BOX_EDGES[:, 0], BOX_EDGES[:, 1]
    pa, pb, za, zb = corners_cam[..., a, :], corners_cam[..., b, :], z[..., a], z[..., b]
    crosses = front[..., a] != front[..., b]
    dz = jnp.where(crosses, zb - za, 1.0)  # non-zero whenever the edge crosses
    t = jnp.clip((near - za) / dz, 0.0, 1.0)
    hits = pa + t[..., None] * (pb - pa)
    return (jnp.concatenate([corners_cam, hits], axis=-2), jnp.concatenate([front, crosses], axis=-1))


def _hull_mask(pts, valid, qu, qv):
    """Which grid points ``(qu[x], qv[y])`` lie in the convex hull of the valid 2D points.

    ``pts [..., P, 2]``, ``valid [..., P]``, ``qu [w]``, ``qv [h]`` -> ``[..., h, w]`` bool (closed
    hull). The hull is an intersection of half-planes, at most one per point: pair (i, j) is a
    hull edge iff every valid point lies on its left (within tolerance) and at least one lies
    strictly left (so collinear / degenerate sets have no edges, hence no pixels: a zero-area
    hull covers no pixel centre). Each point i keeps its farthest such j: for a hull vertex that
    is the far end of its counter-clockwise hull edge; nearer candidates (near-duplicates of i)
    could carry a direction set by rounding. Every kept pair is a supporting line of the set and
    every hull edge is kept, so the intersection is exactly the hull.
    Cost: O(P^3) per set for the edges, then O(P h w) for the grid (P = 20 for a clipped box).
    """
    scale = jnp.max(jnp.where(valid[..., None], jnp.abs(pts), 0.0), axis=(-2, -1))
    tol = _HULL_RTOL * jnp.maximum(scale, 1.0)[..., None, None, None]
    d = pts[..., None, :, :] - pts[..., :, None, :]  # [..., i, j, 2] = p_j - p_i
    # cross[i, j, k] = (p_j - p_i) x (p_k - p_i): > 0 when p_k is left of the line i -> j.
    cross = (
        d[..., :, :, None, 0] * d[..., :, None, :, 1] - d[..., :, :, None, 1] * d[..., :, None, :, 0]
    )  # [..., i, j, k]
    length = jnp.sqrt(jnp.sum(d * d, axis=-1))[..., None]  # [..., i, j, 1]
    kv = valid[..., None, None, :]
    all_left = jnp.all(~kv | (cross >= -tol * length), axis=-1)
    some_left = jnp.any(kv & (cross > tol * length), axis=-1)
    pair_ok = valid[..., :, None] & valid[..., None, :]
    is_edge = pair_ok & all_left & some_left  # [..., i, j]
    best = jnp.argmax(jnp.where(is_edge, length[..., 0], -1.0), axis=-1)
    direction = jnp.take_along_axis(d, best[..., None, None], axis=-2)[..., 0, :]  # [..., P, 2]
    active = jnp.any(is_edge, axis=-1)  # [..., P]
    ou, ov = pts[..., 0, None, None], pts[..., 1, None, None]
    du, dv = direction[..., 0, None, None], direction[..., 1, None, None]
    side = du * (qv[:, None] - ov) - dv * (qu[None, :] - ou)  # [..., P, h, w]
    inside = jnp.all(~active[..., None, None] | (side >= 0), axis=-3)
    return inside & jnp.any(active, axis=-1)[..., None, None]  # no edge: degenerate, empty


def foreground_weight_map(boxes, box_valid, intrinsics, cam_to_ego, *, map_hw, image_hw, k=1.0, c=0.5, near=0.1):
    """STAGE's foreground-weighted loss map ``[B, V, F, h, w]`` (float32, mean 1 per image).

    Args:
      boxes: ``[B, F, N, 7]`` (x, y, z, length, width, height, yaw), ego frame of each frame.
      box_valid: ``[B, F, N]`` bool; invalid boxes are ignored (their values may be anything,
        NaN included).
      intrinsics: ``[B, V, 3, 3]`` in pixels of an ``image_hw = (H, W)`` image (pixel centres at
        integer + 0.5, see :mod:`jaxdrive.geometry`).
      cam_to_ego: ``[B, V, 4, 4]`` rigid camera-to-ego transforms (same for every frame).
      map_hw: ``(h, w)`` of the map, typically the latent resolution. Map pixel (i, j) covers an
        ``H/h x W/w`` block of the image and belongs to an object iff its centre
        ``((j + 0.5) W / w, (i + 0.5) H / h)`` lies in the object's hull.
      k, c: STAGE's constants (k > 0, c >= 0); near: near-plane depth in metres (> 0).

    STAGE's ``w' = k / p^c`` inside an object, ``1 / (H W)^c`` outside, evaluated at map
    resolution:
      * Each box is clipped against the plane z_cam = near (visible part of boxes that straddle
        it; boxes fully behind contribute nothing) and projected; its polygon is the exact convex
        hull of the projected vertices.
      * p = number of map pixels inside that hull (its visible area, in map pixels) and the
        background uses ``h * w`` in place of ``H * W``, so the foreground / background ratio
        ``k (h w / p)^c`` is the same at any map resolution. Objects off-image, and objects whose
        hull covers no map-pixel centre (smaller than about one map pixel), have p = 0 and
        contribute nothing. As in STAGE's formula, k < (p / (h w))^c weighs an object below the
        background.
      * Where hulls overlap the pixel takes the largest weight, i.e. the smallest object: the
        weighting exists to protect small objects, which an occluding large one would erase.
      * "Then normalised": each (view, frame) map is divided by its mean, so the weighted loss
        keeps the scale of the plain loss (a map without objects is all ones).
    Boxes for latent frames are the caller's choice (e.g. the boxes of each latent frame's first
    video frame). The map is a constant loss weight: its gradient is stopped.
    """
    check_shape("boxes", boxes, (None, None, None, 7))
    bsz, frames, nbox = np.shape(boxes)[:3]
    check_shape("box_valid", box_valid, (bsz, frames, nbox))
    if jnp.result_type(box_valid) != jnp.bool_:
        raise ValueError(f"box_valid: expected dtype bool, got {jnp.result_type(box_valid)}")
    check_shape("intrinsics", intrinsics, (bsz, None, 3, 3))
    views = np.shape(intrinsics)[1]
    check_shape("cam_to_ego", cam_to_ego, (bsz, views, 4, 4))
    h, w = _hw_pair("map_hw", map_hw)
    img_h, img_w = _hw_pair("image_hw", image_hw)
    check_range("k", k, 0.0, math.inf, lo_open=True)
    check_range("c", c, 0.0, math.inf)
    check_range("near", near, 0.0, math.inf, lo_open=True)

    valid = jnp.asarray(box_valid)
    boxes = jnp.where(valid[..., None], jnp.asarray(boxes, jnp.float32), 0.0)  # no NaN leaks
    corners = box_corners(boxes)  # [B, F, N, 8, 3]
    cams = ego_to_camera(corners[:, None], jnp.asarray(cam_to_ego)[:, :, None, None])
    verts, vmask = _clip_near(cams, jnp.float32(near))  # [B, V, F, N, 20, .]
    pix, _ = project_to_image(verts, jnp.asarray(intrinsics)[:, :, None, None])
    vmask = vmask & valid[:, None, :, :, None]
    # Centre coordinates on the image so their magnitude (hence rounding) stays small.
    centre = jnp.array([img_w / 2, img_h / 2], jnp.float32)
    # Map pixel centres, in the same centred image pixels.
    qu = (jnp.arange(w, dtype=jnp.float32) + 0.5) * (img_w / w) - img_w / 2
    qv = (jnp.arange(h, dtype=jnp.float32) + 0.5) * (img_h / h) - img_h / 2
    inside = _hull_mask(pix - centre, vmask, qu, qv)  # [B, V, F, N, h, w]

    # Log-weights relative to the background (1 / (h w)^c -> 0): k (h w / p)^c inside.
    area = jnp.sum(inside, axis=(-2, -1)).astype(jnp.float32)  # [B, V, F, N]
    c = jnp.asarray(c, jnp.float32)
    log_fg = jnp.log(jnp.asarray(k, jnp.float32)) + c * (math.log(h * w) - jnp.log(jnp.maximum(area, 1.0)))
    log_fg = jnp.where(inside, log_fg[..., None, None], -jnp.inf)
    log_w = jnp.where(jnp.any(inside, axis=-3), jnp.max(log_fg, axis=-3), 0.0)  # [B, V, F, h, w]
    # Normalise in log space first (subtract the max) so large c or k cannot overflow.
    weights = jnp.exp(log_w - jnp.max(log_w, axis=(-2, -1), keepdims=True))
    weights = weights / jnp.mean(weights, axis=(-2, -1), keepdims=True)
    return jax.lax.stop_gradient(weights)
