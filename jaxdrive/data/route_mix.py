"""Training scenes under several ego routes: the same past followed by different futures.

A dataset written by ``jaxdrive data synth --counterfactuals`` holds each training scene's
re-render along each route it can drive (:func:`jaxdrive.data.synthetic.counterfactual_clip`: the
same town, traffic, look and light, the same frames before the route's start) in the split
``train_route_<route>``. :class:`RoutedScenes` is a random-access source over the scenes: a
sample of scene ``i`` reads one of the routes the scene has, drawn by the pipeline per clip,
epoch and round (:mod:`jaxdrive.data.pipeline`) from ``data.routes``'s weights renormalised over
those routes. So within one epoch the same history is followed by different futures, and a model
can no longer extrapolate the motion its given frames show and ignore its route (the recorded
future continues that motion: in a log of expert drives the route is redundant with the history;
ReSim, arXiv 2506.09981, and ACT-Bench find the same for models trained on expert logs).

``data.routes`` items are ``"route"`` (weight 1) or ``"route:weight"``; ``recorded`` is the
``train`` split itself.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from jaxdrive.data.synth_routes import parse_routes


def parse_route_mix(items: Sequence[str], option: str = "data.routes") -> dict[str, float]:
    """``("recorded:2", "stop", ...)`` -> ``{"recorded": 2.0, "stop": 1.0, ...}`` (insertion order);
    ``ValueError`` naming ``option`` for an unknown or repeated route or a weight that is not a
    positive number."""
    if isinstance(items, str):
        items = [s for s in items.split(",") if s.strip()]
    pairs = [tuple(s.strip() for s in str(item).partition(":")) for item in items]
    names = parse_routes([name for name, _, _ in pairs], option)  # known and distinct
    if len(names) != len(pairs):
        raise ValueError(f"{option}: expected a route in every item, got {list(items)!r}")
    out: dict[str, float] = {}
    for item, name, (_, sep, weight) in zip(items, names, pairs):
        try:
            w = float(weight) if sep else 1.0
        except ValueError:
            w = math.nan
        if not (math.isfinite(w) and w > 0):
            raise ValueError(f"{option}: expected a weight > 0 after 'route:', got {item!r}")
        out[name] = w
    return out


class RoutedScenes:
    """Random access to training scenes, each read along a route it has.

    ``sources``: ``{route: source}`` (``recorded``: the scenes' own split; a counterfactual route's
    source holds the rows of ``rows[route]``, the scene index of each row, in order); ``weights``:
    the mix (:func:`parse_route_mix`). ``len`` and ``frame_counts`` are the scenes'; ``src[i]`` is
    scene ``i`` as recorded (what a substitute for an unreadable record reads when no draw is
    given), :meth:`read` draws a route. ``part_frame``: the first frame where the counterfactual
    routes leave the recorded drive (the dataset's ``counterfactuals.start``; None: unknown), what
    ``data.route_parting`` places windows before. Picklable when its sources are."""

    kind = "clips"

    def __init__(
        self,
        sources: Mapping[str, object],
        rows: Mapping[str, Sequence[int]],
        weights: Mapping[str, float],
        part_frame: int | None = None,
    ):
        if "recorded" not in sources:
            raise ValueError(f"sources: expected the recorded scenes ('recorded'), got {sorted(sources)}")
        self.recorded = sources["recorded"]
        n = len(self.recorded)
        self.frame_counts = getattr(self.recorded, "frame_counts", None)
        self.routes = [r for r in weights if r in sources]  # the mix's order
        if not self.routes:
            raise ValueError(f"weights: expected routes of {sorted(sources)}, got {sorted(weights)}")
        self._sources = dict(sources)
        self._row = {}  # route -> scene index -> row in that route's source
        for route in self.routes:
            scenes = range(n) if route == "recorded" else rows[route]
            if route != "recorded" and len(scenes) != len(sources[route]):
                raise ValueError(
                    f"rows[{route!r}]: expected one scene index per row of its source "
                    f"({len(sources[route])}), got {len(scenes)}"
                )
            self._row[route] = {int(s): j for j, s in enumerate(scenes)}
        self._weights = np.asarray([weights[r] for r in self.routes], np.float64)
        self.part_frame = part_frame

    def __len__(self) -> int:
        return len(self.recorded)

    def __getitem__(self, index: int) -> dict:
        return self.recorded[index]

    def routes_of(self, index: int) -> list[str]:
        """The routes of the mix that scene ``index`` has (``recorded`` first if in the mix)."""
        return [r for r in self.routes if int(index) in self._row[r]]

    def read(self, index: int, rng: np.random.Generator) -> tuple[dict, str]:
        """``(clip, route)``: scene ``index`` along a route drawn from the mix's weights over the
        routes the scene has (one draw of ``rng`` always). A scene with none of them (``recorded``
        left out of the mix and no counterfactual of this scene in it) reads as recorded."""
        have = np.asarray([int(index) in self._row[r] for r in self.routes])
        u = rng.random()
        if not have.any():
            return self.recorded[index], "recorded"
        w = np.where(have, self._weights, 0.0)
        k = int(np.searchsorted(np.cumsum(w) / w.sum(), u, side="right"))
        route = self.routes[min(k, len(self.routes) - 1)]
        return self.along(index, route), route

    def along(self, index: int, route: str) -> dict:
        """Scene ``index`` rendered along ``route`` (one of :meth:`routes_of`)."""
        if route == "recorded":
            return self.recorded[index]
        if route not in self._row or int(index) not in self._row[route]:
            raise ValueError(f"route: expected one of scene {index}'s routes {self.routes_of(index)}, got {route!r}")
        return self._sources[route][self._row[route][int(index)]]

    def __repr__(self):
        return f"RoutedScenes({len(self)} scenes, routes={self.routes})"


def check_route_mix(path, weights: Mapping[str, float], option: str = "data.routes") -> dict:
    """What the dataset at ``path`` holds of the training routes of ``weights`` (its metadata's
    ``train_routes``); a route it holds no training renders of is a ``ValueError`` naming
    ``option`` and the routes it has."""
    from jaxdrive.data.synthetic import read_counterfactuals

    held = read_counterfactuals(path).get("train_routes", {})
    missing = [r for r in weights if r != "recorded" and r not in held]
    if missing:
        have = (
            ", ".join(["recorded", *held])
            if held
            else "recorded only: write it with 'jaxdrive data synth --counterfactuals ROUTES'"
        )
        raise ValueError(f"{option}: expected routes the training split of {path} holds ({have}), got {missing}")
    return held


def open_routed_scenes(path, weights: Mapping[str, float], option: str = "data.routes") -> RoutedScenes:
    """The ``train`` scenes of the dataset at ``path`` along the routes of ``weights``
    (:func:`check_route_mix` first)."""
    from jaxdrive.data.synthetic import read_counterfactuals
    from jaxdrive.data.tfds_io import open_source

    held = check_route_mix(path, weights, option)
    start = read_counterfactuals(path).get("start")
    sources = {"recorded": open_source(path, "train")}
    rows = {}
    for route in weights:
        if route != "recorded":
            sources[route] = open_source(path, held[route]["split"])
            rows[route] = held[route]["clips"]
    return RoutedScenes(sources, rows, weights, part_frame=None if start is None else int(start))
