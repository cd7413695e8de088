"""Controls beyond the log: a sampled clip's per-frame controls extended, or replaced, by the
future-controls predictor, along the recorded path or a user's route.

``jaxdrive sample --strategy S --predictor RUN`` lets ``--frames`` run past the end of the clip's
recorded controls: from the last recorded frame on (from the given frames on with ``--controls
predicted``), the predictor (:mod:`jaxdrive.models.predictor`) is rolled forward at its own step
(interpolated to the clip's frames), its ego and agent poses become the frames' ``ego_to_world``,
``waypoints`` and boxes, and each frame's BEV map is re-cut from the clip's stitched scene map at
the ego's pose (:mod:`jaxdrive.data.scene_map`). With ``--route`` the ego drives the route through
every frame (its map re-cut along it, the recorded agents re-expressed around it) and the
predictor, when given, moves the agents from the given frames on. The whole horizon's controls
exist before the first window is sampled, so every strategy runs unchanged for any length: the
predictor reads controls, never generated pixels, so rolling it ahead is the same closed loop as
rolling it window by window.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.data.scene_map import DEFAULT_RANGE, SceneMap, cut
from jaxdrive.data.traffic import clip_fields, clip_tracks, interpolate, planar
from jaxdrive.models.predictor import PredictorConfig, Traffic, rollout_program

CONTROLS = ("recorded", "predicted")
BOX_FIELDS = ("boxes", "box_classes", "box_ids", "box_valid")


@dataclasses.dataclass(frozen=True)
class FuturePredictor:
    """A trained predictor: its config, parameters and the seconds of one of its steps (a run's:
    :func:`jaxdrive.train.predictor_run.load_future_predictor`)."""

    config: PredictorConfig
    params: Any = dataclasses.field(compare=False, repr=False)
    step_seconds: float = 1 / 6


@jax.jit
def _cut_all(scene, poses, fallback):
    return jax.vmap(lambda p: cut(scene, p, fallback))(poses)


def _fit_tracks(tracks: dict, n: int) -> tuple[dict, np.ndarray]:
    """Tracks padded or cut to ``n`` slots (present ones first); also the kept slots' indices."""
    order = np.argsort(~tracks["valid"], kind="stable")[:n]
    out = {}
    for k, v in tracks.items():
        if k == "ego":
            out[k] = v
            continue
        axis = 1 if k in ("agents", "seen") else 0
        v = np.take(v, order, axis=axis)
        if v.shape[axis] < n:
            pad = [(0, 0)] * v.ndim
            pad[axis] = (0, n - v.shape[axis])
            v = np.pad(v, pad)
        out[k] = v
    return out, order


def future_controls(
    sample: dict,
    clip: dict,
    *,
    frames: int,
    keep: int,
    predictor: FuturePredictor | None = None,
    route=None,
    bev_range=DEFAULT_RANGE,
    where: str = "clip",
    allow_off_road: bool = False,
    warned: set | None = None,
) -> dict:
    """``sample`` (:func:`jaxdrive.data.pipeline.sample_clip` of the first frames of ``clip``, at
    the clip's rate over its stride) with controls for ``frames`` frames: frames before ``keep``
    keep their recorded controls, later ones come from ``predictor``; with a ``route``
    (:class:`jaxdrive.generate.route.Route`) the ego drives it through every frame, placed on and
    checked against the scene's map (:func:`jaxdrive.generate.route.drive_on_map`, with
    ``allow_off_road`` and ``warned``; what it says is added as ``route_drive``, not a model
    input). ``video`` keeps the recorded frames. ``predicted_from`` is added: the first frame not
    recorded."""
    have = int(np.shape(sample["ego_to_world"])[0])
    fps = float(sample["fps"])
    if not 1 <= keep <= have:
        raise ValueError(f"keep: expected 1..{have} recorded frames to keep, got {keep}")
    if frames > keep and predictor is None and (route is None or frames > have):
        raise ValueError(
            f"frames: expected at most {have} frames (the recorded controls of {where}), got {frames}; "
            f"pass --predictor RUN to predict the controls beyond them"
        )
    scene = SceneMap.from_clip(clip["bev_map"], clip["ego_to_world"], bev_range)
    on_device = scene.device()
    times = np.asarray(sample["frame_times"], np.float64)
    times = (
        np.concatenate([times, times[-1] + (np.arange(1, frames - have + 1) / fps)])
        if frames > have
        else times[:frames]
    )
    recorded = {k: np.asarray(sample[k])[:have] for k in ("ego_to_world", *BOX_FIELDS)}
    tracks = clip_tracks(recorded, ref=keep - 1)
    ego = np.concatenate([planar(recorded["ego_to_world"])[: min(have, frames)], np.zeros((max(frames - have, 0), 3))])
    drive = None
    if route is not None:
        from jaxdrive.generate.route import drive_on_map

        start = np.asarray(sample["ego_to_world"][0], np.float64)
        route, drive = drive_on_map(route, start, scene, frames, fps, allow_off_road=allow_off_road, warned=warned)
        ego = planar(start @ route.poses(frames, fps))
    n = tracks["agents"].shape[1]
    agents = np.concatenate([tracks["agents"][: min(have, frames)], np.zeros((max(frames - have, 0), n, 3))])
    seen = np.concatenate([tracks["seen"][: min(have, frames)], np.zeros((max(frames - have, 0), n), bool)])
    if predictor is not None and frames > keep:
        ego_pred, agents_pred, present = _predict(
            predictor, tracks, times, keep, frames, on_device, sample, ego if route is not None else None
        )
        ego[keep:], agents[keep:] = ego_pred, agents_pred
        seen[keep:] = present
    out = dict(sample)
    rebuilt = clip_fields(
        ego,
        agents,
        size=tracks["size"],
        z=tracks["z"],
        classes=tracks["classes"],
        ids=tracks["ids"],
        valid=seen,
        ego_z=float(recorded["ego_to_world"][keep - 1, 2, 3]),
    )
    first = 0 if route is not None else keep  # recorded frames stay exactly as recorded
    for k in ("ego_to_world", *BOX_FIELDS):
        cur = np.asarray(sample[k])[: min(first, frames)]
        new = rebuilt[k][first:].astype(cur.dtype)
        if k in BOX_FIELDS and new.shape[1] != cur.shape[1]:  # slots: the recorded count
            width = cur.shape[1]
            new = (
                new[:, :width]
                if new.shape[1] > width
                else np.pad(
                    new,
                    [(0, 0), (0, width - new.shape[1])] + [(0, 0)] * (new.ndim - 2),
                    constant_values=-1 if k in ("box_classes", "box_ids") else 0,
                )
            )
        out[k] = np.concatenate([cur, new])
    e2w = out["ego_to_world"].astype(np.float64)
    out["waypoints"] = (np.linalg.inv(e2w[0]) @ e2w)[:, :2, 3].astype(np.float32)
    fallback = jnp.asarray(np.asarray(sample["bev_map"])[min(keep, have) - 1])
    cut_maps = np.asarray(_cut_all(on_device, jnp.asarray(ego[first:], jnp.float32), fallback))
    out["bev_map"] = np.concatenate([np.asarray(sample["bev_map"])[: min(first, frames)], cut_maps])
    out["frame_times"] = times.astype(np.float32)
    out["predicted_from"] = keep if predictor is not None and frames > keep else frames
    if drive is not None:
        out["route_drive"] = drive
    return out


