"""A tiny nuScenes dataroot in the official layout, written from scratch for the reader's tests.

Two scenes (boston-seaport by day in summer with a map expansion; singapore-onenorth at night in
winter without one), 3 keyframes each at 2 Hz, 6 cameras at 12 Hz: 5 sweeps between keyframes,
2 sweeps before the first and 2 after the last keyframe. Cameras fire with realistic offsets from
the keyframe (sample) time; CAM_BACK drops one sweep in scene 0. The ego drives an arc (yaw
crossing +-pi in scene 0) with a little pitch and roll. Images are 16x32 JPEGs of one colour
:func:`colour` per (scene, view, frame). Tokens, prev/next chains, sample tokens (a sweep belongs
to the next keyframe's sample, the last ones to the last sample), calibrations and poses are
consistent, so the official devkit loads it.
"""

from __future__ import annotations

import json
import os

import numpy as np

CAMS = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_FRONT_LEFT")
CAM_YAW_DEG = {
    "CAM_FRONT": 0,
    "CAM_FRONT_RIGHT": -55,
    "CAM_BACK_RIGHT": -110,
    "CAM_BACK": 180,
    "CAM_BACK_LEFT": 110,
    "CAM_FRONT_LEFT": 55,
}
CAM_OFFSET_US = {
    "CAM_FRONT": 2000,
    "CAM_FRONT_RIGHT": 10000,
    "CAM_BACK_RIGHT": 30000,
    "CAM_BACK": 40000,
    "CAM_BACK_LEFT": -25000,
    "CAM_FRONT_LEFT": -8000,
}
H, W = 16, 32
FX = {"CAM_BACK": 16.0}  # focal length in pixels of the 32-wide images (nuScenes 1266 / 50, back 800 / 50)
KEYFRAMES, SWEEPS, PRE, POST = 3, 5, 2, 2  # per scene
PERIOD = 500000 / (SWEEPS + 1)
T0 = (1532402927000000, 1542801000000000)
DROPPED = (0, "CAM_BACK", 4)  # (scene, camera, frame j) missing in the fixture
SCENES = (
    dict(
        name="scene-0001",
        location="boston-seaport",
        date="2018-07-24",
        description="Drive by the harbour",
        start=(600.0, 1600.0),
        yaw0=np.deg2rad(160.0),
        speed=8.0,
        yaw_rate=0.25,
    ),
    dict(
        name="scene-0002",
        location="singapore-onenorth",
        date="2018-12-03",
        description="Night, rain, turn",
        start=(400.0, 1100.0),
        yaw0=np.deg2rad(20.0),
        speed=5.0,
        yaw_rate=-0.2,
    ),
)
# (scene, instance, category, {keyframe: (x, y, z, w, l, h, yaw_deg)}) in the global frame. Sizes stay
# constant per instance, as in nuScenes (the devkit interpolates centres and rotations only).
ANNOTATIONS = (
    (
        0,
        "car",
        "vehicle.car",
        {
            0: (610.0, 1605.0, 0.9, 1.9, 4.5, 1.6, 175.0),
            1: (606.0, 1607.0, 1.0, 1.9, 4.5, 1.6, -165.0),
            2: (602.0, 1608.0, 1.0, 1.9, 4.5, 1.6, -150.0),
        },
    ),
    (
        0,
        "ped",
        "human.pedestrian.adult",
        {1: (598.0, 1596.0, 1.0, 0.6, 0.7, 1.8, 30.0), 2: (598.5, 1596.5, 1.0, 0.6, 0.7, 1.8, 60.0)},
    ),
    (0, "dog", "animal", {0: (605.0, 1590.0, 0.3, 0.3, 0.8, 0.5, 0.0), 1: (605.5, 1590.0, 0.3, 0.3, 0.8, 0.5, 10.0)}),
    (
        1,
        "truck",
        "vehicle.truck",
        {
            0: (420.0, 1110.0, 1.5, 2.5, 8.0, 3.0, 10.0),
            1: (423.0, 1111.0, 1.5, 2.5, 8.0, 3.0, 20.0),
            2: (426.0, 1112.0, 1.5, 2.5, 8.0, 3.0, 40.0),
        },
    ),
    (
        1,
        "cone",
        "movable_object.trafficcone",
        {
            0: (410.0, 1098.0, 0.3, 0.4, 0.4, 0.7, 0.0),
            1: (410.0, 1098.0, 0.3, 0.4, 0.4, 0.7, 0.0),
            2: (410.0, 1098.0, 0.3, 0.4, 0.4, 0.7, 0.0),
        },
    ),
)
CATEGORIES = (
    "vehicle.car",
    "vehicle.truck",
    "human.pedestrian.adult",
    "animal",
    "movable_object.trafficcone",
    "vehicle.bus.rigid",
    "movable_object.barrier",
)


