"""User-given routes for driving beyond the log: ``jaxdrive sample --route SPEC``.

A route is the ego's path in the first frame's ego frame (x forward, y left, metres), with the
time each point is passed: :class:`Route` ``points [K, 2]`` and ``times [K]`` (seconds from the
first frame). ``SPEC`` is one of

- a JSON file: ``{"points": [[x, y], ...], "times": [t, ...]}`` (``times`` optional), or a list
  of ``[x, y]`` / ``[x, y, t]`` rows, or a list of ``{"x": .., "y": .., "t": ..}`` objects;
- a CSV file with a header naming the columns ``x, y`` and optionally ``t``;
- a named manoeuvre: ``"straight [V m/s]"`` (default 10 m/s), ``"left turn [V m/s]"`` /
  ``"right turn [V m/s]"`` (default 8 m/s: a quarter circle of radius 15 m, then straight on) or
  ``"stop [V m/s]"`` (braking from V, default 10 m/s, at 3 m/s^2, then standing).

Without times, the points are spread evenly over the clip. :meth:`Route.poses` gives the dense ego
pose per frame (:func:`jaxdrive.warp.trajectory_poses`, LongDWM [2506.01546v1] appendix A.1). Bad input is a
``ValueError`` naming the file and the row.

On the scene's map (:func:`drive_on_map`, what ``jaxdrive sample --route`` runs for each clip):
a turn starts at the next intersection ahead, the first place within the frames generated where
the ego, driving straight on, can turn with the whole arc on the road; with none in reach it turns
where the clip is, as the manoeuvre alone says, with one warning. A manoeuvre that drives
beyond the seen map (a long clip, a turn off the recorded path) runs with one warning: its BEV
map controls are blank there. A route file whose path runs more than :data:`OFF_ROAD_METRES` off
the road is a ``ValueError`` naming the file and where it
leaves the road, unless ``allow_off_road``. A map with no road at all (nuScenes without its map
expansion) leaves the route unchecked, with one warning.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import re
import warnings
from pathlib import Path

import numpy as np

TURN_RADIUS = 15.0  # metres: a quarter circle at an urban intersection
BRAKING = 3.0  # m/s^2: a firm, comfortable stop
DEFAULT_SPEED = {"straight": 10.0, "left turn": 8.0, "right turn": 8.0, "stop": 10.0}
TURNS = ("left turn", "right turn")
# a route file may leave the road for this much of its path in one stretch (a wide corner, a lane
# edge on the map's cells) before it is refused; jaxdrive sample --allow-off-road drives it anyway
OFF_ROAD_METRES = 3.0
TURN_MARGIN = 1.0  # metres either side of a turn's path that must be road too: half a car
TURN_EXIT = 5.0  # metres after the arc that must be road: the turn ends on a street
SEARCH_STEP = 0.5  # metres between the turn starts tried
_MANOEUVRE = re.compile(r"^\s*(straight|left turn|right turn|stop)\s*(?:([0-9]*\.?[0-9]+)\s*m/s)?\s*$", re.I)


@dataclasses.dataclass(frozen=True)
class Route:
    """The ego's path: ``points [K, 2]`` (x forward, y left, metres, in the first frame's ego
    frame) passed at ``times [K]`` seconds (None: evenly over the clip); ``source`` names where
    it came from, for messages."""

    points: np.ndarray
    times: np.ndarray | None = None
    source: str = "route"
    first_row: int | None = None  # the file row of the first point (None: a manoeuvre)
    manoeuvre: str | None = None  # the named manoeuvre, its speed (m/s) and the metres it
    speed: float | None = None  # drives straight on before it begins (a turn placed at
    lead: float = 0.0  # an intersection ahead)

    def frame_times(self, frames: int, fps: float) -> np.ndarray:
        """The frame (a float) at which each point is passed in a clip of ``frames`` at ``fps``."""
        if self.times is None:
            return np.linspace(0.0, frames - 1, len(self.points))
        return np.asarray(self.times, np.float64) * fps

    def poses(self, frames: int, fps: float) -> np.ndarray:
        """Ego poses ``[frames, 4, 4]`` along the route (frames after its last point stay there)."""
        from jaxdrive.warp import trajectory_poses

        if not fps > 0:
            raise ValueError(f"fps: expected a positive frame rate, got {fps}")
        return trajectory_poses(self.points, frames, times=self.frame_times(frames, fps))


def _turn_path(name: str, s, lead: float = 0.0):
    """``(xy [N, 2], heading [N])`` at path lengths ``s`` of a turn that first drives ``lead``
    metres straight on: a quarter circle of :data:`TURN_RADIUS`, then straight on."""
    s = np.asarray(s, np.float64)
    arc = np.pi / 2 * TURN_RADIUS
    into = np.maximum(s - lead, 0.0)
    angle = np.minimum(into, arc) / TURN_RADIUS
    x = np.minimum(s, lead) + TURN_RADIUS * np.sin(angle)
    y = TURN_RADIUS * (1 - np.cos(angle)) + np.maximum(into - arc, 0.0)
    side = 1.0 if name == "left turn" else -1.0
    return np.stack([x, side * y], axis=-1), side * angle


def manoeuvre(name: str, speed: float | None, duration: float, step: float = 0.1, lead: float = 0.0) -> Route:
    """A named manoeuvre (module docstring) sampled about every ``step`` seconds over ``duration``;
    a turn drives ``lead`` metres straight on first."""
    name = name.lower()
    v = DEFAULT_SPEED[name] if speed is None else float(speed)
    if not (np.isfinite(lead) and lead >= 0):
        raise ValueError(f"lead: expected metres >= 0 driven before the manoeuvre, got {lead}")
    duration = max(float(duration), step)
    t = np.linspace(0.0, duration, max(2, int(np.ceil(duration / step)) + 1))  # up to the clip's end
    s = v * t  # distance along the path
    if name == "straight":
        xy = np.stack([s, np.zeros_like(s)], axis=1)
    elif name == "stop":
        t_stop = v / BRAKING
        tt = np.minimum(t, t_stop)
        xy = np.stack([v * tt - 0.5 * BRAKING * tt**2, np.zeros_like(tt)], axis=1)
    else:
        xy = _turn_path(name, s, lead if name in TURNS else 0.0)[0]
    return Route(
        xy.astype(np.float32),
        t,
        source=f"manoeuvre {name!r}",
        manoeuvre=name,
        speed=v,
        lead=float(lead) if name in TURNS else 0.0,
    )


def _rows_from_json(path: Path, data):
    """``(rows [[x, y(, t)]], has_times)`` of a JSON route, each row with its 1-based number."""
    if isinstance(data, dict):
        if "points" not in data:
            raise ValueError(f"route {path}: expected a 'points' list (and optional 'times'), got keys {sorted(data)}")
        pts, times = data["points"], data.get("times")
        if times is not None and len(times) != len(pts):
            raise ValueError(f"route {path}: expected one time per point, got {len(times)} times for {len(pts)} points")
        rows = [list(p) + ([times[i]] if times is not None else []) for i, p in enumerate(pts)]
        width = 3 if times is not None else 2
    elif isinstance(data, list):
        rows = []
        for i, r in enumerate(data):
            if isinstance(r, dict):
                if not {"x", "y"} <= set(r) or not set(r) <= {"x", "y", "t"}:
                    raise ValueError(f"route {path} row {i + 1}: expected keys x, y and optionally t, got {sorted(r)}")
                r = [r["x"], r["y"]] + ([r["t"]] if "t" in r else [])
            rows.append(r)
        width = len(rows[0]) if rows and isinstance(rows[0], list) else 2
    else:
        raise ValueError(
            f"route {path}: expected a JSON object with 'points' or a list of points, got {type(data).__name__}"
        )
    return rows, width


def _rows_from_csv(path: Path):
    with open(path, newline="") as f:
        reader = csv.reader(f)
        header = [h.strip().lower() for h in next(reader, [])]
        if header[:2] != ["x", "y"] or header[2:] not in ([], ["t"]):
            raise ValueError(f"route {path} row 1: expected the header 'x,y' or 'x,y,t', got {','.join(header)!r}")
        return [r for r in reader if any(c.strip() for c in r)], len(header), 2  # data rows start at row 2


def load_route_file(path) -> Route:
    """A route from a JSON or CSV file (module docstring)."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(
            f"route: expected a JSON or CSV file or a manoeuvre ({', '.join(DEFAULT_SPEED)}), got {str(path)!r}"
        )
    first_row = 1
    if path.suffix.lower() == ".csv":
        rows, width, first_row = _rows_from_csv(path)
    else:
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as e:
            raise ValueError(f"route {path}: expected JSON or a .csv file, got a parse error: {e}") from None
        rows, width = _rows_from_json(path, data)
    if width not in (2, 3):
        raise ValueError(
            f"route {path} row {first_row}: expected 2 or 3 values (x, y and optionally t), got {rows[0]!r}"
        )
    values = []
    for i, r in enumerate(rows):
        row = i + first_row
        if not isinstance(r, (list, tuple)) or len(r) != width:
            raise ValueError(
                f"route {path} row {row}: expected {width} values (x, y{', t' if width == 3 else ''}), got {r!r}"
            )
        try:
            v = [float(c) for c in r]
        except (TypeError, ValueError):
            raise ValueError(f"route {path} row {row}: expected numbers, got {r!r}") from None
        if not all(np.isfinite(v)):
            raise ValueError(f"route {path} row {row}: expected finite values, got {r!r}")
        values.append(v)
    if len(values) < 2:
        raise ValueError(f"route {path}: expected at least 2 points, got {len(values)}")
    arr = np.asarray(values, np.float64)
    if np.abs(arr[0, :2]).max() > 1e-3 or (width == 3 and abs(arr[0, 2]) > 1e-6):
        raise ValueError(
            f"route {path} row {first_row}: expected the ego's start (x, y) = (0, 0)"
            f"{' at t = 0' if width == 3 else ''} (points are in the first frame's ego frame), "
            f"got {values[0]}"
        )
    times = None
    if width == 3:
        times = arr[:, 2]
        bad = np.nonzero(np.diff(times) <= 0)[0]
        if len(bad):
            raise ValueError(
                f"route {path} row {bad[0] + 1 + first_row}: expected times increasing, got "
                f"{times[bad[0] + 1]} after {times[bad[0]]}"
            )
    return Route(arr[:, :2].astype(np.float32), times, source=str(path), first_row=first_row)