def _predict(
    predictor: FuturePredictor, tracks: dict, times, keep: int, frames: int, scene: SceneMap, sample, ego_path=None
):
    """Ego and agent poses at ``times[keep:]`` rolled out from the history ending at frame ``keep - 1``."""
    cfg, dt = predictor.config, predictor.step_seconds
    t_now = times[keep - 1]
    hist_t = t_now - dt * np.arange(cfg.history - 1, -1, -1)
    rec_t = times[:keep]
    fit, order = _fit_tracks(tracks, cfg.max_agents)

    def at(values, t):  # the recorded history, held before its start
        if len(rec_t) == 1:
            return np.repeat(values[:1], len(t), 0)
        return interpolate(rec_t, values[:keep], np.maximum(t, rec_t[0]))

    past_seen = fit["seen"][np.clip(np.searchsorted(rec_t, hist_t, side="right") - 1, 0, keep - 1)]
    traffic = Traffic(
        ego=jnp.asarray(at(fit["ego"], hist_t), jnp.float32)[None],
        agents=jnp.asarray(at(fit["agents"], hist_t), jnp.float32)[None],
        seen=jnp.asarray(past_seen & fit["valid"])[None],
        size=jnp.asarray(fit["size"], jnp.float32)[None],
        z=jnp.asarray(fit["z"], jnp.float32)[None],
        classes=jnp.asarray(np.maximum(fit["classes"], 0), jnp.int32)[None],
        ids=jnp.asarray(fit["ids"], jnp.int32)[None],
    )
    steps = max(1, math.ceil((times[frames - 1] - t_now) / dt - 1e-6))
    step_t = t_now + dt * np.arange(1, steps + 1)
    path = None
    if ego_path is not None:
        path = jnp.asarray(interpolate(times[:frames], ego_path, step_t), jnp.float32)[None]
    bev = jnp.asarray(np.asarray(sample["bev_map"])[keep - 1], jnp.float32)[None]
    ego, agents = rollout_program(cfg)(predictor.params, traffic, steps, bev, scene, path)
    all_t = np.concatenate([[t_now], step_t])
    ego = np.concatenate([np.asarray(traffic.ego[0, -1:]), np.asarray(ego[0])])
    agents = np.concatenate([np.asarray(traffic.agents[0, -1:]), np.asarray(agents[0])])
    want = times[keep:frames]
    ego_f = interpolate(all_t, ego, want)
    agents_f = interpolate(all_t, agents, want)  # [F', max_agents, 3]
    n = tracks["agents"].shape[1]
    out = np.zeros((len(want), n, 3))
    kept = order[: min(len(order), cfg.max_agents)]
    out[:, kept] = agents_f[:, : len(kept)]
    present = np.zeros(n, bool)
    present[kept] = tracks["valid"][kept]  # slots past max_agents are not predicted
    return ego_f, out, present
