"""nuScenes reader: 12 Hz multi-view camera clips in the :mod:`jaxdrive.data.schema` record.

Reads the official layout (``<dataroot>/<version>/*.json`` tables, ``samples/`` and ``sweeps/``
JPEGs, optional ``maps/expansion/<location>.json``) with numpy and Pillow only (no devkit).

Frames. A scene's frames are CAM_FRONT's sample_data chain (``prev``/``next``, keyframes and
sweeps, ~12 Hz). For every CAM_FRONT frame each other camera contributes its sample_data of the
same scene nearest in timestamp. By default (``trim_to_keyframes=True``) the chain is cut to the
frames from the scene's first to its last CAM_FRONT keyframe, because boxes exist only where two
annotations bracket a frame (below); the number of frames cut is logged.

Boxes. Annotations live at the 2 Hz keyframes (``sample`` timestamps). A keyframe frame takes them
as they are (time = its sample's timestamp, as the devkit does). A sweep at time t takes, per
instance, the two consecutive annotations of that instance (in time) with t0 < t < t1 and
interpolates linearly: centre and size linearly, yaw by the shorter arc. An instance with no
bracketing pair at t has no box at t: before its first and after its last annotation (so nothing
at a scene's ends outside the keyframe span, and no box in the sweeps before an instance's first
annotation; the devkit's ``get_boxes`` would show the next keyframe's box there instead).
Boxes carry yaw only (nuScenes annotations are yaw-only rotations). They are moved from the global
frame into the ego frame of their frame (the CAM_FRONT sample_data's ego_pose) as
``(x, y, z, length, width, height, yaw)``; nuScenes sizes are ``(w, l, h)``.

Classes follow MagicDrive-V2 / the nuScenes detection benchmark, :data:`CATEGORY_TO_CLASS`;
annotations of other categories are dropped and counted per scene in the log.

Cameras. ``intrinsics`` are the calibrated_sensor's ``camera_intrinsic`` converted to jaxdrive's
pixel-centre convention (``c_x, c_y`` + 0.5, see :mod:`jaxdrive.geometry`) and scaled to
``image_hw``; calibrations are taken from each view's first frame of the clip.

BEV map. ``bev_map[f]`` rasterises the map expansion around the ego of frame f (ego at the
centre, ego x up, ego y left), channels :data:`~jaxdrive.classes.BEV_CLASSES`: polygons
(even-odd fill, holes cut out) for the area layers, 1-cell polylines for the dividers. A cell is
set when its centre is inside. Without ``maps/expansion/<location>.json`` the map is zeros and
one warning per location is logged.
"""

from __future__ import annotations

import json
import logging
import os
from collections import Counter, defaultdict
from collections.abc import Iterator, Sequence

import numpy as np

from jaxdrive.classes import BEV_CLASSES, OBJECT_CLASSES
from jaxdrive.data.bev import LINE_LAYERS, POLYGON_LAYERS, rasterize_map
from jaxdrive.data.faults import BadRecordError, OncePerFile
from jaxdrive.data.schema import CAMERAS, caption
from jaxdrive.validate import check_positive_int

log = logging.getLogger(__name__)

# table -> fields the reader uses (a missing one raises, naming the file and the field).
TABLE_FIELDS = {
    "scene": ("token", "name", "description", "log_token", "first_sample_token"),
    "sample": ("token", "timestamp", "scene_token"),
    "sample_data": (
        "token",
        "sample_token",
        "ego_pose_token",
        "calibrated_sensor_token",
        "timestamp",
        "filename",
        "is_key_frame",
        "prev",
        "next",
    ),
    "ego_pose": ("token", "translation", "rotation"),
    "calibrated_sensor": ("token", "sensor_token", "translation", "rotation", "camera_intrinsic"),
    "sensor": ("token", "channel"),
    "sample_annotation": ("token", "sample_token", "instance_token", "translation", "size", "rotation"),
    "instance": ("token", "category_token"),
    "category": ("token", "name"),
    "log": ("token", "location", "date_captured"),
    "map": ("token", "log_tokens"),
}

