"""The synthetic town's layout: streets, road markings, static scenery and the ego's route.

World frame: z up, ground at z = 0. The main street runs along world x (centre line y = 0) and is
crossed by a few cross streets along world y (centre lines ``x = xc``). Traffic drives on the
right: on the main street lanes with y < 0 head +x, lanes with y > 0 head -x; on a cross street
lanes with x > xc head +y, lanes with x < xc head -y. Every street has 2 lanes per direction
(:data:`LANE` wide), a sidewalk (:data:`SIDEWALK` wide) and buildings set back to :data:`SETBACK`.

Boxes follow :mod:`jaxdrive.geometry`: ``(x, y, z, length, width, height, yaw)`` with (x, y, z) the
centre, length along the heading.
"""

from __future__ import annotations

import dataclasses

import numpy as np

LANE = 3.5
ROAD = 2 * LANE  # half-width of a street's carriageway
SIDEWALK = 3.0  # sidewalk band: ROAD <= |offset| < ROAD + SIDEWALK
SETBACK = ROAD + SIDEWALK + 2.0  # buildings start here
STOP = ROAD + SIDEWALK + 0.5  # stop lines at this distance from the crossing street's centre
LINE_HW = 0.08  # half-width of painted lines (m)
STOP_HW = 0.25  # half-width of a stop line (m)

# Static scenery kinds (agents use AGENT_KIND + class id).
BUILDING, TRUNK, CANOPY, POLE, LAMP = 0, 1, 2, 3, 4
AGENT_KIND = 10


def nearest_cross(x, crosses):
    """Signed offset of ``x`` from the nearest cross street centre line."""
    crosses = np.asarray(crosses, np.float64)
    d = np.asarray(x, np.float64)[..., None] - crosses
    return np.take_along_axis(d, np.abs(d).argmin(-1)[..., None], -1)[..., 0]


def road_classes(x, y, crosses, *, pad: float = 0.0) -> np.ndarray:
    """MagicDrive's 8 BEV road classes (jaxdrive.classes.BEV_CLASSES order) at world points -> bool [..., 8].

    ``pad`` widens painted lines (half a BEV cell, so that thin lines are not missed by sampling).
    Lane dividers are solid here (the polylines a map stores); the renderer dashes them.
    """
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    sx = nearest_cross(x, crosses)
    ay, ax = np.abs(y), np.abs(sx)
    on_main, on_cross = ay < ROAD, ax < ROAD
    drivable = on_main | on_cross
    inter = on_main & on_cross
    band_y = (ay >= ROAD) & (ay < ROAD + SIDEWALK)
    band_x = (ax >= ROAD) & (ax < ROAD + SIDEWALK)
    walkway = (band_y & ~on_cross) | (band_x & ~on_main)
    crossing = (on_cross & band_y) | (on_main & band_x)
    shw, lhw = STOP_HW + pad, LINE_HW + pad
    stop = (on_main & (np.abs(ax - STOP) < shw) & (sx * y > 0)) | (on_cross & (np.abs(ay - STOP) < shw) & (sx * y < 0))
    road_div = ((ay < 2 * lhw) & on_main & ~on_cross) | ((ax < 2 * lhw) & on_cross & ~on_main)
    lane_div = ((np.abs(ay - LANE) < lhw) & on_main & ~on_cross) | ((np.abs(ax - LANE) < lhw) & on_cross & ~on_main)
    carpark = np.zeros_like(drivable)
    road_block = drivable & ~inter
    return np.stack([drivable, crossing, walkway, stop, carpark, road_div, lane_div, road_block], -1)


# ----------------------------------------------------------------------------------- ego route


def _arc(cx, cy, radius, a0, a1, n=48):
    a = np.linspace(a0, a1, n)
    return np.stack([cx + radius * np.cos(a), cy + radius * np.sin(a)], -1)


def turn_path(start: float, lane_y: float, turn: str, radius: float):
    """The polyline of a turn off the main street (heading +x in the lane at ``lane_y``) that
    leaves it at ``x = start`` on a circular arc of ``radius``, then drives 1 km along the cross
    street -> ``(points [P, 2], heading [P])``, the first point ``(0, lane_y)``."""
    if turn == "left":
        arc = _arc(start, lane_y + radius, radius, -np.pi / 2, 0.0)
        end = arc[-1] + np.array([0.0, 1000.0])
        arc_heading = np.linspace(0.0, np.pi / 2, len(arc))
        end_heading = np.pi / 2
    else:
        arc = _arc(start, lane_y - radius, radius, np.pi / 2, 0.0)
        end = arc[-1] + np.array([0.0, -1000.0])
        arc_heading = np.linspace(0.0, -np.pi / 2, len(arc))
        end_heading = -np.pi / 2
    pts = np.concatenate([[[0.0, lane_y]], arc, [end]])
    heading = np.concatenate([[0.0], arc_heading, [end_heading]])
    return pts, heading


