"""Counterfactual ego routes of the synthetic town: the same scene driven another way.

A counterfactual keeps everything of a recorded clip (town, scenery, agents and their paths, look,
light) and replaces the ego's drive from frame ``start`` on by one of :data:`ROUTES`:

- ``recorded``: the clip as generated (bit for bit);
- ``stop``: brake to a standstill (target speed 0, at most 2.5 m/s^2, gentle for the traffic
  behind) and stay;
- ``slower`` / ``faster``: half the recorded speed / ``max(1.5 v, v + 3 m/s)`` capped at 15 m/s,
  along the recorded path;
- ``lane-left`` / ``lane-right``: a lane change of one lane width (:data:`LANE`) to that side along
  the recorded path, over ``clip(2 s x speed, 10 m, 25 m)`` of road, at no less than 4 m/s so the
  change happens. It starts at the first frame (from ``start`` on) where the target lane is free
  from :data:`GAP_BEHIND` metres behind the ego to :data:`GAP_AHEAD` ahead (gap acceptance); a
  clip that never offers the gap cannot drive it. From the main street's
  inner lane ``lane-left`` moves into the oncoming inner lane (an overtaking manoeuvre on the road
  surface); from the outer lane ``lane-right`` leaves the road and is undrivable;
- ``branch``: the other branch at the next intersection: straight on where the recorded ego
  turns, and where it drives straight on, a left turn from the inner lane or a right turn from the
  outer lane at the next cross street ahead (at most 7 m/s on the arc, as recorded turns).

The ego is driven by :class:`EgoDriver` inside the agents' simulation
(:func:`jaxdrive.data.synth_agents.simulate`): it follows its target speed, takes curves at no more
than 3 m/s^2 of lateral acceleration, and brakes for any agent whose footprint lies on its path
ahead (the lane it drives in and the lane it changes to). Agents keep their recorded rules, so an
agent the new ego never meets keeps its recorded path exactly; from ``start`` on the ego blocks
every agent's lane whatever its heading, so followers and oncoming traffic brake for it. This was
chosen over keeping every agent's recorded path and deleting the ones the ego would hit (a
deletion would change the given frames, which every route must share) and over replaying the
recorded paths through the ego (a ground truth with collisions is no future a model should
generate).

A route is undrivable, a ``ValueError`` naming the route and the clip, when the ego's footprint
leaves the drivable road classes, when it drives more than :data:`MAP_MARGIN` metres beyond the
recorded route's bounding box (the town is built around the recorded route: past it there are no
buildings), when it still touches an agent, or for ``branch`` when the clip reaches no
intersection after ``start``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxdrive.data.synth_agents import EGO_CENTRE, EGO_SIZE, overlaps, rect_corners
from jaxdrive.data.synth_world import LANE, ROAD, EgoRoute, along_path, road_classes, straight_path, turn_path

ROUTES = ("recorded", "stop", "slower", "faster", "lane-left", "lane-right", "branch")
MAP_MARGIN = 40.0  # metres the ego may drive beyond the recorded route's bounding box
LANE_CHANGE_SECONDS = 2.0
GAP_BEHIND, GAP_AHEAD = 8.0, 12.0  # metres of free target lane a lane change waits for
TURN_SPEED = 7.0  # the synthetic world's speed cap on turn arcs (as ego_route)
LATERAL_ACCEL = 3.0  # m/s^2 in curves
ACCEL, BRAKE, HARD_BRAKE = 2.5, 2.5, 7.0  # m/s^2 of the driven ego: comfortable, and for an obstacle
LOOKAHEAD = np.arange(0.5, 40.0, 0.5)  # metres along the path checked for obstacles


def parse_routes(routes, option: str, *, recorded: bool = True) -> list[str]:
    """Route names from a comma-separated string (or a sequence): distinct names of :data:`ROUTES`
    (without ``recorded`` unless ``recorded``); ``ValueError`` naming ``option`` otherwise."""
    names = [n.strip() for n in (routes.split(",") if isinstance(routes, str) else routes) if n.strip()]
    allowed = ROUTES if recorded else ROUTES[1:]
    if any(n not in allowed for n in names) or len(set(names)) != len(names):
        raise ValueError(
            f"{option}: expected distinct comma-separated routes from {', '.join(allowed)}, got {routes!r}"
        )
    return names


class UndrivableRoute(ValueError):
    """A counterfactual route the scene cannot drive (a ``ValueError``)."""


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


@dataclasses.dataclass
class EgoDriver:
    """Drives the ego along ``points`` / ``heading`` (a polyline) from frame ``start`` on, at the
    per-frame target speed ``target [F]``, braking for agents on its path, and (``shift`` metres,
    left positive, over ``shift_length`` metres of road) changes lanes once the target lane is free.
    The state starts at the recorded arc length ``s`` and speed ``v`` of frame ``start - 1``;
    ``lateral [F]`` records the offset from the path driven at each frame."""

    start: int
    fps: float
    points: np.ndarray
    heading: np.ndarray
    target: np.ndarray
    s: float
    v: float
    shift: float = 0.0
    shift_length: float = 1.0

    def __post_init__(self):
        seglen = np.linalg.norm(np.diff(self.points, axis=0), axis=-1)
        self._cum = np.concatenate([[0.0], np.cumsum(seglen)])
        self.lateral = np.zeros(len(self.target))
        self.shift_from = None if self.shift else -np.inf  # arc length where the lane change began

    def _offset(self, s):
        if self.shift_from is None:
            return 0.0
        return self.shift * float(_smoothstep((s - self.shift_from) / self.shift_length))

    def _footprints(self, s, lateral):
        xy, yaw = self._pose(s, lateral)
        centre = xy + EGO_CENTRE * np.stack([np.cos(yaw), np.sin(yaw)], -1)
        return rect_corners(centre, yaw, np.full_like(yaw, EGO_SIZE[0]), np.full_like(yaw, EGO_SIZE[1]))

    def _pose(self, s, lateral):
        xy, yaw = along_path(self.points, self.heading, s)
        normal = np.stack([-np.sin(yaw), np.cos(yaw)], -1)
        return xy + np.asarray(lateral)[..., None] * normal, yaw

    def _curvature_cap(self, s):
        ahead = s + LOOKAHEAD[LOOKAHEAD <= 15.0]
        h = np.interp(np.concatenate([[s], ahead]), self._cum, self.heading)
        kappa = np.abs(np.diff(h)).max() / 0.5
        return np.inf if kappa < 1e-6 else np.sqrt(LATERAL_ACCEL / kappa)

    def _obstacle_distance(self, agents, lateral):
        """Distance along the path to the first point where the ego's footprint at offset
        ``lateral`` would touch one of the ``agents`` rectangles as they stand now (inf: free)."""
        if len(agents) == 0:
            return np.inf
        ego = self._footprints(self.s + LOOKAHEAD, np.full(len(LOOKAHEAD), lateral))
        hit = overlaps(ego[:, None], agents[None]).any(1)  # [L]
        return float(LOOKAHEAD[np.argmax(hit)]) if hit.any() else np.inf

    def _gap_free(self, agents):
        if len(agents) == 0:
            return True
        along = np.arange(-GAP_BEHIND, GAP_AHEAD + 0.1, 1.0)
        ego = self._footprints(self.s + along, np.full(len(along), self.shift))
        return not overlaps(ego[:, None], agents[None]).any()

    def step(self, f, agents_xy, agents_yaw, sizes):
        """The ego's pose at frame ``f`` from its state at ``f - 1`` and the agents at ``f - 1``."""
        dt = 1.0 / self.fps
        agents = rect_corners(agents_xy, agents_yaw, sizes[:, 0] + 0.4, sizes[:, 1] + 0.4)  # [N, 4, 2]
        if self.shift_from is None and self._gap_free(agents):
            self.shift_from = self.s
        target = min(float(self.target[f]), self._curvature_cap(self.s))
        lanes = {self._offset(self.s), self._offset(self.s + LOOKAHEAD[-1])}
        d_hit = min(self._obstacle_distance(agents, lat) for lat in lanes)
        brake = BRAKE
        if np.isfinite(d_hit):
            free = max(0.0, d_hit - 2.0)
            if min(free / 1.2, np.sqrt(2 * BRAKE * free)) < target:
                target, brake = min(free / 1.2, np.sqrt(2 * BRAKE * free)), HARD_BRAKE
        s_prev, lat_prev = self.s, self._offset(self.s)
        self.v = max(0.0, self.v + float(np.clip((target - self.v) / 0.6, -brake, ACCEL)) * dt)
        self.s += self.v * dt
        self.lateral[f] = self._offset(self.s)
        xy, yaw = self._pose(self.s, self.lateral[f])
        return xy, yaw + np.arctan2(self.lateral[f] - lat_prev, max(self.s - s_prev, 1e-6))