_CLASS = {name: i for i, name in enumerate(OBJECT_CLASSES)}
# nuScenes category -> OBJECT_CLASSES index (mmdet3d's / MagicDrive's NameMapping).
CATEGORY_TO_CLASS = {
    "vehicle.car": _CLASS["car"],
    "vehicle.truck": _CLASS["truck"],
    "vehicle.construction": _CLASS["construction_vehicle"],
    "vehicle.bus.bendy": _CLASS["bus"],
    "vehicle.bus.rigid": _CLASS["bus"],
    "vehicle.trailer": _CLASS["trailer"],
    "movable_object.barrier": _CLASS["barrier"],
    "vehicle.motorcycle": _CLASS["motorcycle"],
    "vehicle.bicycle": _CLASS["bicycle"],
    "human.pedestrian.adult": _CLASS["pedestrian"],
    "human.pedestrian.child": _CLASS["pedestrian"],
    "human.pedestrian.construction_worker": _CLASS["pedestrian"],
    "human.pedestrian.police_officer": _CLASS["pedestrian"],
    "movable_object.trafficcone": _CLASS["traffic_cone"],
}


# ----------------------------------------------------------------------------------- tables


def load_tables(dataroot: str, version: str = "v1.0-mini") -> dict:
    """``{table: {token: record}}`` for the tables in :data:`TABLE_FIELDS`.

    A missing or unreadable table raises ``ValueError`` naming the file; a record without a
    field the reader uses raises naming the file, the field and the record.
    """
    tables = {}
    for name, fields in TABLE_FIELDS.items():
        path = os.path.join(dataroot, version, f"{name}.json")
        if not os.path.isfile(path):
            raise ValueError(f"{path}: expected the nuScenes table {name!r}, got no such file")
        try:
            with open(path) as f:
                records = json.load(f)
        except (OSError, json.JSONDecodeError) as e:
            raise ValueError(f"{path}: expected a JSON list of records, got unreadable JSON ({e})") from None
        if not isinstance(records, list):
            raise ValueError(f"{path}: expected a JSON list of records, got {type(records).__name__}")
        for i, rec in enumerate(records):
            missing = [k for k in fields if not isinstance(rec, dict) or k not in rec]
            if missing:
                who = rec.get("token", f"#{i}") if isinstance(rec, dict) else f"#{i}"
                raise ValueError(
                    f"{path}: record {who}: expected field {missing[0]!r}, got fields "
                    f"{sorted(rec) if isinstance(rec, dict) else type(rec).__name__}"
                )
        tables[name] = {rec["token"]: rec for rec in records}
    return tables


def scene_names(tables: dict) -> list[str]:
    """The scene names of loaded tables, in table order."""
    return [s["name"] for s in tables["scene"].values()]


def quaternion_to_matrix(q) -> np.ndarray:
    """nuScenes quaternion ``(w, x, y, z)`` -> rotation matrix ``[3, 3]`` (float64)."""
    w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _pose(rec) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = quaternion_to_matrix(rec["rotation"])
    m[:3, 3] = rec["translation"]
    return m


def _yaw(rot: np.ndarray) -> float:
    return float(np.arctan2(rot[1, 0], rot[0, 0]))


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _get(tables: dict, table: str, token: str, where: str) -> dict:
    """``tables[table][token]``; a dangling reference raises naming both files."""
    try:
        return tables[table][token]
    except KeyError:
        raise ValueError(f"{where}: expected a token of {table}.json, got {token!r} (no such record)") from None