def quat_from_matrix(m: np.ndarray) -> list:
    """Rotation matrix -> (w, x, y, z) with w >= 0."""
    w = np.sqrt(max(0.0, 1 + m[0, 0] + m[1, 1] + m[2, 2])) / 2
    x = np.copysign(np.sqrt(max(0.0, 1 + m[0, 0] - m[1, 1] - m[2, 2])) / 2, m[2, 1] - m[1, 2])
    y = np.copysign(np.sqrt(max(0.0, 1 - m[0, 0] + m[1, 1] - m[2, 2])) / 2, m[0, 2] - m[2, 0])
    z = np.copysign(np.sqrt(max(0.0, 1 - m[0, 0] - m[1, 1] + m[2, 2])) / 2, m[1, 0] - m[0, 1])
    q = np.array([w, x, y, z])
    return (q / np.linalg.norm(q)).tolist()


def rot(yaw=0.0, pitch=0.0, roll=0.0) -> np.ndarray:
    cz, sz, cy, sy, cx, sx = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    return rz @ ry @ rx


def cam_rotation(channel: str) -> np.ndarray:
    """Camera -> ego rotation: camera z (forward) along the camera's heading, x right, y down."""
    base = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    return rot(np.deg2rad(CAM_YAW_DEG[channel])) @ base


def ego_pose(scene: int, t_us: int):
    """(translation, rotation matrix) of the ego at time t (constant speed and yaw rate)."""
    s = SCENES[scene]
    dt = (t_us - T0[scene]) * 1e-6
    yaw = s["yaw0"] + s["yaw_rate"] * dt
    x = s["start"][0] + s["speed"] / s["yaw_rate"] * (np.sin(yaw) - np.sin(s["yaw0"]))
    y = s["start"][1] - s["speed"] / s["yaw_rate"] * (np.cos(yaw) - np.cos(s["yaw0"]))
    return np.array([x, y, 0.05 * dt]), rot(yaw, 0.01 * np.sin(3 * dt), 0.008 * np.cos(2 * dt))


def frame_time(scene: int, channel: str, j: int) -> int:
    return int(T0[scene] + round(j * PERIOD) + CAM_OFFSET_US[channel])


def colour(scene: int, view: int, j: int) -> tuple:
    return (40 * view + 20, (12 * (j + PRE)) % 256, 90 + 100 * scene)


def _write_jpeg(path, rgb):
    from PIL import Image

    os.makedirs(os.path.dirname(path), exist_ok=True)
    Image.fromarray(np.full((H, W, 3), rgb, np.uint8)).save(path, quality=95)


