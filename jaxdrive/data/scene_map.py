"""A scene's road map in the world frame, stitched from a clip's BEV maps, re-cut at any ego pose.

Every BEV map a clip records is rasterised from the scene's own vector map (nuScenes' map
expansion, the synthetic town's road layout, :mod:`jaxdrive.data.bev`) around the recorded ego,
so stitching them into one world-frame raster (:meth:`SceneMap.from_clip`) gives the scene's map
over all the ground the recorded car saw: a ``bev_range`` square around each recorded pose. It
needs nothing a dataset does not already hold, so it serves every source alike.

:func:`cut` (jitted; the predictor's rollout calls it every step) re-cuts a BEV map at any ego
pose: each cell takes the stitched map where the recorded car saw it; an unseen cell takes the
typical seen value of its column (the ego's direction): the road the ego drives on goes on
straight, without the cross streets seen here and there; a column seen nowhere takes
``fallback`` (the newest recorded BEV map in the ego frame). That continuation is the only prediction of the map
jaxdrive makes; a user's route must stay on the seen map (:meth:`SceneMap.covers`), and on its road
(:meth:`SceneMap.on_road`, :data:`ROAD_CLASSES`) unless its user says otherwise.
"""

from __future__ import annotations

import flax.struct
import jax.numpy as jnp
import numpy as np

from jaxdrive.classes import BEV_CLASSES
from jaxdrive.data.bev import cell_centres

DEFAULT_RANGE = (100.0, 100.0)  # metres (x, y) a BEV map spans: the synthetic world's and nuScenes' default
# the surfaces a car drives on: walkways are not, the divider lines lie on drivable area anyway (a
# stray line cell alone is no road), and a cell with no class set is verge or building
ROAD_CLASSES = ("drivable_area", "ped_crossing", "stop_line", "carpark_area", "road_block")


def bev_range_of(metadata: dict) -> tuple[float, float]:
    """The metres ``(x, y)`` a dataset's BEV maps span, from its metadata (``bev_range``, or
    nuScenes' ``bev_size`` x ``bev_resolution``), else :data:`DEFAULT_RANGE`."""
    if "bev_range" in metadata:
        return tuple(float(r) for r in metadata["bev_range"])
    if "bev_resolution" in metadata and "bev_size" in metadata:
        return tuple(float(n) * float(metadata["bev_resolution"]) for n in metadata["bev_size"])
    return DEFAULT_RANGE


