"""A procedural multi-view driving world in numpy: clips in the record of :mod:`jaxdrive.data.schema`.

:func:`generate_clip` builds a small town (a main street with cross streets, lanes and markings,
sidewalks, buildings, trees and street lamps, see :mod:`jaxdrive.data.synth_world`), drives the
ego along a smooth route that speeds up, slows down and may turn at an intersection, adds 3-20
agents that follow lanes, keep their distance and stop (:mod:`jaxdrive.data.synth_agents`), and
ray casts every pixel of a nuScenes-like camera rig (:mod:`jaxdrive.data.synth_render`), so the
video, the per-pixel instance ids, the 3D boxes and the BEV map agree exactly. Everything is
deterministic by ``seed``.

Choices: ``box_valid`` marks the agents that exist (all of them, in every frame, visible or not;
slots past the number of agents are padding); ``N = max_boxes`` (20 by default) so clips batch
without re-padding. The ego frame's origin is the rear axle on the ground (nuScenes), so camera
mounts and box centres sit at their heights above the road.
"""

from __future__ import annotations

import numpy as np

from jaxdrive.data import schema
from jaxdrive.data.bev import cell_centres
from jaxdrive.data.synth_agents import traffic
from jaxdrive.data.synth_render import camera_rig, pixel_rays, raycast, yaw_matrix
from jaxdrive.data.synth_shade import (DAYTIME, LOOKS, box_colour, ego_headlights, fog, ground_colour,
                                      lamp_light, rain_streaks, sky_colour)
from jaxdrive.data.synth_world import AGENT_KIND, LAMP, ego_route, road_classes, static_scenery
from jaxdrive.validate import check_choice, check_positive_int, check_range

TOWNS = ("synthtown-harbour", "synthtown-old-quarter", "gridville-centre", "boxford-heights",
         "raycast-bay")
SEASONS = ("spring", "summer", "autumn", "winter")
MAX_AGENTS = 20


def _pose(xy, yaw):
    m = np.tile(np.eye(4), (len(yaw), 1, 1))
    m[:, :3, :3] = yaw_matrix(yaw)
    m[:, :2, 3] = xy
    return m


def bev_maps(ego_to_world, crosses, bev_size, bev_range):
    """Rasterise the road layout around each ego pose -> uint8 ``[F, Hm, Wm, 8]`` (x up, y left)."""
    rx, ry = bev_range[0] / bev_size[0], bev_range[1] / bev_size[1]
    pts = cell_centres(bev_size, (rx, ry))                                    # [Hm, Wm, 2]
    rot, trans = ego_to_world[:, :2, :2], ego_to_world[:, :2, 3]
    world = np.einsum("fij,hwj->fhwi", rot, pts) + trans[:, None, None]
    return road_classes(world[..., 0], world[..., 1], crosses, pad=0.5 * max(rx, ry)).astype(np.uint8)


def _render_frame(cam_to_world, intrinsics, rays, boxes, scene, look, season, light, ego_xy, ego_yaw):
    """Colour ``[V, H, W, 3]`` float32 and box index ``[V, H, W]`` (-1: ground or sky) of one frame."""
    views, height, width, _ = rays.shape
    npx = views * height * width
    depth, owner, axis, local = (a.reshape(npx, *a.shape[3:]) for a in
                                 raycast(cam_to_world, intrinsics, boxes, height, width))
    dirs = (rays.reshape(views, -1, 3) @ np.swapaxes(cam_to_world[:, :3, :3], -1, -2)).reshape(npx, 3)
    cam_pos = np.repeat(cam_to_world[:, :3, 3], height * width, axis=0)
    down = np.flatnonzero(dirs[:, 2] < -1e-9)
    t_ground = np.full(npx, np.inf)
    t_ground[down] = -cam_pos[down, 2] / dirs[down, 2]
    ground = np.flatnonzero(t_ground < depth)
    owner[ground] = -1
    hit = np.flatnonzero(owner >= 0)
    sky = np.flatnonzero(~(np.minimum(t_ground, depth) < np.inf))
    col = np.empty((npx, 3), np.float32)
    col[sky] = sky_colour(dirs[sky], look)
    p = LOOKS[look]
    gpts = cam_pos[ground] + t_ground[ground, None] * dirs[ground]
    gx, gy = gpts[:, 0], gpts[:, 1]
    light_g = p["ambient"] + p["sun"] * light[2]
    if look == "night":
        rel_x, rel_y = gx - ego_xy[0], gy - ego_xy[1]
        ce, se = np.cos(ego_yaw), np.sin(ego_yaw)
        light_g = light_g + ego_headlights(rel_x * ce + rel_y * se, -rel_x * se + rel_y * ce)
        lamps = scene["lamps"]
        light_g = light_g + lamp_light(gx, gy, lamps[np.linalg.norm(lamps - ego_xy, axis=1) < 70.0])
    col[ground] = ground_colour(gx, gy, scene["crosses"], look, season) * np.asarray(light_g)[..., None]
    col[hit] = box_colour(owner[hit], axis[hit], local[hit], boxes, scene["colours"], scene["kinds"],
                          scene["classes"], scene["box_key"], light, look)
    solid = np.concatenate([ground, hit])
    col[solid] = fog(col[solid], np.concatenate([t_ground[ground], depth[hit]]), look)
    return col.reshape(views, height, width, 3), owner.reshape(views, height, width)


