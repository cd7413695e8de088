"""Colours of the synthetic town: looks (day, night, rain), ground texture, cuboid shading, fog and
rain streaks. Works on the ray caster's per-pixel outputs (:mod:`jaxdrive.data.synth_render`).
"""

from __future__ import annotations

import numpy as np

from jaxdrive.classes import OBJECT_CLASSES
from jaxdrive.data.synth_world import AGENT_KIND, BUILDING, LAMP, ROAD, nearest_cross, road_classes

LOOKS = {
    "day": dict(
        sky_top=(0.33, 0.55, 0.88),
        sky_horizon=(0.78, 0.86, 0.95),
        ambient=0.55,
        sun=0.55,
        fog=(0.8, 0.86, 0.93),
        fog_dist=260.0,
        asphalt=0.34,
    ),
    "night": dict(
        sky_top=(0.005, 0.008, 0.03),
        sky_horizon=(0.05, 0.06, 0.1),
        ambient=0.12,
        sun=0.04,
        fog=(0.03, 0.035, 0.06),
        fog_dist=110.0,
        asphalt=0.3,
    ),
    "rain": dict(
        sky_top=(0.42, 0.44, 0.47),
        sky_horizon=(0.6, 0.62, 0.65),
        ambient=0.5,
        sun=0.12,
        fog=(0.55, 0.57, 0.6),
        fog_dist=75.0,
        asphalt=0.2,
    ),
}
DAYTIME = {"day": "daytime", "night": "night", "rain": "rainy daytime"}
_GRASS = {
    "summer": (0.3, 0.42, 0.2),
    "spring": (0.34, 0.5, 0.24),
    "autumn": (0.42, 0.4, 0.22),
    "winter": (0.82, 0.83, 0.86),
}
_VEHICLES = tuple(
    OBJECT_CLASSES.index(n) for n in ("car", "truck", "construction_vehicle", "bus", "trailer", "motorcycle")
)
_PED = OBJECT_CLASSES.index("pedestrian")


def _hash(*xs):
    """Deterministic pseudo-random value in [0, 1) from coordinates (elementwise)."""
    h = np.zeros(np.broadcast_shapes(*(np.shape(x) for x in xs)))
    for i, x in enumerate(xs):
        h = h + np.asarray(x, np.float64) * (12.9898 + 65.233 * i)
    return np.modf(np.abs(np.sin(h) * 43758.5453))[0]


def _frac(x):
    return x - np.floor(x)


def ground_colour(xw, yw, crosses, look, season):
    """Albedo ``[..., 3]`` of the ground at world points: road, markings, sidewalk, verge."""
    cls = road_classes(xw, yw, crosses)
    drivable, crossing, walkway, stop, _, road_div, lane_div, _ = np.moveaxis(cls, -1, 0)
    col = np.empty(np.shape(xw) + (3,))
    col[:] = _GRASS[season]
    paved = (np.abs(yw) > ROAD + 5.0) & (np.abs(nearest_cross(xw, crosses)) > ROAD + 5.0)
    col[paved] = (0.5, 0.48, 0.45)
    col[walkway] = (0.62, 0.6, 0.57)
    col[drivable] = LOOKS[look]["asphalt"]
    on_main = np.abs(yw) < ROAD
    stripes = _frac(np.where(on_main, yw, xw) / 1.2) < 0.5
    white = (lane_div & (_frac((xw + yw) / 6.0) < 0.5)) | stop | (crossing & stripes)
    col[white] = (0.88, 0.88, 0.86)
    col[road_div] = (0.9, 0.75, 0.2)
    noise = (_hash(np.floor(xw * 4), np.floor(yw * 4)) - 0.5) * 0.06
    return col + noise[..., None]


def sky_colour(dir_world, look):
    p = LOOKS[look]
    elev = dir_world[..., 2] / np.linalg.norm(dir_world, axis=-1)
    w = np.clip(elev * 3.0, 0.0, 1.0)[..., None]
    return np.array(p["sky_horizon"]) * (1 - w) + np.array(p["sky_top"]) * w


