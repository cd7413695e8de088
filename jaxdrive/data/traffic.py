"""A clip's controls as traffic, and back: the ego's and every agent's planar pose per frame.

The predictor of future controls (:mod:`jaxdrive.models.predictor`) reads and writes poses
``(x, y, yaw)`` in the world frame, one row per agent *track*; a clip stores boxes per frame in
that frame's ego frame, one *slot* per box. :func:`clip_tracks` turns the one into the other
(following each track id from a reference frame; a dataset without ids keeps slots as tracks),
:func:`clip_fields` the other way, so predicted traffic becomes the clip fields a DiT reads
(``ego_to_world``, ``waypoints``, ``boxes``, ``box_classes``, ``box_ids``, ``box_valid``).
:func:`load_controls` reads a dataset's clips as controls alone, and :func:`window_traffic` cuts
the predictor's windows from them (its training, :mod:`jaxdrive.train.predictor_run`, and ADE / FDE).
"""

from __future__ import annotations

import numpy as np

from jaxdrive.geometry import wrap

# the fields of a clip that are its controls (:func:`load_controls`): traffic and the map, no video
CONTROL_FIELDS = ("ego_to_world", "boxes", "box_classes", "box_ids", "box_valid", "bev_map")


def planar(ego_to_world) -> np.ndarray:
    """``[..., 4, 4]`` poses -> ``[..., 3]`` (x, y, yaw)."""
    p = np.asarray(ego_to_world, np.float64)
    return np.stack([p[..., 0, 3], p[..., 1, 3], np.arctan2(p[..., 1, 0], p[..., 0, 0])], -1)


def clip_tracks(clip, ref: int = -1) -> dict:
    """The traffic of a clip (schema fields ``ego_to_world``, ``boxes``, ``box_classes``,
    ``box_ids``, ``box_valid``; F frames, N slots), with the tracks of frame ``ref``'s slots:

    ``ego [F, 3]``, ``agents [F, N, 3]`` world poses, ``seen [F, N]`` (the track has a box in that
    frame), and per track its ``size [N, 3]``, box centre height ``z [N]`` (ego frame), ``classes
    [N]``, ``ids [N]`` and ``valid [N]`` as in frame ``ref``."""
    e2w = np.asarray(clip["ego_to_world"], np.float64)
    boxes, ids = np.asarray(clip["boxes"], np.float64), np.asarray(clip["box_ids"])
    valid, classes = np.asarray(clip["box_valid"], bool), np.asarray(clip["box_classes"])
    frames, n = valid.shape
    ego = planar(e2w)
    ref = ref % frames
    if (ids[ref][valid[ref]] >= 0).all() and valid[ref].any():  # follow ids: slots may reorder
        same = (ids[:, None, :] == ids[ref][None, :, None]) & valid[:, None, :] & valid[ref][None, :, None]
        slot = np.where(same.any(-1), same.argmax(-1), -1)  # [F, N]: frame f's slot of track k
    else:
        slot = np.where(valid, np.arange(n), -1)
    seen = slot >= 0
    take = np.take_along_axis(boxes, np.maximum(slot, 0)[..., None], 1)  # [F, N, 7]
    c, s = np.cos(ego[:, 2])[:, None], np.sin(ego[:, 2])[:, None]
    x = ego[:, None, 0] + c * take[..., 0] - s * take[..., 1]
    y = ego[:, None, 1] + s * take[..., 0] + c * take[..., 1]
    agents = np.stack([x, y, wrap(take[..., 6] + ego[:, None, 2])], -1)
    agents = np.where(seen[..., None], agents, 0.0)
    return {
        "ego": ego,
        "agents": agents,
        "seen": seen & valid[ref][None],
        "size": boxes[ref, :, 3:6],
        "z": boxes[ref, :, 2],
        "classes": classes[ref].astype(np.int32),
        "ids": ids[ref].astype(np.int32),
        "valid": valid[ref],
    }