def straight_path(lane_y: float, length: float):
    """The main street's lane at ``lane_y`` as a polyline from x = 0 -> ``(points [2, 2], heading [2])``."""
    return np.array([[0.0, lane_y], [length + 1000.0, lane_y]]), np.zeros(2)


def along_path(pts, heading, dist):
    """Positions ``[..., 2]`` and headings ``[...]`` at arc lengths ``dist`` along a polyline."""
    seglen = np.linalg.norm(np.diff(pts, axis=0), axis=-1)
    cum = np.concatenate([[0.0], np.cumsum(seglen)])
    xy = np.stack([np.interp(dist, cum, pts[:, 0]), np.interp(dist, cum, pts[:, 1])], -1)
    return xy, np.interp(dist, cum, heading)


@dataclasses.dataclass(frozen=True)
class EgoRoute:
    """The ego's recorded drive: per-frame ``xy [F, 2]`` and ``yaw [F]`` (world frame), the cross
    streets' x (``crosses [C]``), the manoeuvre (``turn``: "straight", "left", "right"), the path
    it follows (``points [P, 2]``, ``heading [P]``), the distance driven along it at each frame
    (``dist [F]``), the main-street lane it starts in (``lane_y``) and, for a turn, the x where it
    leaves the main street (``turn_start``, None when straight)."""

    xy: np.ndarray
    yaw: np.ndarray
    crosses: np.ndarray
    turn: str
    points: np.ndarray
    heading: np.ndarray
    dist: np.ndarray
    lane_y: float
    turn_start: float | None


def ego_route(rng, frames: int, fps: float) -> EgoRoute:
    """The ego's smooth route and speed profile (an :class:`EgoRoute`).

    The speed follows random key speeds every ~2 s (cosine-blended, sometimes stopping); a turn
    happens at the first cross street when the clip is long enough to reach it.
    """
    duration = (frames - 1) / fps
    n_keys = max(2, int(np.ceil(duration / 2.0)) + 1)
    keys = np.empty(n_keys)
    keys[0] = 0.0 if rng.random() < 0.1 else rng.uniform(3.0, 12.0)
    for i in range(1, n_keys):
        keys[i] = 0.0 if rng.random() < 0.12 else np.clip(keys[i - 1] + rng.normal(0, 3.0), 1.0, 14.0)
    sub = 8
    t = np.linspace(0.0, duration, (frames - 1) * sub + 1)
    key_t = np.linspace(0.0, max(duration, 1e-9), n_keys)
    seg = np.clip(np.searchsorted(key_t, t, side="right") - 1, 0, n_keys - 2)
    w = (t - key_t[seg]) / (key_t[seg + 1] - key_t[seg])
    w = 0.5 - 0.5 * np.cos(np.pi * np.clip(w, 0, 1))
    turn = ("straight", "left", "right")[rng.choice(3, p=[0.5, 0.25, 0.25])]
    speed = keys[seg] * (1 - w) + keys[seg + 1] * w
    if turn != "straight":
        speed = np.minimum(speed, 7.0)
    dist = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(t))])
    dist = dist[::sub]
    total = dist[-1]
    if total < 12.0:
        turn = "straight"
    start = None
    if turn == "straight":
        lane_y = -LANE / 2 if rng.random() < 0.5 else -1.5 * LANE
        xc = rng.uniform(15.0, 70.0)
        pts, heading = straight_path(lane_y, total)
    else:
        lane_y = -LANE / 2
        start = rng.uniform(0.25, 0.6) * total
        if turn == "left":
            radius = rng.uniform(ROAD + LANE / 2, ROAD + LANE / 2 + 2.0)
            xc = start + radius - LANE / 2
        else:
            radius = rng.uniform(ROAD - LANE / 2, ROAD - LANE / 2 + 1.5)
            xc = start + radius + LANE / 2
        pts, heading = turn_path(start, lane_y, turn, radius)
    xy, yaw = along_path(pts, heading, dist)
    spacing = rng.uniform(80.0, 120.0)
    crosses = np.array([xc - spacing, xc, xc + spacing])
    return EgoRoute(xy, yaw, crosses, turn, pts, heading, dist, float(lane_y), start)


# ------------------------------------------------------------------------------ static scenery


