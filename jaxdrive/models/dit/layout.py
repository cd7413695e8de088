"""The projected layout control: the 3D boxes and the BEV map's road classes drawn into each
camera's image, as a canvas on the latent grid (``controls.layout``; the layout-canvas
conditioning of Ctrl-V and CoGen, beside MagicDrive-V2's box cross-attention).

Design choices:

- **Inside the model.** The canvas is drawn in the jitted forward from ``boxes``, ``box_classes``,
  ``box_valid``, ``intrinsics``, ``cam_to_ego`` and ``bev_map``, not on the host: it follows any
  boxes a caller puts in (a counterfactual scene, removed boxes, guidance's drop) and shards with
  the batch like every other control, and the data pipeline stays as it is.
- **Ray casting, not polygon filling.** Each sample point of the image casts the ray through it
  (camera depth = ray parameter, the camera-frame direction has z = 1). A box's filled hull in
  the image is the set of rays that hit the box: the slab test in the box's frame decides it
  exactly, also for a box that reaches behind the camera, where the convex hull of the projected
  corners is wrong (a corner behind the camera projects mirrored). The nearest hit wins per ray
  (a z-buffer: nearer boxes over farther ones, by true depth rather than by centre distance).
  One box at a time in a ``lax.scan`` keeps the memory at one ``[B, F, V, rays]`` buffer
  whatever the number of boxes.
- **Roads by ground intersection.** A ray below the horizon meets the ground ``z = 0`` of the ego
  frame; the BEV cell under that point (the grid of :func:`jaxdrive.data.bev.cell_centres`: ego
  at the centre, x up, y left) gives the road classes there, exactly and at one gather per ray,
  where rasterising the map's polygons into each camera would need them as polygons. A box hit
  nearer than the ground hides the road behind it; outside the map there is no road.
- **Resolution.** The functions take any sample grid: the model casts ``samples x samples`` rays
  per latent cell (the VAE's ``vae_spatial`` pixels) and averages them, so a channel is the
  fraction of the cell covered; the test casts one ray per stored pixel and compares with the
  synthetic world's instance ids.
- **Memory.** About 60 bytes of temporaries per ray (XLA:CPU's ``memory_analysis`` of
  :func:`layout_canvas` for 6 views x 17 frames x 106 x 200 latent cells x 4 rays, 60 boxes and a
  200 x 200 map: 0.50 GiB): the per-ray depth, owner and road classes before pooling. At
  MagicDrive-V2's 129 frames of 848 x 1600 that is ~3.8 GiB per clip; ``samples=1`` a quarter.
- **Channels** (:func:`layout_canvas`): ``num_classes`` one-hot box classes of the nearest box,
  one near-box channel ``1 / max(depth, 1 m)`` (0 where no box: it tells adjacent boxes and
  their distance apart), then the BEV map's channels on the visible ground.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.models.dit.controls import Conv3x3, align_frames
from jaxdrive.models.tokens import merge, reshape, split
from jaxdrive.validate import check_positive_int, check_shape

_EPS = 1e-9


def camera_rays(intrinsics, cam_to_ego, image_hw, grid_hw, samples: int = 1):
    """Rays of ``samples x samples`` points per cell of a ``grid_hw = (gh, gw)`` grid over the
    image ``[0, W] x [0, H]`` (``image_hw = (H, W)``, the pixels ``intrinsics`` are in; sample
    ``j`` of a row sits at ``u = (j + 0.5) W / (gw samples)``, so one sample per stored pixel is
    the pixel centres). ``intrinsics [..., V, 3, 3]``, ``cam_to_ego [..., V, 4, 4]`` ->
    ``(origin [..., V, 3], dirs [..., V, gh s, gw s, 3])`` in the ego frame; each direction is the
    camera-frame ray with z = 1 rotated, so the ray parameter of a point is its camera depth.
    ``K`` is read as ``fx, fy, cx, cy`` (skew taken as 0, as calibrated cameras have it)."""
    if np.ndim(intrinsics) < 3 or tuple(np.shape(intrinsics)[-2:]) != (3, 3):
        raise ValueError(f"intrinsics: expected shape [..., V, 3, 3], got {list(np.shape(intrinsics))}")
    if tuple(np.shape(cam_to_ego)) != tuple(np.shape(intrinsics)[:-2]) + (4, 4):
        raise ValueError(
            f"cam_to_ego: expected shape {list(np.shape(intrinsics)[:-2]) + [4, 4]}, got {list(np.shape(cam_to_ego))}"
        )
    for name, hw in (("image_hw", image_hw), ("grid_hw", grid_hw)):
        if len(tuple(hw)) != 2:
            raise ValueError(f"{name}: expected (height, width), got {hw!r}")
        for n in hw:
            check_positive_int(name, n)
    check_positive_int("samples", samples)
    (h, w), (gh, gw) = image_hw, grid_hw
    u = (np.arange(gw * samples) + 0.5) * (w / (gw * samples))
    v = (np.arange(gh * samples) + 0.5) * (h / (gh * samples))
    k = jnp.asarray(intrinsics, jnp.float32)
    fx, fy, cx, cy = (k[..., i, j][..., None, None] for i, j in ((0, 0), (1, 1), (0, 2), (1, 2)))
    x = (jnp.asarray(u, jnp.float32)[None, :] - cx) / fx  # [..., V, 1, Ws]
    y = (jnp.asarray(v, jnp.float32)[:, None] - cy) / fy  # [..., V, Hs, 1]
    x, y = jnp.broadcast_arrays(x, y)
    cam = jnp.stack([x, y, jnp.ones_like(x)], -1)  # [..., V, Hs, Ws, 3]
    pose = jnp.asarray(cam_to_ego, jnp.float32)
    dirs = jnp.einsum("...ij,...hwj->...hwi", pose[..., :3, :3], cam)
    return pose[..., :3, 3], dirs


def _hit(box, origin, dirs):
    """Camera depth of the ray hits of one box per (batch, frame): ``box [B, F, 7]``, ``origin
    [B, V, 3]``, ``dirs [B, V, P, 3]`` -> ``[B, F, V, P]`` (inf where the ray misses or the box
    lies behind the camera). The slab test in the box's frame (yaw about z)."""
    c, s = jnp.cos(box[..., 6]), jnp.sin(box[..., 6])  # [B, F]
    c, s = c[:, :, None], s[:, :, None]  # [B, F, 1] (views)
    rel = origin[:, None] - box[:, :, None, :3]  # [B, F, V, 3]
    o = jnp.stack([c * rel[..., 0] + s * rel[..., 1], -s * rel[..., 0] + c * rel[..., 1], rel[..., 2]], -1)
    d = dirs[:, None]  # [B, 1, V, P, 3]
    c, s = c[..., None], s[..., None]
    d = jnp.stack(
        [
            c * d[..., 0] + s * d[..., 1],
            -s * d[..., 0] + c * d[..., 1],
            jnp.broadcast_to(d[..., 2], jnp.broadcast_shapes(c.shape, d[..., 2].shape)),
        ],
        -1,
    )
    inv = 1.0 / jnp.where(jnp.abs(d) < _EPS, _EPS, d)  # a parallel ray: +-huge slabs
    half = 0.5 * box[:, :, None, None, 3:6]  # [B, F, 1, 1, 3]
    t1 = (-half - o[..., None, :]) * inv
    t2 = (half - o[..., None, :]) * inv
    t_in = jnp.max(jnp.minimum(t1, t2), -1)
    t_out = jnp.min(jnp.maximum(t1, t2), -1)
    hit = (t_out >= t_in) & (t_out > 0)
    return jnp.where(hit, jnp.maximum(t_in, 0.0), jnp.inf)


