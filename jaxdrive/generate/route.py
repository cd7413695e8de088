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
pose per frame (:func:`jaxdrive.warp.trajectory_poses`, LongDWM appendix A.1). Bad input is a
``ValueError`` naming the file and the row.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import re
from pathlib import Path

import numpy as np

TURN_RADIUS = 15.0        # metres: a quarter circle at an urban intersection
BRAKING = 3.0             # m/s^2: a firm, comfortable stop
DEFAULT_SPEED = {"straight": 10.0, "left turn": 8.0, "right turn": 8.0, "stop": 10.0}
_MANOEUVRE = re.compile(r"^\s*(straight|left turn|right turn|stop)\s*(?:([0-9]*\.?[0-9]+)\s*m/s)?\s*$", re.I)


@dataclasses.dataclass(frozen=True)
class Route:
    """The ego's path: ``points [K, 2]`` (x forward, y left, metres, in the first frame's ego
    frame) passed at ``times [K]`` seconds (None: evenly over the clip); ``source`` names where
    it came from, for messages."""

    points: np.ndarray
    times: np.ndarray | None = None
    source: str = "route"
    first_row: int | None = None          # the file row of the first point (None: a manoeuvre)

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


def manoeuvre(name: str, speed: float | None, duration: float, step: float = 0.1) -> Route:
    """A named manoeuvre (module docstring) sampled about every ``step`` seconds over ``duration``."""
    name = name.lower()
    v = DEFAULT_SPEED[name] if speed is None else float(speed)
    duration = max(float(duration), step)
    t = np.linspace(0.0, duration, max(2, int(np.ceil(duration / step)) + 1))      # up to the clip's end
    s = v * t                                                   # distance along the path
    if name == "straight":
        xy = np.stack([s, np.zeros_like(s)], axis=1)
    elif name == "stop":
        t_stop = v / BRAKING
        tt = np.minimum(t, t_stop)
        xy = np.stack([v * tt - 0.5 * BRAKING * tt ** 2, np.zeros_like(tt)], axis=1)
    else:
        arc = np.pi / 2 * TURN_RADIUS
        on_arc = np.minimum(s, arc) / TURN_RADIUS
        after = np.maximum(s - arc, 0.0)
        x = TURN_RADIUS * np.sin(on_arc)
        y = TURN_RADIUS * (1 - np.cos(on_arc)) + after
        xy = np.stack([x, y if name == "left turn" else -y], axis=1)
    return Route(xy.astype(np.float32), t, source=f"manoeuvre {name!r}")


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
        raise ValueError(f"route {path}: expected a JSON object with 'points' or a list of points, "
                         f"got {type(data).__name__}")
    return rows, width


def _rows_from_csv(path: Path):
    with open(path, newline="") as f:
        reader = csv.reader(f)
        header = [h.strip().lower() for h in next(reader, [])]
        if header[:2] != ["x", "y"] or header[2:] not in ([], ["t"]):
            raise ValueError(f"route {path} row 1: expected the header 'x,y' or 'x,y,t', got {','.join(header)!r}")
        return [r for r in reader if any(c.strip() for c in r)], len(header), 2     # data rows start at row 2


def load_route_file(path) -> Route:
    """A route from a JSON or CSV file (module docstring)."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"route: expected a JSON or CSV file or a manoeuvre ({', '.join(DEFAULT_SPEED)}), "
                         f"got {str(path)!r}")
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
        raise ValueError(f"route {path} row {first_row}: expected 2 or 3 values (x, y and optionally t), "
                         f"got {rows[0]!r}")
    values = []
    for i, r in enumerate(rows):
        row = i + first_row
        if not isinstance(r, (list, tuple)) or len(r) != width:
            raise ValueError(f"route {path} row {row}: expected {width} values (x, y{', t' if width == 3 else ''}), "
                             f"got {r!r}")
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
        raise ValueError(f"route {path} row {first_row}: expected the ego's start (x, y) = (0, 0)"
                         f"{' at t = 0' if width == 3 else ''} (points are in the first frame's ego frame), "
                         f"got {values[0]}")
    times = None
    if width == 3:
        times = arr[:, 2]
        bad = np.nonzero(np.diff(times) <= 0)[0]
        if len(bad):
            raise ValueError(f"route {path} row {bad[0] + 1 + first_row}: expected times increasing, got "
                             f"{times[bad[0] + 1]} after {times[bad[0]]}")
    return Route(arr[:, :2].astype(np.float32), times, source=str(path), first_row=first_row)


def load_route(spec: str, *, duration: float) -> Route:
    """``--route SPEC``: a named manoeuvre lasting ``duration`` seconds, or a route file."""
    m = _MANOEUVRE.match(str(spec))
    if m:
        return manoeuvre(m.group(1), None if m.group(2) is None else float(m.group(2)), duration)
    return load_route_file(spec)


def check_on_map(route: Route, start, scene, frames: int, fps: float) -> None:
    """``ValueError`` naming the route and its first row (a manoeuvre: the time) whose point, or the
    path leading to it, leaves the seen part of ``scene`` (a
    :class:`jaxdrive.data.scene_map.SceneMap`) when driven from the ego pose ``start [4, 4]``."""
    start = np.asarray(start, np.float64)
    at_rows = route.frame_times(frames, fps)
    dense = route.poses(frames, fps)[:, :2, 3]
    pts = np.concatenate([np.asarray(route.points, np.float64), dense])
    world = pts @ start[:2, :2].T + start[:2, 3]
    off = ~scene.covers(world)
    if not off.any():
        return
    k = int(np.argmax(off))
    if k >= len(route.points):        # between rows: name the row the path was heading to
        frame = k - len(route.points)
        k = int(min(np.searchsorted(at_rows, frame), len(route.points) - 1))
    x, y = route.points[k]
    where = (f"row {k + route.first_row}" if route.first_row is not None else
             f"at t = {at_rows[k] / fps:.1f} s")
    raise ValueError(f"route {route.source} {where}: expected a point on the scene's map (the BEV maps the clip "
                     f"recorded, about {scene.cell[0] * scene.size[0] / 2:.0f} m around its path), got ({x:.1f}, "
                     f"{y:.1f}) m beyond it: shorten the route or use a longer clip")