class _Index:
    """Reverse indices over loaded tables (channel and scene of each sample_data, tracks)."""

    def __init__(self, tables: dict):
        self.t = tables
        self.channel = {}
        self.by_scene_channel = defaultdict(list)  # (scene, channel) -> [(timestamp, token)]
        self.front_keyframe = {}  # sample token -> CAM_FRONT keyframe sample_data token
        for tok, sd in tables["sample_data"].items():
            where = f"sample_data.json: record {tok}"
            cs = _get(tables, "calibrated_sensor", sd["calibrated_sensor_token"], where)
            sensor = _get(tables, "sensor", cs["sensor_token"], f"calibrated_sensor.json: record {cs['token']}")
            ch = self.channel[tok] = sensor["channel"]
            scene = _get(tables, "sample", sd["sample_token"], where)["scene_token"]
            _get(tables, "ego_pose", sd["ego_pose_token"], where)
            self.by_scene_channel[scene, ch].append((sd["timestamp"], tok))
            if ch == "CAM_FRONT" and sd["is_key_frame"]:
                self.front_keyframe[sd["sample_token"]] = tok
        for v in self.by_scene_channel.values():
            v.sort()
        self.tracks = defaultdict(list)  # (scene, instance) -> [(sample timestamp, annotation)]
        for ann in tables["sample_annotation"].values():
            where = f"sample_annotation.json: record {ann['token']}"
            sample = _get(tables, "sample", ann["sample_token"], where)
            inst = _get(tables, "instance", ann["instance_token"], where)
            _get(tables, "category", inst["category_token"], f"instance.json: record {inst['token']}")
            self.tracks[sample["scene_token"], ann["instance_token"]].append((sample["timestamp"], ann))
        self.scene_tracks = defaultdict(list)
        for (scene, inst), anns in self.tracks.items():
            anns.sort(key=lambda a: a[0])
            self.scene_tracks[scene].append(inst)


def _scene_grid(tables, idx, scene, views, trim_to_keyframes):
    """(CAM_FRONT tokens [F], tokens [F][V])."""
    by_name = {s["name"]: s for s in tables["scene"].values()}
    if scene not in by_name:
        raise ValueError(f"scenes: expected names from the scene table, got {scene!r}")
    rec = by_name[scene]
    first = idx.front_keyframe.get(rec["first_sample_token"])
    if first is None:
        raise ValueError(
            f"sample_data.json: scene {scene!r}: expected a CAM_FRONT keyframe for its "
            f"first sample {rec['first_sample_token']}, got none"
        )
    sds = tables["sample_data"]
    tok = first
    while sds[tok]["prev"]:
        tok = sds[tok]["prev"]
    chain = []
    while tok:
        chain.append(tok)
        tok = sds[tok]["next"]
    if trim_to_keyframes:
        keys = [i for i, t in enumerate(chain) if sds[t]["is_key_frame"]]
        cut = len(chain) - (keys[-1] + 1 - keys[0])
        if cut:
            log.info("scene %s: %d CAM_FRONT sweeps outside the keyframe span left out", scene, cut)
        chain = chain[keys[0] : keys[-1] + 1]
    frames = []
    for ref in chain:
        t, row = sds[ref]["timestamp"], []
        for view in views:
            if view == "CAM_FRONT":
                row.append(ref)
                continue
            cands = idx.by_scene_channel.get((rec["token"], view))
            if not cands:
                raise ValueError(f"sample_data.json: scene {scene!r}: expected {view} sample_data, got none")
            ts = np.array([c[0] for c in cands])
            j = int(np.argmin(np.abs(ts - t)))
            row.append(cands[j][1])
        frames.append(row)
    return chain, frames


def _box_at(track, t):
    """Global (centre[3], wlh[3], yaw) of a track at time t, or None without a bracketing pair."""
    for (t0, a0), (t1, a1) in zip(track, track[1:] + [(None, None)]):
        if t == t0:
            return (
                np.asarray(a0["translation"], float),
                np.asarray(a0["size"], float),
                _yaw(quaternion_to_matrix(a0["rotation"])),
            )
        if t1 is not None and t0 < t < t1:
            a = (t - t0) / (t1 - t0)
            c = (1 - a) * np.asarray(a0["translation"], float) + a * np.asarray(a1["translation"], float)
            s = (1 - a) * np.asarray(a0["size"], float) + a * np.asarray(a1["size"], float)
            y0, y1 = _yaw(quaternion_to_matrix(a0["rotation"])), _yaw(quaternion_to_matrix(a1["rotation"]))
            return c, s, float(_wrap(y0 + a * _wrap(y1 - y0)))
    return None