def box_hits(boxes, box_valid, origin, dirs):
    """The nearest box along every ray: ``boxes [B, F, N, 7]`` (ego frame of their frame, the
    geometry conventions of :mod:`jaxdrive.geometry`), ``box_valid [B, F, N]``, rays from
    :func:`camera_rays` (``origin [B, V, 3]``, ``dirs [B, V, Hs, Ws, 3]``) -> ``(depth, owner)``,
    each ``[B, F, V, Hs, Ws]``: the camera depth of the nearest hit (inf: none) and that box's
    index (-1: none). Boxes one at a time in a ``lax.scan`` (the z-buffer of the module
    docstring)."""
    check_shape("boxes", boxes, [None, None, None, 7])
    b, f, n = np.shape(boxes)[:3]
    check_shape("box_valid", box_valid, [b, f, n])
    check_shape("origin", origin, [b, None, 3])
    check_shape("dirs", dirs, [b, np.shape(origin)[1], None, None, 3])
    hs, ws = np.shape(dirs)[2:4]
    flat = reshape(jnp.asarray(dirs, jnp.float32), (b, np.shape(dirs)[1], hs * ws, 3))
    origin = jnp.asarray(origin, jnp.float32)
    bx = jnp.moveaxis(jnp.asarray(boxes, jnp.float32), 2, 0)  # [N, B, F, 7]
    ok = jnp.moveaxis(jnp.asarray(box_valid, bool), 2, 0)  # [N, B, F]
    shape = (b, f, np.shape(origin)[1], hs, ws)
    if n == 0:
        return jnp.full(shape, jnp.inf, jnp.float32), jnp.full(shape, -1, jnp.int32)

    def one(i, box, valid):
        t = jnp.where(valid[:, :, None, None], _hit(box, origin, flat), jnp.inf)
        return t, jnp.where(jnp.isfinite(t), i, -1).astype(jnp.int32)

    def step(carry, item):
        depth, owner = carry
        t, who = one(*item)
        nearer = t < depth
        return (jnp.where(nearer, t, depth), jnp.where(nearer, who, owner)), None

    # the first box outside the scan: the carry then has the body's type (and sharding) from the start
    first = one(jnp.int32(0), bx[0], ok[0])
    (depth, owner), _ = jax.lax.scan(step, first, (jnp.arange(1, n, dtype=jnp.int32), bx[1:], ok[1:]))
    return reshape(depth, shape), reshape(owner, shape)


