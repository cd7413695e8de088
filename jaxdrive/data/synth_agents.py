"""Traffic of the synthetic town: agents that follow lanes (pedestrians: sidewalks), keep their
distance to the agent (or the ego) ahead, stop at random times and at stop lines.

A lane is a straight line ``p = origin + s * direction`` (world frame, see
:mod:`jaxdrive.data.synth_world`). Agents whose footprints ever overlap another agent's or the
ego's are dropped and replaced by fresh samples, so the clip never shows collisions and no camera
ever sits inside an agent.
"""

from __future__ import annotations

import numpy as np

from jaxdrive.classes import OBJECT_CLASSES
from jaxdrive.data.synth_world import LANE, ROAD, SIDEWALK, STOP

# class name -> (probability, (length, width, height), cruise speed range m/s)
_CLASSES = {
    "car": (0.52, (4.5, 1.9, 1.6), (6.0, 13.0)),
    "truck": (0.08, (7.5, 2.5, 3.2), (5.0, 10.0)),
    "bus": (0.05, (11.5, 2.6, 3.3), (5.0, 9.0)),
    "motorcycle": (0.06, (2.1, 0.8, 1.5), (6.0, 12.0)),
    "bicycle": (0.06, (1.8, 0.6, 1.7), (3.0, 6.0)),
    "pedestrian": (0.23, (0.6, 0.6, 1.75), (0.9, 1.7)),
}
_NAMES = tuple(_CLASSES)
_PROBS = np.array([c[0] for c in _CLASSES.values()])
_PROBS = _PROBS / _PROBS.sum()

EGO_SIZE = (4.6, 1.95, 1.7)
EGO_CENTRE = 1.3  # the ego box centre lies this far ahead of the ego origin (rear axle)


def _lanes(name, xc):
    """Candidate lanes ``(origin, direction, stop_s)`` for a class; ``stop_s`` is the lane position
    of a stop line the agent must not pass (inf if none)."""
    inf = np.inf
    if name == "pedestrian":
        off = ROAD + 1.2
        return [((0.0, s * off), (d, 0.0), inf) for s in (-1, 1) for d in (-1.0, 1.0)]
    if name in ("bicycle", "motorcycle"):
        main = [((0.0, -(ROAD - 1.0)), (1.0, 0.0), inf), ((0.0, ROAD - 1.0), (-1.0, 0.0), inf)]
    else:
        main = [((0.0, -o), (1.0, 0.0), inf) for o in (LANE / 2, 1.5 * LANE)]
        main += [((0.0, o), (-1.0, 0.0), inf) for o in (LANE / 2, 1.5 * LANE)]
    # Cross street at xc: lanes x > xc head +y (approach from y < 0), lanes x < xc head -y.
    cross = [((xc + o, 0.0), (0.0, 1.0), -STOP) for o in (LANE / 2, 1.5 * LANE)]
    cross += [((xc - o, 0.0), (0.0, -1.0), -STOP) for o in (LANE / 2, 1.5 * LANE)]
    return main + cross


def sample_agents(rng, count, xc, route_xy):
    """``count`` random agents near the route: dicts of lane, start, speeds, size, stop window."""
    x_lo, x_hi = route_xy[:, 0].min() - 30.0, route_xy[:, 0].max() + 60.0
    out = []
    for _ in range(count):
        name = _NAMES[rng.choice(len(_NAMES), p=_PROBS)]
        _, size, (v_lo, v_hi) = _CLASSES[name]
        lanes = _lanes(name, xc)
        origin, direction, stop_s = lanes[rng.integers(len(lanes))]
        origin, direction = np.array(origin), np.array(direction)
        if direction[1] == 0.0:  # along the main street: s = x * direction_x
            s0 = rng.uniform(x_lo, x_hi) * direction[0]
        elif rng.random() < 0.5:  # cross street, approaching the main street
            s0 = -rng.uniform(STOP + 3.0, 60.0)
        else:  # cross street, leaving the main street
            s0, stop_s = rng.uniform(ROAD + SIDEWALK, 60.0), np.inf
        jitter = 1.0 + rng.uniform(-0.08, 0.08, 3)
        stop_window = (np.inf, np.inf)
        if rng.random() < 0.3:
            t0 = rng.uniform(0.0, 3.0)
            stop_window = (t0, t0 + rng.uniform(0.5, 4.0))
        out.append(
            dict(
                cls=OBJECT_CLASSES.index(name),
                name=name,
                origin=origin,
                direction=direction,
                s0=s0,
                v0=rng.uniform(0.0, 1.0) * v_hi if rng.random() < 0.3 else rng.uniform(v_lo, v_hi),
                cruise=rng.uniform(v_lo, v_hi),
                size=np.array(size) * jitter,
                stop_s=stop_s,
                stop_window=stop_window,
            )
        )
    return out