def _frontage(rng, lo, hi, blocked):
    """Random building spans ``[(start, width)]`` along a street between lo and hi, skipping the
    ``blocked`` intervals (other streets' corridors)."""
    spans, pos = [], lo
    while pos < hi:
        width = rng.uniform(8.0, 20.0)
        hit = [b for b in blocked if pos < b[1] and pos + width > b[0]]
        if hit:
            pos = max(b[1] for b in hit)
            continue
        spans.append((pos, width))
        pos += width + rng.uniform(0.5, 5.0)
    return spans


def static_scenery(rng, crosses, xy_route, *, reach: float = 90.0, season: str = "summer"):
    """Buildings, trees (trunk + canopy) and street lamps near the route.

    Returns ``(boxes [S, 7], colours [S, 3], kinds [S])`` in the world frame.
    """
    boxes, colours, kinds = [], [], []
    x_lo, x_hi = xy_route[:, 0].min() - reach, xy_route[:, 0].max() + reach
    y_lo, y_hi = xy_route[:, 1].min() - reach, xy_route[:, 1].max() + reach
    canopy = {
        "summer": (0.22, 0.45, 0.18),
        "spring": (0.35, 0.58, 0.25),
        "autumn": (0.65, 0.38, 0.12),
        "winter": (0.55, 0.55, 0.5),
    }[season]

    def building(cx, cy, along, depth, yaw):
        height = rng.uniform(5.0, 24.0)
        boxes.append((cx, cy, height / 2, along, depth, height, yaw))
        base = rng.choice(
            [(0.62, 0.55, 0.48), (0.55, 0.35, 0.3), (0.7, 0.7, 0.68), (0.45, 0.47, 0.52), (0.78, 0.72, 0.6)]
        )
        colours.append(np.clip(np.array(base) + rng.normal(0, 0.04, 3), 0, 1))
        kinds.append(BUILDING)

    def furniture(cx, cy):
        if rng.random() < 0.6:
            trunk_h = rng.uniform(1.8, 2.8)
            boxes.append((cx, cy, trunk_h / 2, 0.35, 0.35, trunk_h, 0.0))
            colours.append(np.array((0.35, 0.25, 0.16)))
            kinds.append(TRUNK)
            size, height = rng.uniform(2.0, 3.2), rng.uniform(1.8, 3.0)
            boxes.append((cx, cy, trunk_h + height / 2 - 0.2, size, size, height, rng.uniform(0, np.pi)))
            colours.append(np.clip(np.array(canopy) + rng.normal(0, 0.03, 3), 0, 1))
            kinds.append(CANOPY)
        else:
            boxes.append((cx, cy, 3.0, 0.18, 0.18, 6.0, 0.0))
            colours.append(np.array((0.3, 0.3, 0.32)))
            kinds.append(POLE)
            boxes.append((cx, cy, 6.1, 0.6, 0.35, 0.2, 0.0))
            colours.append(np.array((0.9, 0.9, 0.8)))
            kinds.append(LAMP)

    corridor = ROAD + SIDEWALK + 1.0
    blocked_x = [(xc - SETBACK, xc + SETBACK) for xc in crosses]
    for side in (-1.0, 1.0):
        for start, width in _frontage(rng, x_lo, x_hi, blocked_x):
            depth = rng.uniform(8.0, 16.0)
            building(start + width / 2, side * (SETBACK + depth / 2), width, depth, 0.0)
        pos = x_lo + rng.uniform(0, 6)
        while pos < x_hi:
            if np.min(np.abs(pos - np.asarray(crosses))) > corridor:
                furniture(pos, side * (ROAD + SIDEWALK - 0.7))
            pos += rng.uniform(8.0, 16.0)
    for xc in crosses:
        if not x_lo - SETBACK < xc < x_hi + SETBACK:
            continue
        for side in (-1.0, 1.0):
            for start, width in _frontage(rng, y_lo, y_hi, [(-SETBACK, SETBACK)]):
                depth = rng.uniform(8.0, 16.0)
                building(xc + side * (SETBACK + depth / 2), start + width / 2, width, depth, np.pi / 2)
            pos = y_lo + rng.uniform(0, 6)
            while pos < y_hi:
                if abs(pos) > corridor:
                    furniture(xc + side * (ROAD + SIDEWALK - 0.7), pos)
                pos += rng.uniform(8.0, 16.0)
    return (
        np.asarray(boxes, np.float64).reshape(-1, 7),
        np.asarray(colours, np.float64).reshape(-1, 3),
        np.asarray(kinds, np.int32),
    )