def _recorded_speed(rec: EgoRoute, fps: float) -> np.ndarray:
    v = np.diff(rec.dist, prepend=rec.dist[:1]) * fps
    v[0] = v[1] if len(v) > 1 else 0.0
    return v


def _branch_path(rec: EgoRoute, s0: float, route: str, clip: str):
    """The polyline of the other branch, or UndrivableRoute when no intersection lies ahead."""
    if rec.turn != "straight":
        if s0 >= rec.turn_start:
            raise UndrivableRoute(
                f"route {route!r}: expected clip {clip} to reach its turn after the route's "
                f"start, got the ego {s0 - rec.turn_start:.1f} m past it"
            )
        return straight_path(rec.lane_y, rec.dist[-1] + 100.0), "straight"
    turn = "left" if rec.lane_y > -LANE else "right"
    radius = ROAD + LANE / 2 + 1.0 if turn == "left" else ROAD - LANE / 2 + 0.75
    ends = rec.crosses + (LANE / 2 if turn == "left" else -LANE / 2)
    starts = ends - radius
    ahead = starts[starts > s0 + 1.0]
    if len(ahead) == 0 or ahead.min() > rec.dist[-1]:
        raise UndrivableRoute(
            f"route {route!r}: expected clip {clip} to reach an intersection after the route's "
            f"start, got none within the {rec.dist[-1] - s0:.1f} m it drives"
        )
    return turn_path(float(ahead.min()), rec.lane_y, turn, radius), turn