def load_route(spec: str, *, duration: float) -> Route:
    """``--route SPEC``: a named manoeuvre lasting ``duration`` seconds, or a route file."""
    m = _MANOEUVRE.match(str(spec))
    if m:
        return manoeuvre(m.group(1), None if m.group(2) is None else float(m.group(2)), duration)
    return load_route_file(spec)


def _first_off_map(route: Route, start, scene, frames: int, fps: float) -> tuple[int, int] | None:
    """The first row of ``route`` (a manoeuvre: its one row) whose point, or the path leading to
    it, leaves the seen part of ``scene`` when driven from ``start [4, 4]``, with the first frame
    off it; None when the whole route is on the seen map."""
    at_rows = route.frame_times(frames, fps)
    dense = route.poses(frames, fps)[:, :2, 3]
    off_rows = ~scene.covers(_to_world(start, route.points))
    off_frames = ~scene.covers(_to_world(start, dense))
    if not (off_rows.any() or off_frames.any()):
        return None
    frame = int(np.argmax(off_frames)) if off_frames.any() else None
    if off_rows.any():
        k = int(np.argmax(off_rows))
    else:  # between rows: name the row the path was heading to
        k = int(min(np.searchsorted(at_rows, frame), len(route.points) - 1))
    if frame is None:
        frame = int(min(np.ceil(at_rows[k]), frames - 1))
    return k, frame