def _map_expansion():
    """boston-seaport: a drivable square with a hole, a walkway, a crossing, two dividers."""
    nodes, polygons, lines = [], [], []

    def node(x, y):
        nodes.append({"token": f"n{len(nodes)}", "x": x, "y": y})
        return nodes[-1]["token"]

    def polygon(ext, holes=()):
        polygons.append(
            {
                "token": f"p{len(polygons)}",
                "exterior_node_tokens": [node(*p) for p in ext],
                "holes": [{"node_tokens": [node(*p) for p in h]} for h in holes],
            }
        )
        return polygons[-1]["token"]

    def line(pts):
        lines.append({"token": f"l{len(lines)}", "node_tokens": [node(*p) for p in pts]})
        return lines[-1]["token"]

    square = [(500, 1500), (700, 1500), (700, 1700), (500, 1700)]
    hole = [(590, 1610), (596, 1610), (596, 1616), (590, 1616)]
    return {
        "version": "1.3",
        "canvas_edge": [2000.0, 2000.0],
        "node": nodes,
        "line": lines,
        "polygon": polygons,
        "drivable_area": [{"token": "da0", "polygon_tokens": [polygon(square, [hole])]}],
        "road_segment": [],
        "lane": [],
        "traffic_light": [],
        "lane_connector": [],
        "arcline_path_3": {},
        "connectivity": {},
        "road_block": [],
        "ped_crossing": [
            {
                "token": "pc0",
                "polygon_token": polygon([(560, 1590), (565, 1590), (565, 1620), (560, 1620)]),
                "road_segment_token": None,
            }
        ],
        "walkway": [{"token": "ww0", "polygon_token": polygon([(600, 1615), (620, 1615), (620, 1620), (600, 1620)])}],
        "stop_line": [],
        "carpark_area": [],
        "road_divider": [
            {"token": "rd0", "line_token": line([(520, 1598.2), (680, 1598.2)]), "road_segment_token": None}
        ],
        "lane_divider": [{"token": "ld0", "line_token": line([(580, 1580), (580, 1640)]), "lane_divider_segments": []}],
    }