def _boxes(idx: _Index, scene_token: str, ref_tokens, poses, max_boxes, scene_name):
    t = idx.t
    category = {tok: t["category"][i["category_token"]]["name"] for tok, i in t["instance"].items()}
    dropped = Counter()
    for inst in idx.scene_tracks[scene_token]:
        if category[inst] not in CATEGORY_TO_CLASS:
            dropped[category[inst]] += len(idx.tracks[scene_token, inst])
    if dropped:
        log.info(
            "scene %s: dropped %d annotations of categories outside OBJECT_CLASSES: %s",
            scene_name,
            sum(dropped.values()),
            dict(dropped),
        )
    per_frame, ids = [], {}
    for ref, pose in zip(ref_tokens, poses):
        sd = t["sample_data"][ref]
        time = t["sample"][sd["sample_token"]]["timestamp"] if sd["is_key_frame"] else sd["timestamp"]
        rot_inv = pose[:3, :3].T
        rows = []
        for inst in sorted(idx.scene_tracks[scene_token]):
            if category[inst] not in CATEGORY_TO_CLASS:
                continue
            box = _box_at(idx.tracks[scene_token, inst], time)
            if box is None:
                continue
            centre, wlh, yaw = box
            r = rot_inv @ np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
            xyz = rot_inv @ (centre - pose[:3, 3])
            track = ids.setdefault(inst, len(ids))
            rows.append(([*xyz, wlh[1], wlh[0], wlh[2], _yaw(r)], CATEGORY_TO_CLASS[category[inst]], track))
        per_frame.append(sorted(rows, key=lambda row: row[2]))
    n = max((len(r) for r in per_frame), default=0) if max_boxes is None else max_boxes
    over = sum(max(0, len(r) - n) for r in per_frame)
    if over:
        log.warning("scene %s: %d boxes beyond max_boxes=%d left out", scene_name, over, n)
    frames = len(per_frame)
    boxes = np.zeros((frames, n, 7), np.float32)
    classes = np.zeros((frames, n), np.int32)
    box_ids = np.full((frames, n), -1, np.int32)
    valid = np.zeros((frames, n), bool)
    for f, rows in enumerate(per_frame):
        for k, (b, c, i) in enumerate(rows[:n]):
            boxes[f, k], classes[f, k], box_ids[f, k], valid[f, k] = b, c, i, True
    return boxes, classes, box_ids, valid, sorted(ids, key=ids.get)


# ----------------------------------------------------------------------------------- BEV map


def load_map_expansion(path: str) -> dict:
    """``{layer: [(kind, [rings or polylines as [P, 2] global xy arrays], bbox)]}`` of a map file."""
    try:
        with open(path) as f:
            m = json.load(f)
        nodes = {n["token"]: (n["x"], n["y"]) for n in m["node"]}
        polys = {
            p["token"]: [np.array([nodes[k] for k in p["exterior_node_tokens"]], float)]
            + [np.array([nodes[k] for k in h["node_tokens"]], float) for h in p["holes"] if h["node_tokens"]]
            for p in m["polygon"]
        }
        lines = {ln["token"]: [np.array([nodes[k] for k in ln["node_tokens"]], float)] for ln in m["line"]}
        out = {}
        for layer in POLYGON_LAYERS:
            items = []
            for rec in m.get(layer, []):
                for tok in rec.get("polygon_tokens", [rec.get("polygon_token")]):
                    items.append(polys[tok])
            out[layer] = items
        for layer in LINE_LAYERS:
            out[layer] = [lines[rec["line_token"]] for rec in m.get(layer, [])]
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as e:
        raise ValueError(f"{path}: expected a nuScenes map expansion, got an unreadable file ({e!r})") from None
    return {
        layer: [(rings, np.concatenate(rings).min(0), np.concatenate(rings).max(0)) for rings in items]
        for layer, items in out.items()
    }


# ----------------------------------------------------------------------------------- clips


def _load_image(path: str, hw):
    try:
        from PIL import Image
    except ImportError as e:  # pragma: no cover
        raise ImportError("jaxdrive.data.nuscenes needs Pillow to decode JPEGs: pip install Pillow") from e
    if not os.path.isfile(path):
        raise BadRecordError(path, "expected a camera image, got no such file")
    try:
        with Image.open(path) as im:
            im = im.convert("RGB")
            size = im.size
            if hw is not None and (im.height, im.width) != tuple(hw):
                im = im.resize((hw[1], hw[0]), Image.BILINEAR)
            return np.asarray(im, np.uint8), size
    except OSError as e:  # PIL: truncated data, or not an image at all
        raise BadRecordError(path, f"expected a readable image, got {e}") from None