def check_on_map(route: Route, start, scene, frames: int, fps: float) -> None:
    """``ValueError`` naming the route and its first row (a manoeuvre: the time) whose point, or the
    path leading to it, leaves the seen part of ``scene`` (a
    :class:`jaxdrive.data.scene_map.SceneMap`) when driven from the ego pose ``start [4, 4]``."""
    start = np.asarray(start, np.float64)
    first = _first_off_map(route, start, scene, frames, fps)
    if first is None:
        return
    k = first[0]
    x, y = route.points[k]
    where = (
        f"row {k + route.first_row}"
        if route.first_row is not None
        else f"at t = {route.frame_times(frames, fps)[k] / fps:.1f} s"
    )
    raise ValueError(
        f"route {route.source} {where}: expected a point on the scene's map (the BEV maps the clip "
        f"recorded, about {scene.cell[0] * scene.size[0] / 2:.0f} m around its path), got ({x:.1f}, "
        f"{y:.1f}) m beyond it: shorten the route or use a longer clip"
    )


class RouteWarning(UserWarning):
    """A route driven although the scene's map could not vouch for it (``jaxdrive sample --route``)."""


def _to_world(start, xy):
    return np.asarray(xy, np.float64) @ start[:2, :2].T + start[:2, 3]


def _turn_lead(route: Route, start, scene, reach: float) -> float | None:
    """Metres to drive straight on before the turn of ``route`` so that it turns at the next
    intersection within ``reach`` metres: the middle of the first stretch of starts where the
    straight run up to it and the whole turn (arc and :data:`TURN_EXIT`, :data:`TURN_MARGIN`
    either side) lie on the road; None when there is none."""
    leads = np.arange(0.0, reach + 1e-9, SEARCH_STEP)
    s = np.arange(0.0, np.pi / 2 * TURN_RADIUS + TURN_EXIT + 1e-9, SEARCH_STEP)
    xy, heading = _turn_path(route.manoeuvre, s)
    normal = np.stack([-np.sin(heading), np.cos(heading)], -1)
    sides = np.array([-TURN_MARGIN, 0.0, TURN_MARGIN])
    shape = (xy + sides[:, None, None] * normal)[None] + np.stack([leads, 0 * leads], -1)[:, None, None]  # [L, 3, N, 2]
    turn_ok = scene.on_road(_to_world(start, shape)).all((1, 2))
    straight = np.stack(np.broadcast_arrays(leads[None], sides[:, None]), -1)  # [3, L, 2]
    straight_ok = np.logical_and.accumulate(scene.on_road(_to_world(start, straight)).all(0))  # road so far
    fits = np.nonzero(turn_ok & straight_ok)[0]
    if not len(fits):
        return None
    gaps = np.nonzero(np.diff(fits) > 1)[0]
    run = fits[: gaps[0] + 1] if len(gaps) else fits  # the first intersection, not a later one
    return float(leads[(run[0] + run[-1]) // 2])


def _off_road(route: Route, start, scene, frames: int, fps: float, sub: int = 4):
    """Where the path of ``route`` leaves the road: a list of ``(metres, frame, (x, y))`` per
    stretch off the road (its length, where it begins, in the first frame's ego frame), the path
    sampled ``sub`` times a frame; an off-road sample counts half of each step beside it."""
    xy = route.poses(sub * (frames - 1) + 1, sub * fps)[:, :2, 3]
    world = _to_world(start, xy)
    off = ~scene.on_road(world) & scene.covers(world)  # beyond the seen map is unknown, not off road
    step = np.linalg.norm(np.diff(xy, axis=0), axis=-1)
    weight = 0.5 * (off[1:].astype(float) + off[:-1])
    stretches, i = [], 0
    while i < len(off):
        if not off[i]:
            i += 1
            continue
        j = i
        while j + 1 < len(off) and off[j + 1]:
            j += 1
        metres = float((step * weight)[max(i - 1, 0) : j + 1].sum())
        stretches.append((metres, i / sub, tuple(float(v) for v in xy[i])))
        i = j + 1
    return stretches


def _at(frame: float, fps: float, xy) -> dict:
    return {
        "frame": int(np.floor(frame + 1e-6)),
        "time": round(frame / fps, 3),
        "x": round(float(xy[0]), 2),
        "y": round(float(xy[1]), 2),
    }


def drive_on_map(
    route: Route,
    start,
    scene,
    frames: int,
    fps: float,
    *,
    allow_off_road: bool = False,
    max_off_road: float = OFF_ROAD_METRES,
    warned: set | None = None,
) -> tuple[Route, dict]:
    """``route`` driven from the ego pose ``start [4, 4]`` on ``scene`` (a
    :class:`jaxdrive.data.scene_map.SceneMap`) for ``frames`` at ``fps`` (module docstring):
    ``(route, drive)``, the route placed on the map (a turn: at the next intersection) and what
    ``report.json`` records of it: ``start`` (frame, time, x, y in the first frame's ego frame,
    where the manoeuvre begins), ``start_at`` ("intersection" or "clip"), ``map_checked``,
    ``off_road``, ``off_road_metres`` (the longest stretch off the road) and ``off_road_from``
    (where the path first leaves it). A file off the road for more than ``max_off_road`` metres
    in one stretch is a ``ValueError`` unless ``allow_off_road``; so is a point beyond the seen
    map (:func:`check_on_map`), unless ``allow_off_road`` too. A named manoeuvre always runs:
    beyond the map it is driven with one warning, and ``beyond_map_from`` records where it left
    the map (None: it stayed on it). Warnings (:class:`RouteWarning`) are given once per kind:
    ``warned`` collects the kinds given (share one set across the clips of a run)."""
    start = np.asarray(start, np.float64)
    if start.shape != (4, 4) or not np.isfinite(start).all():
        raise ValueError(f"start: expected a finite ego pose [4, 4], got shape {list(start.shape)}")
    if int(frames) < 2:
        raise ValueError(f"frames: expected at least 2 frames to drive, got {frames}")
    if not fps > 0:
        raise ValueError(f"fps: expected a positive frame rate, got {fps}")
    if not (np.isfinite(max_off_road) and max_off_road >= 0):
        raise ValueError(f"max_off_road: expected metres >= 0, got {max_off_road}")
    warned = set() if warned is None else warned

    def warn(kind, message):
        if kind not in warned:
            warned.add(kind)
            warnings.warn(message, RouteWarning, stacklevel=3)

    checked = scene.has_road()
    start_at = "clip"
    if checked and route.manoeuvre in TURNS and route.speed:
        reach = route.speed * (frames - 1) / fps
        lead = _turn_lead(route, start, scene, reach)
        if lead is not None:
            route, start_at = manoeuvre(route.manoeuvre, route.speed, float(route.times[-1]), lead=lead), "intersection"
    beyond = None
    if route.manoeuvre is None and not allow_off_road:
        check_on_map(route, start, scene, frames, fps)
    else:  # a manoeuvre always runs: past the seen map its BEV maps are blank
        off_map = _first_off_map(route, start, scene, frames, fps)
        if off_map is not None:
            frame = off_map[1]
            beyond = _at(frame, fps, route.poses(frames, fps)[frame, :2, 3])
            warn(
                "beyond map",
                f"route {route.source}: it drives beyond the scene's map (the BEV maps the clip "
                f"recorded) from frame {beyond['frame']} (t = {beyond['time']:.2f} s) at "
                f"({beyond['x']:.1f}, {beyond['y']:.1f}) m: the map controls are blank from there "
                f"and nothing says whether it stays on the road",
            )
    begin = route.lead / route.speed * fps if route.lead else 0.0
    drive = {
        "start": _at(begin, fps, (route.lead, 0.0)),
        "start_at": start_at,
        "map_checked": checked,
        "off_road": False,
        "off_road_metres": 0.0,
        "off_road_from": None,
        "beyond_map_from": beyond,
    }
    if not checked:
        warn(
            "unchecked",
            f"route {route.source}: unchecked: the scene's map has no road (nuScenes without its map "
            f"expansion?), so nothing says whether the route stays on the road",
        )
        return route, drive
    stretches = _off_road(route, start, scene, frames, fps)
    if stretches:
        drive.update(
            off_road=True,
            off_road_metres=round(max(m for m, _, _ in stretches), 2),
            off_road_from=_at(stretches[0][1], fps, stretches[0][2]),
        )
    too_far = [st for st in stretches if st[0] > max_off_road]
    if too_far and route.manoeuvre is None and not allow_off_road:
        metres, frame, (x, y) = too_far[0]
        raise ValueError(
            f"route {route.source}: expected a path on the road of the scene's map (at most "
            f"{max_off_road:g} m off it in one stretch), got {metres:.1f} m off the road from frame "
            f"{int(frame)} (t = {frame / fps:.2f} s) at ({x:.1f}, {y:.1f}) m; pass --allow-off-road to "
            f"drive it anyway"
        )
    where = (
        ""
        if not stretches
        else (
            f": it leaves the road at frame {drive['off_road_from']['frame']} "
            f"({drive['off_road_from']['x']:.1f}, {drive['off_road_from']['y']:.1f}) m, "
            f"{drive['off_road_metres']:.1f} m off it"
        )
    )
    if route.manoeuvre in TURNS and start_at == "clip":
        warn(
            "no intersection",
            f"route {route.source}: no intersection within the "
            f"{(route.speed or 0) * (frames - 1) / fps:.0f} m the ego drives ahead on the scene's "
            f"map, so the turn starts where the clip is{where or ' (on the road so far)'}",
        )
    elif too_far:  # a named manoeuvre, or a file with allow_off_road
        warn("off road", f"route {route.source}: driven off the road{where}")
    return route, drive