def write_fixture(root: str, version: str = "v1.0-mini", *, with_map: bool = True) -> str:
    """Write the dataroot under ``root``; return ``root``."""
    tables = {
        k: []
        for k in (
            "category",
            "attribute",
            "visibility",
            "instance",
            "sensor",
            "calibrated_sensor",
            "ego_pose",
            "log",
            "scene",
            "sample",
            "sample_data",
            "sample_annotation",
            "map",
        )
    }
    for i, name in enumerate(CATEGORIES):
        tables["category"].append({"token": f"cat{i}", "name": name, "description": name})
    for i, lvl in enumerate(("v0-40", "v40-60", "v60-80", "v80-100")):
        tables["visibility"].append({"token": str(i + 1), "level": lvl, "description": lvl})
    for c, ch in enumerate(CAMS):
        tables["sensor"].append({"token": f"sensor_{ch}", "channel": ch, "modality": "camera"})
    for si, s in enumerate(SCENES):
        log_tok, scene_tok = f"log{si}", f"scene{si}"
        tables["log"].append(
            {
                "token": log_tok,
                "logfile": f"log-{si}",
                "vehicle": "n015",
                "date_captured": s["date"],
                "location": s["location"],
            }
        )
        tables["map"].append(
            {
                "token": f"map{si}",
                "log_tokens": [log_tok],
                "category": "semantic_prior",
                "filename": f"maps/map{si}.png",
            }
        )
        samples = [f"s{si}_{k}" for k in range(KEYFRAMES)]
        for k, tok in enumerate(samples):
            tables["sample"].append(
                {
                    "token": tok,
                    "timestamp": int(T0[si] + k * 500000),
                    "scene_token": scene_tok,
                    "prev": samples[k - 1] if k else "",
                    "next": samples[k + 1] if k + 1 < KEYFRAMES else "",
                }
            )
        tables["scene"].append(
            {
                "token": scene_tok,
                "log_token": log_tok,
                "nbr_samples": KEYFRAMES,
                "first_sample_token": samples[0],
                "last_sample_token": samples[-1],
                "name": s["name"],
                "description": s["description"],
            }
        )
        last_j = (KEYFRAMES - 1) * (SWEEPS + 1) + POST
        for c, ch in enumerate(CAMS):
            cs_tok = f"cs{si}_{ch}"
            fx = FX.get(ch, 25.32)
            tables["calibrated_sensor"].append(
                {
                    "token": cs_tok,
                    "sensor_token": f"sensor_{ch}",
                    "translation": [
                        1.7 * np.cos(np.deg2rad(CAM_YAW_DEG[ch])) + 0.3 * si,
                        0.9 * np.sin(np.deg2rad(CAM_YAW_DEG[ch])),
                        1.55,
                    ],
                    "rotation": quat_from_matrix(cam_rotation(ch)),
                    "camera_intrinsic": [[fx, 0.0, 16.3], [0.0, fx, 8.73], [0.0, 0.0, 1.0]],
                }
            )
            js = [j for j in range(-PRE, last_j + 1) if (si, ch, j) != DROPPED]
            toks = [f"sd{si}_{ch}_{j}" for j in js]
            for n, (j, tok) in enumerate(zip(js, toks)):
                t = frame_time(si, ch, j)
                key = j >= 0 and j % (SWEEPS + 1) == 0 and j // (SWEEPS + 1) < KEYFRAMES
                sample = samples[min(KEYFRAMES - 1, max(0, -(-j // (SWEEPS + 1))))]
                folder = "samples" if key else "sweeps"
                fname = f"{folder}/{ch}/n015-{si}__{ch}__{t}.jpg"
                trans, r = ego_pose(si, t)
                tables["ego_pose"].append(
                    {
                        "token": f"ep_{tok}",
                        "timestamp": t,
                        "translation": trans.tolist(),
                        "rotation": quat_from_matrix(r),
                    }
                )
                tables["sample_data"].append(
                    {
                        "token": tok,
                        "sample_token": sample,
                        "ego_pose_token": f"ep_{tok}",
                        "calibrated_sensor_token": cs_tok,
                        "timestamp": t,
                        "fileformat": "jpg",
                        "is_key_frame": key,
                        "height": H,
                        "width": W,
                        "filename": fname,
                        "prev": toks[n - 1] if n else "",
                        "next": toks[n + 1] if n + 1 < len(toks) else "",
                    }
                )
                _write_jpeg(os.path.join(root, fname), colour(si, c, j))
    for si_, inst, cat, keyed in ANNOTATIONS:
        itok = f"inst_{inst}"
        ks = sorted(keyed)
        atoks = [f"ann_{inst}_{k}" for k in ks]
        tables["instance"].append(
            {
                "token": itok,
                "category_token": f"cat{CATEGORIES.index(cat)}",
                "nbr_annotations": len(ks),
                "first_annotation_token": atoks[0],
                "last_annotation_token": atoks[-1],
            }
        )
        for n, (k, atok) in enumerate(zip(ks, atoks)):
            x, y, z, w, length, h, yaw = keyed[k]
            tables["sample_annotation"].append(
                {
                    "token": atok,
                    "sample_token": f"s{si_}_{k}",
                    "instance_token": itok,
                    "visibility_token": "4",
                    "attribute_tokens": [],
                    "translation": [x, y, z],
                    "size": [w, length, h],
                    "rotation": quat_from_matrix(rot(np.deg2rad(yaw))),
                    "num_lidar_pts": 10,
                    "num_radar_pts": 1,
                    "prev": atoks[n - 1] if n else "",
                    "next": atoks[n + 1] if n + 1 < len(atoks) else "",
                }
            )
    os.makedirs(os.path.join(root, version), exist_ok=True)
    for name, records in tables.items():
        with open(os.path.join(root, version, f"{name}.json"), "w") as f:
            json.dump(records, f)
    from PIL import Image

    os.makedirs(os.path.join(root, "maps"), exist_ok=True)
    for si in range(len(SCENES)):
        Image.fromarray(np.zeros((4, 4), np.uint8)).save(os.path.join(root, "maps", f"map{si}.png"))
    if with_map:
        os.makedirs(os.path.join(root, "maps", "expansion"), exist_ok=True)
        with open(os.path.join(root, "maps", "expansion", "boston-seaport.json"), "w") as f:
            json.dump(_map_expansion(), f)
    return root