def _season(date: str) -> str:
    month = int(date[5:7])
    return ("winter", "spring", "summer", "autumn")[(month % 12) // 3]


def read_clips(
    dataroot: str,
    version: str = "v1.0-mini",
    *,
    frames: int = 33,
    stride: int = 1,
    views: Sequence[str] = CAMERAS,
    image_hw: tuple[int, int] | None = None,
    scenes: Sequence[str] | None = None,
    clip_step: int | None = None,
    max_boxes: int | None = None,
    bev_size: tuple[int, int] = (200, 200),
    bev_resolution: float = 0.5,
    trim_to_keyframes: bool = True,
    tables: dict | None = None,
    skip_bad_records: bool = False,
    skipped: list | None = None,
) -> Iterator[dict]:
    """Yield schema clips (:func:`jaxdrive.data.schema.check_clip`) of ``frames`` frames.

    A clip takes every ``stride``-th frame of a scene, so it spans ``(frames - 1) * stride + 1``
    frames; clips start every ``clip_step`` frames (default: that span, i.e. no overlap) and the
    frames left at a scene's end are logged. A scene shorter than the span raises ``ValueError``
    when it was named in ``scenes``, and is logged and left out otherwise. ``image_hw`` resizes
    (bilinear) and rescales the intrinsics; ``None`` keeps the stored size. ``max_boxes`` fixes
    N (boxes beyond it are logged); ``None`` uses the clip's largest per-frame count. Padding slots
    have ``box_valid`` False, zeros, class 0 and id -1. Extra key ``meta``: scene name,
    CAM_FRONT timestamps [F] (us), sample_data tokens ``[V][F]``, instance tokens (by box id).

    A camera image that is missing, unreadable (truncated, not a JPEG) or of another size than the
    clip's first raises :class:`jaxdrive.data.faults.BadRecordError` (a ``ValueError``) naming the
    file. With ``skip_bad_records`` the clip is left out instead: each such file is named once in
    a warning, the count in one at the end, and ``(scene, first frame, file)`` is appended to
    ``skipped`` when it is given. Tables cannot be skipped (without one there is no dataset):
    :func:`load_tables` raises naming the file.
    """
    frames = check_positive_int("frames", frames)
    stride = check_positive_int("stride", stride)
    if not isinstance(skip_bad_records, bool):
        raise ValueError(f"skip_bad_records: expected True or False, got {skip_bad_records!r}")
    views = tuple(views)
    for v in views:
        if v not in CAMERAS:
            raise ValueError(f"views: expected names from {list(CAMERAS)}, got {v!r}")
    if image_hw is not None:
        image_hw = (check_positive_int("image_hw[0]", image_hw[0]), check_positive_int("image_hw[1]", image_hw[1]))
    tables = tables if tables is not None else load_tables(dataroot, version)
    idx = _Index(tables)
    names = scene_names(tables) if scenes is None else list(scenes)
    span = (frames - 1) * stride + 1
    step = span if clip_step is None else check_positive_int("clip_step", clip_step)
    by_name = {s["name"]: s for s in tables["scene"].values()}
    maps, short, bad = {}, 0, 0
    bad_files = OncePerFile(log, "its clips are left out (skip_bad_records)")
    for name in names:
        ref, grid = _scene_grid(tables, idx, name, views, trim_to_keyframes)
        if len(grid) < span:
            msg = (
                f"scene {name!r}: has {len(grid)} CAM_FRONT frames, a clip of frames={frames} with "
                f"stride={stride} needs {span}"
            )
            if scenes is not None:
                raise ValueError(msg)
            log.warning("%s; scene left out", msg)
            short += 1
            continue
        starts = range(0, len(grid) - span + 1, step)
        rest = len(grid) - (starts[-1] + span)
        if rest:
            log.info("scene %s: %d frames after the last clip left out", name, rest)
        scene = by_name[name]
        log_rec = _get(tables, "log", scene["log_token"], f"scene.json: record {scene['token']}")
        location = log_rec["location"]
        if location not in maps:
            path = os.path.join(dataroot, "maps", "expansion", f"{location}.json")
            maps[location] = load_map_expansion(path) if os.path.isfile(path) else None
            if maps[location] is None:
                log.warning("%s: no map expansion, bev_map is zeros for %s", path, location)
        for s in starts:
            try:
                clip = _clip(
                    tables,
                    idx,
                    scene,
                    ref[s : s + span : stride],
                    grid[s : s + span : stride],
                    views,
                    image_hw,
                    dataroot,
                    maps[location],
                    location,
                    log_rec["date_captured"],
                    max_boxes,
                    bev_size,
                    bev_resolution,
                )
            except BadRecordError as e:
                if not skip_bad_records:
                    raise
                bad_files.note(e)
                bad += 1
                if skipped is not None:
                    skipped.append((name, s, e.path))
                continue
            yield clip
    if short:
        log.warning("%d of %d scenes left out as shorter than a clip (%d frames)", short, len(names), span)
    if bad:
        log.warning("%d clips left out: a camera image could not be read (skip_bad_records)", bad)


def _clip(
    tables,
    idx,
    scene,
    ref,
    grid,
    views,
    image_hw,
    dataroot,
    layers,
    location,
    date,
    max_boxes,
    bev_size,
    bev_resolution,
) -> dict:
    sds = tables["sample_data"]
    poses = np.stack([_pose(tables["ego_pose"][sds[r]["ego_pose_token"]]) for r in ref])
    video, intrinsics, cam_to_ego = [], [], []
    for v in range(len(views)):
        imgs, size0 = [], None
        for row in grid:
            path = os.path.join(dataroot, sds[row[v]]["filename"])
            img, size = _load_image(path, image_hw)
            if size0 is not None and size != size0:
                raise BadRecordError(path, f"expected image size {size0} like the clip's first, got {size}")
            size0 = size
            imgs.append(img)
        video.append(np.stack(imgs))
        cs = tables["calibrated_sensor"][sds[grid[0][v]]["calibrated_sensor_token"]]
        k = np.array(cs["camera_intrinsic"], np.float64)
        if k.shape != (3, 3):
            raise ValueError(
                f"calibrated_sensor.json: record {cs['token']}: field 'camera_intrinsic': "
                f"expected a 3x3 matrix, got shape {list(k.shape)}"
            )
        k[:2, 2] += 0.5
        if image_hw is not None:
            k[0] *= image_hw[1] / size0[0]
            k[1] *= image_hw[0] / size0[1]
        intrinsics.append(k)
        cam_to_ego.append(_pose(cs))
    boxes, classes, ids, valid, instances = _boxes(idx, scene["token"], ref, poses, max_boxes, scene["name"])
    rel = poses[0, :3, :3].T @ (poses[:, :3, 3] - poses[0, :3, 3]).T
    times = np.array([sds[r]["timestamp"] for r in ref], np.int64)
    fps = (len(ref) - 1) / ((times[-1] - times[0]) * 1e-6) if len(ref) > 1 and times[-1] > times[0] else 12.0
    if layers is None:
        bev = np.zeros((len(ref), *bev_size, len(BEV_CLASSES)), np.uint8)
    else:
        bev = np.stack([rasterize_map(layers, p, size=bev_size, resolution=bev_resolution) for p in poses])
    sensor = "6 cameras" if set(views) == set(CAMERAS) else ", ".join(views)
    daytime = "night" if "night" in scene["description"].lower() else "day"
    return {
        "video": np.stack(video),
        "intrinsics": np.stack(intrinsics).astype(np.float32),
        "cam_to_ego": np.stack(cam_to_ego).astype(np.float32),
        "ego_to_world": poses,
        "boxes": boxes,
        "box_classes": classes,
        "box_ids": ids,
        "box_valid": valid,
        "bev_map": bev,
        "waypoints": rel[:2].T.astype(np.float32),
        "fps": float(fps),
        "caption": caption(sensor=sensor, location=location, season=_season(date), daytime=daytime),
        "meta": {
            "scene": scene["name"],
            "timestamps": times,
            "sample_data_tokens": [[row[v] for row in grid] for v in range(len(views))],
            "instance_tokens": instances,
        },
    }