def _check_args(seed, views, frames, height, width, fps, num_agents, look, max_boxes, bev_size, bev_range):
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed: expected a non-negative integer, got {seed!r}")
    check_choice("views", views, (1, 6))
    check_positive_int("frames", frames)
    check_positive_int("height", height, minimum=8)
    check_positive_int("width", width, minimum=8)
    if isinstance(fps, bool) or not isinstance(fps, (int, float, np.number)):
        raise ValueError(f"fps: expected a positive number, got {fps!r}")
    check_range("fps", fps, 0.0, 1000.0, lo_open=True)
    check_positive_int("max_boxes", max_boxes)
    if num_agents is not None:
        check_positive_int("num_agents", num_agents, minimum=0)
        if num_agents > max_boxes:
            raise ValueError(f"num_agents: expected at most max_boxes = {max_boxes}, got {num_agents}")
    if look is not None:
        check_choice("look", look, tuple(LOOKS))
    if len(tuple(bev_size)) != 2:
        raise ValueError(f"bev_size: expected (Hm, Wm), got {bev_size!r}")
    for n in bev_size:
        check_positive_int("bev_size", n)
    if len(tuple(bev_range)) != 2 or not all(float(r) > 0 for r in bev_range):
        raise ValueError(f"bev_range: expected two positive extents in metres (x, y), got {bev_range!r}")