def clip_fields(ego, agents, *, size, z, classes, ids, valid, ego_z: float = 0.0) -> dict:
    """Predicted traffic -> clip fields: ``ego [F, 3]`` and ``agents [F, N, 3]`` world poses,
    the tracks' ``size [N, 3]``, ``z [N]``, ``classes``, ``ids``, ``valid [N]`` ->
    ``ego_to_world [F, 4, 4]`` (float64, at height ``ego_z``, level), ``waypoints [F, 2]`` (in the
    first frame's ego frame), ``boxes [F, N, 7]`` in each frame's ego frame, ``box_classes``,
    ``box_ids``, ``box_valid [F, N]`` (invalid slots zero / -1 / False, as the schema pads)."""
    ego, agents = np.asarray(ego, np.float64), np.asarray(agents, np.float64)
    frames, n = agents.shape[:2]
    c, s = np.cos(ego[:, 2]), np.sin(ego[:, 2])
    e2w = np.tile(np.eye(4), (frames, 1, 1))
    e2w[:, 0, 0], e2w[:, 0, 1], e2w[:, 1, 0], e2w[:, 1, 1] = c, -s, s, c
    e2w[:, :2, 3], e2w[:, 2, 3] = ego[:, :2], ego_z
    d = ego[:, :2] - ego[:1, :2]
    c0, s0 = np.cos(ego[0, 2]), np.sin(ego[0, 2])
    waypoints = np.stack([c0 * d[:, 0] + s0 * d[:, 1], -s0 * d[:, 0] + c0 * d[:, 1]], -1)
    rel = agents[..., :2] - ego[:, None, :2]
    bx = c[:, None] * rel[..., 0] + s[:, None] * rel[..., 1]
    by = -s[:, None] * rel[..., 0] + c[:, None] * rel[..., 1]
    size = np.broadcast_to(np.asarray(size, np.float64), (frames, n, 3))
    zz = np.broadcast_to(np.asarray(z, np.float64), (frames, n))
    boxes = np.concatenate([np.stack([bx, by, zz], -1), size, wrap(agents[..., 2] - ego[:, None, 2])[..., None]], -1)
    keep = np.broadcast_to(np.asarray(valid, bool), (frames, n))
    return {
        "ego_to_world": e2w,
        "waypoints": waypoints.astype(np.float32),
        "boxes": np.where(keep[..., None], boxes, 0.0).astype(np.float32),
        "box_classes": np.where(keep, np.asarray(classes, np.int32), -1).astype(np.int32),
        "box_ids": np.where(keep, np.asarray(ids, np.int32), -1).astype(np.int32),
        "box_valid": keep.copy(),
    }


def interpolate(times, values, at, *, angle_last: bool = True):
    """Linear interpolation of ``values [S, ...]`` given at ``times [S]`` to ``at [F]`` (held at the
    ends), the last component of the trailing axis an angle (interpolated the short way round)."""
    times, values, at = np.asarray(times, np.float64), np.asarray(values, np.float64), np.asarray(at, np.float64)
    i = np.clip(np.searchsorted(times, at, side="right") - 1, 0, len(times) - 2)
    w = np.clip((at - times[i]) / (times[i + 1] - times[i]), 0.0, 1.0)
    w = w.reshape(w.shape + (1,) * (values.ndim - 1))
    a, b = values[i], values[i + 1]
    delta = b - a
    if angle_last:
        delta[..., -1] = wrap(delta[..., -1])
    out = a + w * delta
    if angle_last:
        out[..., -1] = wrap(out[..., -1])
    return out


def load_controls(path, split: str, *, max_agents: int) -> list[dict]:
    """The control fields (:data:`CONTROL_FIELDS`) and ``fps`` of every clip of the dataset
    ``path``'s ``split``, box slots padded or cut to ``max_agents``
    (:func:`jaxdrive.data.pipeline.pad_boxes`)."""
    from jaxdrive.data.tfds_io import open_source
    from jaxdrive.data.transforms import pad_boxes

    source = open_source(path, split)
    clips = []
    for i in range(len(source)):
        rec = source[i]
        clip = {k: np.asarray(rec[k]) for k in CONTROL_FIELDS}
        pad_boxes(clip, max_agents, f"{split} clip {i}")
        clip["fps"] = float(rec["fps"])
        clips.append(clip)
    return clips


def window_traffic(clip: dict, frames: np.ndarray, history: int) -> dict:
    """The traffic of ``clip`` (:func:`load_controls`) at source ``frames``, with the tracks of
    the last history frame: the ``Traffic`` fields (:class:`jaxdrive.models.predictor.Traffic`,
    NumPy) of the first ``history`` steps and the targets of the rest, and each step's ``bev``."""
    sub = {k: clip[k][frames] for k in ("ego_to_world", "boxes", "box_classes", "box_ids", "box_valid")}
    tr = clip_tracks(sub, ref=history - 1)
    return {
        "ego": tr["ego"],
        "agents": tr["agents"],
        "seen": tr["seen"],
        "size": tr["size"],
        "z": tr["z"],
        "classes": np.maximum(tr["classes"], 0),
        "ids": tr["ids"],
        "bev": clip["bev_map"][frames],
    }