def ground_classes(bev_map, origin, dirs, bev_range):
    """The BEV map's classes where each ray meets the ground ``z = 0`` (ego frame):
    ``bev_map [B, F, Hm, Wm, C]`` spanning ``bev_range = (x, y)`` metres around the ego (the grid
    of :func:`jaxdrive.data.bev.cell_centres`), rays from :func:`camera_rays` -> ``(classes
    [B, F, V, Hs, Ws, C], depth [B, V, Hs, Ws])``: zeros (and depth inf) for rays above the horizon
    and ground points outside the map. The cameras are fixed to the ego, so the ground point of a
    ray is the same in every frame; each frame's map is read there."""
    check_shape("bev_map", bev_map, [None, None, None, None, None])
    b, f, hm, wm, ch = np.shape(bev_map)
    check_shape("origin", origin, [b, None, 3])
    check_shape("dirs", dirs, [b, np.shape(origin)[1], None, None, 3])
    if len(tuple(bev_range)) != 2 or not all(float(r) > 0 for r in bev_range):
        raise ValueError(f"bev_range: expected two positive extents in metres (x, y), got {bev_range!r}")
    origin = jnp.asarray(origin, jnp.float32)[:, :, None, None]  # [B, V, 1, 1, 3]
    dirs = jnp.asarray(dirs, jnp.float32)
    down = dirs[..., 2] < -_EPS
    t = jnp.where(down, -origin[..., 2] / jnp.where(down, dirs[..., 2], -1.0), jnp.inf)
    point = origin[..., :2] + jnp.where(down, t, 0.0)[..., None] * dirs[..., :2]
    row = jnp.floor(hm / 2 - point[..., 0] / (float(bev_range[0]) / hm)).astype(jnp.int32)
    col = jnp.floor(wm / 2 - point[..., 1] / (float(bev_range[1]) / wm)).astype(jnp.int32)
    inside = down & (row >= 0) & (row < hm) & (col >= 0) & (col < wm)
    index = jnp.where(inside, row * wm + col, 0)  # [B, V, Hs, Ws]
    flat = reshape(jnp.asarray(bev_map, jnp.float32), (b, f, hm * wm, ch))
    rays = int(np.prod(index.shape[1:]))  # V Hs Ws
    picked = jnp.take_along_axis(flat, reshape(index, (b, 1, rays, 1)), axis=2)  # [B, F, V Hs Ws, C]
    picked = reshape(picked, (b, f, *index.shape[1:], ch)) * inside[:, None, ..., None]
    return picked, jnp.where(inside, t, jnp.inf)