def box_colour(owner, axis, local, boxes, colours, kinds, classes, box_key, light, look):
    """Shaded colour ``[P, 3]`` of box hits (``owner`` box indices, the hit ``axis`` and ``local``
    point). ``classes`` are object class ids (-1 for scenery); ``box_key`` a stable per-box number
    for window patterns."""
    p = LOOKS[look]
    night = look == "night"
    local = local.astype(np.float32)
    coord = np.take_along_axis(local, axis[:, None], 1)[:, 0]
    sign = np.where(coord >= 0, np.float32(1), np.float32(-1))
    # World normal of the face: the box's yaw turns local axes 0, 1; axis 2 is vertical.
    yaw = (boxes[:, 6] + np.pi / 2 * np.arange(2)[:, None]).T  # [B, 2]: heading of axes 0, 1
    face_yaw = np.take_along_axis(yaw[owner], np.minimum(axis, 1)[:, None], 1)[:, 0]
    side = axis != 2
    lambert_side = (np.cos(face_yaw) * light[0] + np.sin(face_yaw) * light[1]) * sign
    nz = np.where(side, 0.0, sign)
    lambert = np.clip(np.where(side, lambert_side, nz * light[2]), 0.0, None).astype(np.float32)
    shade = p["ambient"] * (0.8 + 0.2 * nz) + p["sun"] * lambert
    col = colours.astype(np.float32)[owner] * shade[:, None].astype(np.float32)
    emit = np.zeros_like(col)
    kind, cls = kinds[owner], classes[owner]
    half_h = (boxes[:, 5] / 2).astype(np.float32)[owner]
    zg = local[:, 2] + half_h
    # Buildings: a grid of windows on the walls, some lit at night.
    bld = np.flatnonzero((kind == BUILDING) & side)
    along = np.where(axis[bld] == 0, local[bld, 1], local[bld, 0])
    fa, fz = _frac(along / 3.0), _frac(zg[bld] / 3.2)
    win = (fa > 0.25) & (fa < 0.75) & (fz > 0.35) & (fz < 0.8) & (zg[bld] > 1.2) & (zg[bld] < 2 * half_h[bld] - 0.6)
    wi = bld[win]
    if night:
        col[wi] = (0.04, 0.04, 0.06)
        lit = _hash(np.floor(along[win] / 3.0), np.floor(zg[wi] / 3.2), box_key[owner[wi]]) < 0.35
        emit[wi[lit]] = (0.95, 0.8, 0.5)
        emit[kind == LAMP] = (1.0, 0.95, 0.8)
    else:
        col[wi] = np.array((0.2, 0.26, 0.36), np.float32) * (0.6 + 0.6 * lambert[wi, None])
    # Vehicles: a glass band, head lights at the front, red lights at the back.
    veh = np.flatnonzero((kind >= AGENT_KIND) & np.isin(cls, _VEHICLES) & side)
    if len(veh):
        h, z = 2 * half_h[veh], zg[veh]
        band = veh[(z > 0.58 * h) & (z < 0.88 * h)]
        col[band] = np.array((0.1, 0.12, 0.16), np.float32) * (0.5 + lambert[band, None])
        half_w = (boxes[owner[veh], 4] / 2).astype(np.float32)
        lamp = (axis[veh] == 0) & (z > 0.25 * h) & (z < 0.42 * h) & (np.abs(local[veh, 1]) > 0.55 * half_w)
        front, rear = veh[lamp & (sign[veh] > 0)], veh[lamp & (sign[veh] < 0)]
        col[front] = (0.85, 0.85, 0.8)
        col[rear] = (0.7, 0.06, 0.05)
        if night:
            emit[front] = (1.2, 1.2, 1.0)
            emit[rear] = (0.9, 0.05, 0.03)
    # Pedestrians: darker legs, a light head.
    ped = np.flatnonzero((kind >= AGENT_KIND) & (cls == _PED))
    if len(ped):
        h, z = 2 * half_h[ped], zg[ped]
        legs, head = ped[z < 0.48 * h], ped[z > 0.86 * h]
        col[legs] *= 0.45
        col[head] = np.array((0.82, 0.66, 0.52), np.float32) * shade[head, None]
    return col + emit


def ego_headlights(x_ego, y_ego):
    """Extra light on the ground in front of the ego (ego-frame ground points) at night."""
    x = x_ego - 3.0
    cone = np.exp(-((y_ego / (0.45 * np.maximum(x, 0.0) + 1.0)) ** 2))
    return np.where(x > 0, cone * np.clip(x / 3.0, 0, 1) * np.exp(-x / 30.0), 0.0) * 1.6


def lamp_light(xw, yw, lamps_xy):
    """Pools of light under street lamps ``[L, 2]`` at world ground points (night)."""
    out = np.zeros(np.shape(xw))
    for lx, ly in lamps_xy:
        out += 0.5 * np.exp(-((xw - lx) ** 2 + (yw - ly) ** 2) / 30.0)
    return out


def fog(col, depth, look):
    p = LOOKS[look]
    keep = np.exp(-np.where(np.isfinite(depth), depth, 1e9) / p["fog_dist"])[..., None]
    return col * keep + np.array(p["fog"]) * (1 - keep)


def rain_streaks(rng, video):
    """Blend short bright slanted streaks into float ``video [V, F, H, W, 3]`` in place; darken."""
    nv, nf, height, width, _ = video.shape
    video *= 0.85
    n = max(1, height * width // 45)
    length = max(2, height // 10)
    img = np.repeat(np.arange(nv * nf), n)
    r = rng.integers(-length, height, size=nv * nf * n)
    c = rng.integers(0, width + length, size=nv * nf * n)
    i = np.arange(length)
    rr = r[:, None] + i
    cc = c[:, None] - np.round(0.35 * i).astype(int)
    ok = (rr >= 0) & (rr < height) & (cc >= 0) & (cc < width)
    flat = video.reshape(nv * nf, height, width, 3)
    sel = (np.broadcast_to(img[:, None], rr.shape)[ok], rr[ok], cc[ok])
    flat[sel] = 0.65 * flat[sel] + 0.35 * np.array((0.85, 0.86, 0.9))
    return video