def simulate(agents, ego_xy, ego_yaw, fps, *, driver=None):
    """Roll the agents out over the ego's frames -> ``(xy [F, N, 2], yaw [N])`` world frame.

    ``driver`` (optional, a :class:`jaxdrive.data.synth_routes.EgoDriver`) drives the ego from its
    frame ``driver.start`` on, reacting to the agents, instead of replaying ``ego_xy`` / ``ego_yaw``;
    from then on every agent (pedestrians aside) treats the ego as an obstacle in its lane whatever
    the ego's heading, so that traffic brakes for an ego that changes lanes or turns across it.
    Before ``driver.start`` the arithmetic is exactly the recorded run's. Returns the ego's
    driven ``(xy, yaw)`` too when a driver is given."""
    frames, n = len(ego_xy), len(agents)
    if driver is not None:
        ego_xy, ego_yaw = np.array(ego_xy, np.float64), np.array(ego_yaw, np.float64)
    if n == 0:
        xy, yaw = np.zeros((frames, 0, 2)), np.zeros((0,))
        if driver is None:
            return xy, yaw
        for f in range(driver.start, frames):
            ego_xy[f], ego_yaw[f] = driver.step(f, xy[f - 1], yaw, np.zeros((0, 2)))
        return xy, yaw, ego_xy, ego_yaw
    dt = 1.0 / fps
    origin = np.stack([a["origin"] for a in agents])
    direction = np.stack([a["direction"] for a in agents])
    length = np.array([a["size"][0] for a in agents])
    sizes = np.stack([a["size"][:2] for a in agents])
    cruise = np.array([a["cruise"] for a in agents])
    stop_s = np.array([a["stop_s"] for a in agents])
    window = np.array([a["stop_window"] for a in agents])
    ped = np.array([a["name"] == "pedestrian" for a in agents])
    accel = np.where(ped, 1.0, 2.0)
    brake = np.where(ped, 2.0, 4.5)
    gap0 = np.where(ped, 0.6, 2.0)
    # Lane identity: same origin line and direction.
    key = np.round(np.concatenate([origin * (1 - np.abs(direction)), direction], 1), 3)
    same = (key[:, None, :] == key[None, :, :]).all(-1) & ~np.eye(n, dtype=bool)
    yaw = np.arctan2(direction[:, 1], direction[:, 0])
    s = np.array([a["s0"] for a in agents], np.float64)
    v = np.array([a["v0"] for a in agents], np.float64)
    xy = np.zeros((frames, n, 2))
    for f in range(frames):
        xy[f] = origin + s[:, None] * direction
        driven = driver is not None and f >= driver.start
        if driven:
            ego_xy[f], ego_yaw[f] = driver.step(f, xy[f - 1], yaw, sizes)
        t = f * dt
        # Leaders: agents in the same lane ahead, and the ego when it drives in this lane.
        ahead = s[None, :] - s[:, None]
        gap = np.where(same & (ahead > 0), ahead - 0.5 * (length[:, None] + length[None, :]), np.inf)
        gap = gap.min(1)
        ego_c = ego_xy[f] + EGO_CENTRE * np.array([np.cos(ego_yaw[f]), np.sin(ego_yaw[f])])
        rel = ego_c - origin
        s_e = (rel * direction).sum(1)
        lat = np.abs(rel[:, 0] * direction[:, 1] - rel[:, 1] * direction[:, 0])
        aligned = np.cos(ego_yaw[f]) * direction[:, 0] + np.sin(ego_yaw[f]) * direction[:, 1] > 0.7
        if driven:
            aligned = np.ones_like(aligned)
        in_lane = (lat < 1.6) & aligned & (s_e > s) & ~ped
        gap = np.where(in_lane, np.minimum(gap, s_e - s - 0.5 * (length + EGO_SIZE[0])), gap)
        target = np.where((t >= window[:, 0]) & (t < window[:, 1]), 0.0, cruise)
        target = np.minimum(target, np.maximum(0.0, gap - gap0) / 1.2)
        to_stop = stop_s - (s + 0.5 * length)
        target = np.where(to_stop > -0.5, np.minimum(target, np.sqrt(2 * brake * np.maximum(to_stop, 0.0))), target)
        v = np.clip(v + np.clip((target - v) / 0.6, -brake, accel) * dt, 0.0, None)
        s = s + v * dt
        s = np.where(np.isfinite(gap), np.minimum(s, s + np.maximum(gap, 0.0) - 0.3), s)
    if driver is None:
        return xy, yaw
    return xy, yaw, ego_xy, ego_yaw