def generate_clip(seed, *, views=6, frames=33, height=64, width=112, fps=12.0, num_agents=None,
                  look=None, max_boxes=MAX_AGENTS, bev_size=(64, 64), bev_range=(100.0, 100.0),
                  scenery=True) -> dict:
    """One clip of the synthetic town, a dict per :data:`jaxdrive.data.schema.CLIP_FIELDS`.

    seed: non-negative int; the same seed gives identical arrays. views: 6 (the CAMERAS rig) or 1
    (CAM_FRONT). frames >= 1 at ``fps``. height, width >= 8 pixels. num_agents: 0..max_boxes other
    road users (default: 3-20 drawn by the seed). look: "day", "night" or "rain" (default: drawn by
    the seed). max_boxes: N, the box slots. bev_size (Hm, Wm) cells over bev_range (x, y) metres,
    ego at the centre, x up. scenery=False leaves out buildings, trees and lamps (tests use it to
    check agent occlusion alone).
    """
    _check_args(seed, views, frames, height, width, fps, num_agents, look, max_boxes, bev_size, bev_range)
    fps = float(fps)
    rng = np.random.default_rng(int(seed))
    if look is None:
        look = ("day", "night", "rain")[rng.choice(3, p=[0.55, 0.25, 0.2])]
    season = SEASONS[rng.integers(len(SEASONS))]
    town = TOWNS[rng.integers(len(TOWNS))]
    if num_agents is None:
        num_agents = int(rng.integers(3, min(MAX_AGENTS, max_boxes) + 1))

    ego_xy, ego_yaw, crosses, _ = ego_route(rng, frames, fps)
    if scenery:
        s_boxes, s_colours, s_kinds = static_scenery(rng, crosses, ego_xy, season=season)
    else:
        s_boxes, s_colours, s_kinds = np.zeros((0, 7)), np.zeros((0, 3)), np.zeros(0, np.int32)
    agents, a_xy, a_yaw = traffic(rng, num_agents, crosses[1], ego_xy, ego_yaw, fps)
    n_agents = len(agents)
    a_size = np.array([a["size"] for a in agents]).reshape(-1, 3)
    a_cls = np.array([a["cls"] for a in agents], np.int32)
    a_col = np.array([rng.uniform(0.1, 0.95, 3) if a["name"] != "bus" else (0.85, 0.6, 0.1)
                      for a in agents]).reshape(-1, 3)
    track_ids = np.sort(rng.choice(1000, size=n_agents, replace=False)).astype(np.int32)
    sun_az = rng.uniform(0, 2 * np.pi)
    light = np.array([np.cos(sun_az) * 0.5, np.sin(sun_az) * 0.5, 0.75])
    light /= np.linalg.norm(light)

    ego_to_world = _pose(ego_xy, ego_yaw)
    intrinsics, cam_to_ego = camera_rig(views, height, width)
    rays = pixel_rays(intrinsics, height, width)                             # [V, H, W, 3]
    n_static = len(s_boxes)
    colours = np.concatenate([s_colours, a_col])
    kinds = np.concatenate([s_kinds, AGENT_KIND + a_cls])
    classes = np.concatenate([np.full(n_static, -1, np.int32), a_cls])
    box_key = np.arange(n_static + n_agents, dtype=np.float64)
    scene = dict(colours=colours, kinds=kinds, classes=classes, box_key=box_key, crosses=crosses,
                 lamps=s_boxes[s_kinds == LAMP, :2])

    video = np.empty((views, frames, height, width, 3), np.float32)
    instance = np.full((views, frames, height, width), -1, np.int32)
    boxes_ego = np.zeros((frames, max_boxes, 7), np.float32)
    for f in range(frames):
        a_boxes = np.concatenate([a_xy[f], 0.5 * a_size[:, 2:3], a_size, a_yaw[:, None]], 1)
        world_boxes = np.concatenate([s_boxes, a_boxes])
        cam_to_world = ego_to_world[f] @ cam_to_ego                           # [V, 4, 4]
        img, owner = _render_frame(cam_to_world, intrinsics, rays, world_boxes, scene, look, season, light,
                                   ego_xy[f], ego_yaw[f])
        video[:, f] = img
        agent = owner >= n_static
        instance[:, f][agent] = track_ids[owner[agent] - n_static]
        # Boxes in this frame's ego frame.
        inv = np.linalg.inv(ego_to_world[f])
        centre = np.concatenate([a_boxes[:, :3], np.ones((n_agents, 1))], 1) @ inv.T
        rel_yaw = (a_yaw - ego_yaw[f] + np.pi) % (2 * np.pi) - np.pi
        boxes_ego[f, :n_agents] = np.concatenate([centre[:, :3], a_size, rel_yaw[:, None]], 1)
    if look == "rain":
        rain_streaks(rng, video)
    valid = np.zeros((frames, max_boxes), bool)
    valid[:, :n_agents] = True
    classes_out = np.zeros((frames, max_boxes), np.int32)
    classes_out[:, :n_agents] = a_cls
    ids_out = np.full((frames, max_boxes), -1, np.int32)
    ids_out[:, :n_agents] = track_ids
    first = np.linalg.inv(ego_to_world[0])
    waypoints = np.einsum("ij,fj->fi", first, ego_to_world[:, :, 3])[:, :2]
    clip = {
        "video": np.clip(np.round(video * 255.0), 0, 255).astype(np.uint8),
        "intrinsics": intrinsics.astype(np.float32),
        "cam_to_ego": cam_to_ego.astype(np.float32),
        "ego_to_world": ego_to_world,
        "boxes": boxes_ego,
        "box_classes": classes_out,
        "box_ids": ids_out,
        "box_valid": valid,
        "bev_map": bev_maps(ego_to_world, crosses, tuple(bev_size), tuple(map(float, bev_range))),
        "waypoints": waypoints.astype(np.float32),
        "instance_ids": instance,
        "fps": fps,
        "caption": schema.caption(sensor="CAM_FRONT" if views == 1 else "6 surround cameras",
                                  location=town, season=season, daytime=DAYTIME[look]),
    }
    return clip


def write_synthetic_dataset(out, *, train: int, validation: int = 0, seed: int = 0, overwrite: bool = False,
                            **clip_kwargs):
    """A TFDS dataset of ``train`` (+ ``validation``) synthetic scenes under ``out``, one seed per
    scene (``seed + i``: reproducible, disjoint splits); ``clip_kwargs`` go to :func:`generate_clip`.
    Returns the dataset path."""
    from jaxdrive.data.tfds_io import write_dataset

    def clips(first, count):
        for i in range(first, first + count):
            yield generate_clip(seed + i, **clip_kwargs)
    splits = {"train": clips(0, train)}
    if validation:
        splits["validation"] = clips(train, validation)
    return write_dataset(out, splits, name="jaxdrive_synthetic", overwrite=overwrite,
                         metadata={"source": "synthetic", "seed": seed, **clip_kwargs})