def plan(route: str, rec: EgoRoute, fps: float, start: int, *, clip: str = "") -> EgoDriver | None:
    """The :class:`EgoDriver` of ``route`` (None for ``recorded``)."""
    if route not in ROUTES:
        raise ValueError(f"route: expected one of {', '.join(ROUTES)}, got {route!r}")
    if route == "recorded":
        return None
    frames = len(rec.dist)
    if not 1 <= start < frames:
        raise ValueError(f"start: expected a frame in [1, {frames - 1}] for a clip of {frames} frames, got {start}")
    v_rec = _recorded_speed(rec, fps)
    target = v_rec.copy()
    points, heading = rec.points, rec.heading
    s0 = float(rec.dist[start - 1])
    after = np.arange(frames) >= start
    if route == "stop":
        target[after] = 0.0
    elif route == "slower":
        target[after] = 0.5 * v_rec[after]
    elif route == "faster":
        target[after] = np.minimum(np.maximum(1.5 * v_rec[after], v_rec[after] + 3.0), 15.0)
    elif route in ("lane-left", "lane-right"):
        target[after] = np.maximum(v_rec[after], 4.0)
        shift = LANE if route == "lane-left" else -LANE
        length = float(np.clip(LANE_CHANGE_SECONDS * max(v_rec[start - 1], 4.0), 10.0, 25.0))
        return EgoDriver(start, fps, points, heading, target, s0, float(v_rec[start - 1]), shift, length)
    else:
        (points, heading), _ = _branch_path(rec, s0, route, clip)
        target[after] = np.minimum(v_rec[after], TURN_SPEED)
    return EgoDriver(start, fps, points, heading, target, s0, float(v_rec[start - 1]))


def check_drivable(
    route: str,
    clip: str,
    rec: EgoRoute,
    driver: EgoDriver,
    ego_xy,
    ego_yaw,
    agents_xy,
    agents_yaw,
    agent_sizes,
    track_ids,
) -> None:
    """``UndrivableRoute`` naming the route, the clip and the first bad frame when the driven ego
    leaves the road or the map, touches an agent, or (``branch``) never reaches its new branch."""
    f0 = driver.start
    xy, yaw = ego_xy[f0:], ego_yaw[f0:]
    centre = xy + EGO_CENTRE * np.stack([np.cos(yaw), np.sin(yaw)], -1)
    ego = rect_corners(centre, yaw, np.full_like(yaw, EGO_SIZE[0]), np.full_like(yaw, EGO_SIZE[1]))  # [F, 4, 2]
    on_road = road_classes(ego[..., 0], ego[..., 1], rec.crosses)[..., 0].all(-1)
    if not on_road.all():
        f = f0 + int(np.argmin(on_road))
        raise UndrivableRoute(
            f"route {route!r}: expected clip {clip} to stay on the road, got the ego off the "
            f"drivable area at frame {f} (x = {ego_xy[f, 0]:.1f}, y = {ego_xy[f, 1]:.1f} m)"
        )
    lo, hi = rec.xy.min(0) - MAP_MARGIN, rec.xy.max(0) + MAP_MARGIN
    inside = ((xy >= lo) & (xy <= hi)).all(-1)
    if not inside.all():
        f = f0 + int(np.argmin(inside))
        raise UndrivableRoute(
            f"route {route!r}: expected clip {clip} to stay within {MAP_MARGIN:.0f} m of the "
            f"recorded route (the town's extent), got the ego out of the map at frame {f}"
        )
    if len(agent_sizes):
        size = np.asarray(agent_sizes)
        rects = rect_corners(
            agents_xy[f0:], np.broadcast_to(agents_yaw, agents_xy[f0:].shape[:2]), size[:, 0], size[:, 1]
        )  # [F, N, 4, 2]
        touch = overlaps(rects, ego[:, None])  # [F, N]
        if touch.any():
            f, n = np.argwhere(touch)[0]
            raise UndrivableRoute(
                f"route {route!r}: expected clip {clip} to be driven without a collision, got "
                f"the ego touching agent {int(track_ids[n])} at frame {f0 + int(f)}"
            )
    if driver.shift and driver.shift_from is None:
        raise UndrivableRoute(
            f"route {route!r}: expected clip {clip} to offer a free gap in the target lane before it ends, got none"
        )
    if route == "branch":
        diverged = np.linalg.norm(ego_xy - rec.xy, axis=-1).max()
        if diverged < 0.5:
            raise UndrivableRoute(
                f"route {route!r}: expected clip {clip} to reach its other branch before the "
                f"clip ends, got a drive within {diverged:.2f} m of the recorded one"
            )