def rect_corners(xy, yaw, length, width):
    c, s = np.cos(yaw), np.sin(yaw)
    fx, fy = c * length / 2, s * length / 2
    lx, ly = -s * width / 2, c * width / 2
    signs = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]])
    return np.stack(
        [
            xy[..., 0, None] + signs[:, 0] * fx[..., None] + signs[:, 1] * lx[..., None],
            xy[..., 1, None] + signs[:, 0] * fy[..., None] + signs[:, 1] * ly[..., None],
        ],
        -1,
    )


def overlaps(rects_a, rects_b):
    """Separating-axis test of oriented rectangles ``[..., 4, 2]`` (broadcast) -> bool [...]."""
    sep = np.zeros(np.broadcast_shapes(rects_a.shape[:-2], rects_b.shape[:-2]), bool)
    for rects in (rects_a, rects_b):
        for i in range(2):
            axis = rects[..., i + 1, :] - rects[..., i, :]
            pa = (rects_a * axis[..., None, :]).sum(-1)
            pb = (rects_b * axis[..., None, :]).sum(-1)
            sep |= (pa.max(-1) < pb.min(-1)) | (pb.max(-1) < pa.min(-1))
    return ~sep


def colliding(agents, xy, yaw, ego_xy, ego_yaw, margin=0.4):
    """Indices of agents that touch the ego or another agent in some frame."""
    n = len(agents)
    if n == 0:
        return np.zeros(0, int)
    size = np.stack([a["size"] for a in agents])
    rects = rect_corners(xy, np.broadcast_to(yaw, xy.shape[:2]), size[:, 0] + margin, size[:, 1] + margin)
    ego_c = ego_xy + EGO_CENTRE * np.stack([np.cos(ego_yaw), np.sin(ego_yaw)], -1)
    ego = rect_corners(
        ego_c, ego_yaw, np.full_like(ego_yaw, EGO_SIZE[0] + 1.0), np.full_like(ego_yaw, EGO_SIZE[1] + 0.8)
    )
    bad = overlaps(rects, ego[:, None]).any(0)
    pair = overlaps(rects[:, :, None], rects[:, None, :]).any(0) & ~np.eye(n, dtype=bool)
    # Drop the later-sampled agent of each colliding pair.
    bad |= np.triu(pair, 1).any(0)
    return np.flatnonzero(bad)


def traffic(rng, count, xc, ego_xy, ego_yaw, fps, attempts: int = 40):
    """Sample, simulate and de-collide ``count`` agents (fewer only if attempts run out)."""
    agents: list = []
    xy, yaw = simulate(agents, ego_xy, ego_yaw, fps)
    for _ in range(attempts):
        if len(agents) >= count:
            break
        agents += sample_agents(rng, count - len(agents), xc, ego_xy)
        while True:
            xy, yaw = simulate(agents, ego_xy, ego_yaw, fps)
            bad = colliding(agents, xy, yaw, ego_xy, ego_yaw)
            if len(bad) == 0:
                break
            agents = [a for i, a in enumerate(agents) if i not in set(bad.tolist())]
    return agents, xy, yaw