def _pool(x, s: int):
    """Mean over ``s x s`` blocks of the axes -3, -2 of ``x [..., Hs, Ws, C]``."""
    if s == 1:
        return x
    *lead, hs, ws, c = x.shape
    return jnp.mean(reshape(x, (*lead, hs // s, s, ws // s, s, c)), axis=(-4, -2))


def layout_canvas(
    boxes,
    box_classes,
    box_valid,
    intrinsics,
    cam_to_ego,
    image_hw,
    grid_hw,
    *,
    num_classes: int,
    bev_map=None,
    bev_range=(100.0, 100.0),
    samples: int = 1,
):
    """The layout canvas ``[B, F, V, gh, gw, num_classes + 1 + C]`` (channels in the module
    docstring; ``C`` = the BEV map's channels, 0 without ``bev_map``) of ``boxes [B, F, N, 7]``,
    ``box_classes``, ``box_valid [B, F, N]`` and ``bev_map [B, F, Hm, Wm, C]`` (or None) seen by
    the cameras ``intrinsics [B, V, 3, 3]`` (pixels of ``image_hw``), ``cam_to_ego [B, V, 4, 4]``,
    on a ``grid_hw`` grid of ``samples x samples`` rays per cell (their mean). Class ids outside
    ``[0, num_classes)`` draw no class channel (their near-box channel stays)."""
    check_positive_int("num_classes", num_classes)
    check_shape("boxes", boxes, [None, None, None, 7])
    b, f, n = np.shape(boxes)[:3]
    check_shape("box_classes", box_classes, [b, f, n])
    check_shape("intrinsics", intrinsics, [b, None, 3, 3])
    if bev_map is not None:
        check_shape("bev_map", bev_map, [b, f, None, None, None])
    origin, dirs = camera_rays(intrinsics, cam_to_ego, image_hw, grid_hw, samples)
    depth, owner = box_hits(boxes, box_valid, origin, dirs)  # [B, F, V, Hs, Ws]
    owners = reshape(jnp.maximum(owner, 0), (b, f, int(np.prod(owner.shape[2:]))))  # [B, F, V Hs Ws]
    cls = jnp.take_along_axis(jnp.asarray(box_classes, jnp.int32), owners, axis=2)
    cls = jnp.where(owner >= 0, reshape(cls, owner.shape), -1)
    # each part pooled on its own (a concatenation at the rays' resolution would be kept whole)
    parts = [
        _pool(jax.nn.one_hot(cls, num_classes, dtype=jnp.float32), samples),  # -1, out of range: zeros
        _pool(jnp.where(owner >= 0, 1.0 / jnp.maximum(depth, 1.0), 0.0)[..., None], samples),
    ]
    if bev_map is not None:
        road, ground = ground_classes(bev_map, origin, dirs, bev_range)
        parts.append(_pool(road * (ground[:, None] < depth)[..., None], samples))  # a nearer box hides the road
    return jnp.concatenate(parts, -1)


class LayoutEncoder(nn.Module):
    """The layout canvas (:func:`layout_canvas`) on the latent grid ``grid_hw`` -> features
    ``[B, V, F', h, w, hidden]``: two 3x3 convolutions (SiLU) per frame and view, then the VAE's
    temporal alignment (:func:`jaxdrive.models.dit.controls.align_frames`: pixel-frame canvases are
    grouped as the causal VAE groups frames and mapped by a learned linear layer). The DiT
    patchifies the result and adds it to the tokens through a zero-initialised projection.
    Without ``bev_map`` the ``map_channels`` road channels are zero (no road anywhere)."""

    num_classes: int
    map_channels: int
    hidden: int
    samples: int
    bev_range: tuple[float, float]
    ratio: int
    dtype: jnp.dtype = jnp.float32

    @nn.compact
    def __call__(
        self, boxes, box_classes, box_valid, intrinsics, cam_to_ego, bev_map, image_hw, grid_hw, latent_frames
    ):
        canvas = jax.lax.stop_gradient(
            layout_canvas(
                boxes,
                box_classes,
                box_valid,
                intrinsics,
                cam_to_ego,
                image_hw,
                grid_hw,
                num_classes=self.num_classes,
                bev_map=bev_map,
                bev_range=self.bev_range,
                samples=self.samples,
            )
        )  # [B, F, V, h, w, K]
        if bev_map is None:  # no map: no road anywhere, same channels
            canvas = jnp.pad(canvas, [(0, 0)] * 5 + [(0, self.map_channels)])
        b, f, nv = canvas.shape[:3]
        x = merge(merge(canvas, 0), 0).astype(self.dtype)  # [B F V, h, w, K]
        x = jax.nn.silu(Conv3x3(self.hidden, 1, self.dtype, name="conv_in")(x))
        x = jax.nn.silu(Conv3x3(self.hidden, 1, self.dtype, name="conv_out")(x))
        x = split(split(x, 0, b), 1, f)  # [B, F, V, h, w, hidden]
        x = align_frames(self, "layout", x, None, latent_frames, self.ratio, self.hidden, self.dtype)[0]
        return jnp.moveaxis(x, 2, 1)  # [B, V, F', h, w, hidden]
