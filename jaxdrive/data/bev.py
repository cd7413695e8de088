"""Rasterising a vector road map into MagicDrive's 8-class BEV grid (ego at the centre, x up).

Layers are ``{class name: [(rings, lo, hi), ...]}`` with ``rings`` a list of ``[P, 2]`` world
xy arrays (an exterior ring then holes for areas, one polyline for lines) and ``lo``/``hi`` the
item's bounding box, used to skip items out of reach. Shared by every data source that has a
vector map (nuScenes' map expansion, the synthetic world).
"""

from __future__ import annotations

import numpy as np

from jaxdrive.classes import BEV_CLASSES

POLYGON_LAYERS = ("drivable_area", "ped_crossing", "walkway", "stop_line", "carpark_area", "road_block")
LINE_LAYERS = ("road_divider", "lane_divider")


def cell_centres(size: tuple[int, int], cell: tuple[float, float]) -> np.ndarray:
    """Ego-frame xy ``[Hm, Wm, 2]`` of the BEV cell centres: cell (r, c) sits at
    ``x = (Hm/2 - r - 0.5) * cell_x``, ``y = (Wm/2 - c - 0.5) * cell_y`` (ego at the centre, x up,
    y left), the grid every BEV map of jaxdrive uses."""
    hm, wm = size
    x = (hm / 2 - np.arange(hm) - 0.5) * cell[0]
    y = (wm / 2 - np.arange(wm) - 0.5) * cell[1]
    return np.stack(np.broadcast_arrays(x[:, None], y[None, :]), -1)


def rasterize_map(
    layers: dict, ego_to_world: np.ndarray, *, size: tuple[int, int] = (200, 200), resolution: float = 0.5
) -> np.ndarray:
    """BEV map ``[Hm, Wm, 8]`` uint8 in {0, 1} around one ego pose (ego at the centre, x up, y left).

    Cells follow :func:`cell_centres` with square cells of ``resolution`` metres.
    """
    hm, wm = size
    out = np.zeros((hm, wm, len(BEV_CLASSES)), np.uint8)
    rot, origin = ego_to_world[:2, :2], ego_to_world[:2, 3]
    yaw = np.arctan2(rot[1, 0], rot[0, 0])
    r2 = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    reach = resolution * np.hypot(hm, wm) / 2

    def to_grid(xy):  # global xy [P, 2] -> (col u, row v) continuous grid coordinates
        local = (xy - origin) @ r2
        return np.stack([wm / 2 - local[:, 1] / resolution, hm / 2 - local[:, 0] / resolution], -1)

    for ch, layer in enumerate(BEV_CLASSES):
        for rings, lo, hi in layers.get(layer, []):
            if np.any(lo > origin + reach) or np.any(hi < origin - reach):
                continue
            grids = [to_grid(r) for r in rings]
            if layer in LINE_LAYERS:
                _draw_lines(out[..., ch], grids)
            else:
                _fill_rings(out[..., ch], grids)
    return out


def _fill_rings(canvas: np.ndarray, rings) -> None:
    """Even-odd scanline fill of closed rings (grid coordinates) at cell centres."""
    hm, wm = canvas.shape
    a = np.concatenate(rings)
    b = np.concatenate([np.roll(r, -1, axis=0) for r in rings])
    rows = np.arange(hm) + 0.5
    v0, v1 = a[:, 1][None], b[:, 1][None]
    crosses = (v0 <= rows[:, None]) != (v1 <= rows[:, None])  # [Hm, E]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = a[:, 0] + (rows[:, None] - v0) / (v1 - v0) * (b[:, 0] - a[:, 0])
    r_idx, e_idx = np.nonzero(crosses)
    col = np.clip(np.ceil(u[r_idx, e_idx] - 0.5), 0, wm).astype(np.int64)  # first cell right of it
    toggles = np.zeros((hm, wm + 1), np.int64)
    np.add.at(toggles, (r_idx, col), 1)
    canvas |= (np.cumsum(toggles[:, :wm], axis=1) % 2).astype(np.uint8)


def _draw_lines(canvas: np.ndarray, lines) -> None:
    """Polylines 1 cell wide: the cells under points sampled every 1/4 cell along each segment."""
    hm, wm = canvas.shape
    for pts in lines:
        for p, q in zip(pts[:-1], pts[1:]):
            n = int(np.ceil(np.linalg.norm(q - p) * 4)) + 1
            s = p + np.linspace(0, 1, n)[:, None] * (q - p)
            c, r = np.floor(s[:, 0]).astype(np.int64), np.floor(s[:, 1]).astype(np.int64)
            ok = (r >= 0) & (r < hm) & (c >= 0) & (c < wm)
            canvas[r[ok], c[ok]] = 1