@flax.struct.dataclass
class SceneMap:
    """``raster [Hs, Ws, 8]`` uint8 classes on a world grid (row r at world x = origin_x + (r + 0.5)
    resolution, column c at y = origin_y + (c + 0.5) resolution), ``covered [Hs, Ws]`` where it was
    seen, and the BEV grid cut from it: ``cell`` metres (x, y) of one BEV cell of ``size`` (Hm, Wm)."""

    raster: np.ndarray
    covered: np.ndarray
    origin: np.ndarray
    resolution: float = flax.struct.field(pytree_node=False)  # static under jit: the grid's shape
    cell: tuple[float, float] = flax.struct.field(pytree_node=False)
    size: tuple[int, int] = flax.struct.field(pytree_node=False)

    @classmethod
    def from_clip(cls, bev_map, ego_to_world, bev_range=DEFAULT_RANGE) -> SceneMap:
        """Stitch ``bev_map [F, Hm, Wm, 8]`` recorded at ``ego_to_world [F, 4, 4]``; each world cell
        takes the nearest BEV cell of the newest frame that saw it."""
        bev_map, poses = np.asarray(bev_map), np.asarray(ego_to_world, np.float64)
        if bev_map.ndim != 4 or poses.shape != (bev_map.shape[0], 4, 4):
            raise ValueError(
                f"bev_map, ego_to_world: expected [F, Hm, Wm, C] and [F, 4, 4], got "
                f"{list(bev_map.shape)} and {list(poses.shape)}"
            )
        hm, wm = bev_map.shape[1:3]
        cell = (float(bev_range[0]) / hm, float(bev_range[1]) / wm)
        res = min(cell) / 2  # finer than a BEV cell: re-cutting at another pose moves a line by less
        half = 0.5 * np.hypot(*bev_range)
        lo = poses[:, :2, 3].min(0) - half
        hi = poses[:, :2, 3].max(0) + half
        shape = tuple(np.ceil((hi - lo) / res).astype(int))
        raster = np.zeros(shape + (bev_map.shape[-1],), np.uint8)
        covered = np.zeros(shape, bool)
        gx = lo[0] + (np.arange(shape[0]) + 0.5) * res
        gy = lo[1] + (np.arange(shape[1]) + 0.5) * res
        for f in range(len(poses)):  # newest last: it overwrites older views
            rot, t = poses[f, :2, :2], poses[f, :2, 3]
            r0, r1 = np.searchsorted(gx, [t[0] - half, t[0] + half])
            c0, c1 = np.searchsorted(gy, [t[1] - half, t[1] + half])
            world = np.stack(np.meshgrid(gx[r0:r1], gy[c0:c1], indexing="ij"), -1) - t
            local = world @ rot  # ego frame: R^T (p - t)
            row = np.floor(hm / 2 - local[..., 0] / cell[0]).astype(int)
            col = np.floor(wm / 2 - local[..., 1] / cell[1]).astype(int)
            inside = (row >= 0) & (row < hm) & (col >= 0) & (col < wm)
            rr, cc = np.nonzero(inside)
            raster[r0 + rr, c0 + cc] = bev_map[f, row[rr, cc], col[rr, cc]]
            covered[r0 + rr, c0 + cc] = True
        return cls(raster, covered, lo.astype(np.float64), float(res), cell, (int(hm), int(wm)))

    def _lookup(self, xy, values, empty) -> np.ndarray:
        """``values`` (per grid cell) at world points ``xy [..., 2]``; ``empty`` off the grid."""
        xy = np.asarray(xy, np.float64)
        if xy.shape[-1:] != (2,):
            raise ValueError(f"xy: expected world points [..., 2], got shape {list(xy.shape)}")
        idx = np.floor((xy - self.origin) / self.resolution).astype(int)
        ok = (idx >= 0).all(-1) & (idx[..., 0] < self.covered.shape[0]) & (idx[..., 1] < self.covered.shape[1])
        out = np.full(ok.shape, empty, np.asarray(values).dtype)
        out[ok] = np.asarray(values)[idx[ok][:, 0], idx[ok][:, 1]]
        return out

    def covers(self, xy) -> np.ndarray:
        """Whether world points ``xy [..., 2]`` lie on the seen map."""
        return self._lookup(xy, self.covered, False)

    def _road(self, classes) -> np.ndarray:
        unknown = sorted(set(classes) - set(BEV_CLASSES))
        if unknown or not classes:
            raise ValueError(f"classes: expected names from {', '.join(BEV_CLASSES)}, got {list(classes)}")
        ch = [BEV_CLASSES.index(c) for c in classes]
        return np.asarray(self.covered) & (np.asarray(self.raster)[..., ch] > 0).any(-1)

    def on_road(self, xy, classes=ROAD_CLASSES) -> np.ndarray:
        """Whether world points ``xy [..., 2]`` lie on the seen map on one of ``classes``."""
        return self._lookup(xy, self._road(classes), False)

    def has_road(self, classes=ROAD_CLASSES) -> bool:
        """Whether any seen cell is road: False for a map of zeros (nuScenes without its map
        expansion), where nothing about the road can be checked."""
        return bool(self._road(classes).any())

    def cut(self, pose, fallback):
        """:func:`cut` of this map (what the predictor's rollout calls, jitted, at each pose)."""
        return cut(self, pose, fallback)

    def device(self, multiple: int = 128) -> SceneMap:
        """The arrays as device arrays (what :func:`cut` under jit takes), padded with unseen cells
        to a ``multiple`` of cells per side, so that scenes of similar extent share one program."""
        pad = [(0, -n % multiple) for n in self.covered.shape]
        return self.replace(
            raster=jnp.asarray(np.pad(self.raster, pad + [(0, 0)])),
            covered=jnp.asarray(np.pad(self.covered, pad)),
            origin=jnp.asarray(self.origin, jnp.float32),
        )


def cut(scene: SceneMap, pose, fallback):
    """The BEV map ``[Hm, Wm, 8]`` (``fallback``'s dtype) at ego ``pose = (x, y, yaw)`` (world):
    the stitched map where it was seen, else its column's typical value, else ``fallback``
    (module docstring). Pure ``jax.numpy``: traceable under jit and vmap."""
    centres = jnp.asarray(cell_centres(scene.size, scene.cell), jnp.float32)  # ego frame
    c, s = jnp.cos(pose[2]), jnp.sin(pose[2])
    wx = pose[0] + c * centres[..., 0] - s * centres[..., 1]
    wy = pose[1] + s * centres[..., 0] + c * centres[..., 1]
    r = jnp.floor((wx - scene.origin[0]) / scene.resolution).astype(jnp.int32)
    k = jnp.floor((wy - scene.origin[1]) / scene.resolution).astype(jnp.int32)
    hs, ws = scene.covered.shape
    inside = (r >= 0) & (r < hs) & (k >= 0) & (k < ws)
    r, k = jnp.clip(r, 0, hs - 1), jnp.clip(k, 0, ws - 1)
    seen = inside & scene.covered[r, k]
    values = scene.raster[r, k].astype(fallback.dtype)
    # unseen cells take their column's typical seen value (each class where it covers most of the
    # column's seen cells): the road the ego is on goes on straight, the cross streets and
    # crossings seen here and there are not smeared; a column seen nowhere takes ``fallback``
    count = seen.sum(0)
    share = (values * seen[..., None]).sum(0) / jnp.maximum(count, 1)[:, None]
    typical = (share > 0.5).astype(fallback.dtype)
    fill = jnp.where((count > 0)[None, :, None], typical[None], fallback)
    return jnp.where(seen[..., None], values, fill)
