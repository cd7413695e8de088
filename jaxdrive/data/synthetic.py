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
from jaxdrive.data import synth_routes as routes
from jaxdrive.data.bev import cell_centres
from jaxdrive.data.synth_agents import simulate, traffic
from jaxdrive.data.synth_render import camera_rig, pixel_rays, raycast, yaw_matrix
from jaxdrive.data.synth_routes import ROUTES
from jaxdrive.data.synth_shade import (
    DAYTIME,
    LOOKS,
    box_colour,
    ego_headlights,
    fog,
    ground_colour,
    lamp_light,
    rain_streaks,
    sky_colour,
)
from jaxdrive.data.synth_world import AGENT_KIND, LAMP, ego_route, road_classes, static_scenery
from jaxdrive.validate import check_choice, check_positive_int, check_range

TOWNS = ("synthtown-harbour", "synthtown-old-quarter", "gridville-centre", "boxford-heights", "raycast-bay")
SEASONS = ("spring", "summer", "autumn", "winter")
MAX_AGENTS = 20
COUNTERFACTUAL_START = 8  # the first frame a counterfactual route changes (after the given frames)


def _pose(xy, yaw):
    m = np.tile(np.eye(4), (len(yaw), 1, 1))
    m[:, :3, :3] = yaw_matrix(yaw)
    m[:, :2, 3] = xy
    return m


def bev_maps(ego_to_world, crosses, bev_size, bev_range):
    """Rasterise the road layout around each ego pose -> uint8 ``[F, Hm, Wm, 8]`` (x up, y left)."""
    rx, ry = bev_range[0] / bev_size[0], bev_range[1] / bev_size[1]
    pts = cell_centres(bev_size, (rx, ry))  # [Hm, Wm, 2]
    rot, trans = ego_to_world[:, :2, :2], ego_to_world[:, :2, 3]
    world = np.einsum("fij,hwj->fhwi", rot, pts) + trans[:, None, None]
    return road_classes(world[..., 0], world[..., 1], crosses, pad=0.5 * max(rx, ry)).astype(np.uint8)


def _render_frame(cam_to_world, intrinsics, rays, boxes, scene, look, season, light, ego_xy, ego_yaw):
    """Colour ``[V, H, W, 3]`` float32 and box index ``[V, H, W]`` (-1: ground or sky) of one frame."""
    views, height, width, _ = rays.shape
    npx = views * height * width
    depth, owner, axis, local = (
        a.reshape(npx, *a.shape[3:]) for a in raycast(cam_to_world, intrinsics, boxes, height, width)
    )
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
    col[hit] = box_colour(
        owner[hit],
        axis[hit],
        local[hit],
        boxes,
        scene["colours"],
        scene["kinds"],
        scene["classes"],
        scene["box_key"],
        light,
        look,
    )
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


def _draw_scene(seed, views, frames, height, width, fps, num_agents, look, max_boxes, scenery):
    """Every random draw of a clip, in the order the recorded clip makes them: the look, the town,
    the ego's route, the scenery, the traffic (simulated against the recorded ego), colours, track
    ids and the sun. Returns the scene dict and the generator (rain streaks draw from it last)."""
    rng = np.random.default_rng(int(seed))
    if look is None:
        look = ("day", "night", "rain")[rng.choice(3, p=[0.55, 0.25, 0.2])]
    season = SEASONS[rng.integers(len(SEASONS))]
    town = TOWNS[rng.integers(len(TOWNS))]
    if num_agents is None:
        num_agents = int(rng.integers(3, min(MAX_AGENTS, max_boxes) + 1))

    route = ego_route(rng, frames, fps)
    if scenery:
        s_boxes, s_colours, s_kinds = static_scenery(rng, route.crosses, route.xy, season=season)
    else:
        s_boxes, s_colours, s_kinds = np.zeros((0, 7)), np.zeros((0, 3)), np.zeros(0, np.int32)
    agents, a_xy, a_yaw = traffic(rng, num_agents, route.crosses[1], route.xy, route.yaw, fps)
    n_agents = len(agents)
    a_size = np.array([a["size"] for a in agents]).reshape(-1, 3)
    a_cls = np.array([a["cls"] for a in agents], np.int32)
    a_col = np.array([rng.uniform(0.1, 0.95, 3) if a["name"] != "bus" else (0.85, 0.6, 0.1) for a in agents]).reshape(
        -1, 3
    )
    track_ids = np.sort(rng.choice(1000, size=n_agents, replace=False)).astype(np.int32)
    sun_az = rng.uniform(0, 2 * np.pi)
    light = np.array([np.cos(sun_az) * 0.5, np.sin(sun_az) * 0.5, 0.75])
    light /= np.linalg.norm(light)
    n_static = len(s_boxes)
    scene = dict(
        colours=np.concatenate([s_colours, a_col]),
        kinds=np.concatenate([s_kinds, AGENT_KIND + a_cls]),
        classes=np.concatenate([np.full(n_static, -1, np.int32), a_cls]),
        box_key=np.arange(n_static + n_agents, dtype=np.float64),
        crosses=route.crosses,
        lamps=s_boxes[s_kinds == LAMP, :2],
    )
    return dict(
        views=views,
        frames=frames,
        height=height,
        width=width,
        fps=fps,
        look=look,
        season=season,
        town=town,
        route=route,
        s_boxes=s_boxes,
        agents=agents,
        a_xy=a_xy,
        a_yaw=a_yaw,
        a_size=a_size,
        a_cls=a_cls,
        track_ids=track_ids,
        light=light,
        scene=scene,
        max_boxes=max_boxes,
    ), rng


def _render_clip(d, rng, ego_xy, ego_yaw, a_xy, a_yaw, bev_size, bev_range) -> dict:
    """Ray cast the scene ``d`` with the ego at ``ego_xy`` / ``ego_yaw`` and the agents at
    ``a_xy`` / ``a_yaw`` -> the clip record."""
    views, frames, height, width, look = d["views"], d["frames"], d["height"], d["width"], d["look"]
    max_boxes, a_size, track_ids = d["max_boxes"], d["a_size"], d["track_ids"]
    n_static, n_agents = len(d["s_boxes"]), len(d["agents"])
    ego_to_world = _pose(ego_xy, ego_yaw)
    intrinsics, cam_to_ego = camera_rig(views, height, width)
    rays = pixel_rays(intrinsics, height, width)  # [V, H, W, 3]
    video = np.empty((views, frames, height, width, 3), np.float32)
    instance = np.full((views, frames, height, width), -1, np.int32)
    boxes_ego = np.zeros((frames, max_boxes, 7), np.float32)
    for f in range(frames):
        a_boxes = np.concatenate([a_xy[f], 0.5 * a_size[:, 2:3], a_size, a_yaw[:, None]], 1)
        world_boxes = np.concatenate([d["s_boxes"], a_boxes])
        cam_to_world = ego_to_world[f] @ cam_to_ego  # [V, 4, 4]
        img, owner = _render_frame(
            cam_to_world,
            intrinsics,
            rays,
            world_boxes,
            d["scene"],
            look,
            d["season"],
            d["light"],
            ego_xy[f],
            ego_yaw[f],
        )
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
    classes_out[:, :n_agents] = d["a_cls"]
    ids_out = np.full((frames, max_boxes), -1, np.int32)
    ids_out[:, :n_agents] = track_ids
    first = np.linalg.inv(ego_to_world[0])
    waypoints = np.einsum("ij,fj->fi", first, ego_to_world[:, :, 3])[:, :2]
    return {
        "video": np.clip(np.round(video * 255.0), 0, 255).astype(np.uint8),
        "intrinsics": intrinsics.astype(np.float32),
        "cam_to_ego": cam_to_ego.astype(np.float32),
        "ego_to_world": ego_to_world,
        "boxes": boxes_ego,
        "box_classes": classes_out,
        "box_ids": ids_out,
        "box_valid": valid,
        "bev_map": bev_maps(ego_to_world, d["route"].crosses, tuple(bev_size), tuple(map(float, bev_range))),
        "waypoints": waypoints.astype(np.float32),
        "instance_ids": instance,
        "fps": d["fps"],
        "caption": schema.caption(
            sensor="CAM_FRONT" if views == 1 else "6 surround cameras",
            location=d["town"],
            season=d["season"],
            daytime=DAYTIME[look],
        ),
    }


def generate_clip(
    seed,
    *,
    views=6,
    frames=33,
    height=64,
    width=112,
    fps=12.0,
    num_agents=None,
    look=None,
    max_boxes=MAX_AGENTS,
    bev_size=(64, 64),
    bev_range=(100.0, 100.0),
    scenery=True,
) -> dict:
    """One clip of the synthetic town, a dict per :data:`jaxdrive.data.schema.CLIP_FIELDS`.

    seed: non-negative int; the same seed gives identical arrays. views: 6 (the CAMERAS rig) or 1
    (CAM_FRONT). frames >= 1 at ``fps``. height, width >= 8 pixels. num_agents: 0..max_boxes other
    road users (default: 3-20 drawn by the seed). look: "day", "night" or "rain" (default: drawn by
    the seed). max_boxes: N, the box slots. bev_size (Hm, Wm) cells over bev_range (x, y) metres,
    ego at the centre, x up. scenery=False leaves out buildings, trees and lamps (tests use it to
    check agent occlusion alone).
    """
    return counterfactual_clip(
        seed,
        "recorded",
        views=views,
        frames=frames,
        height=height,
        width=width,
        fps=fps,
        num_agents=num_agents,
        look=look,
        max_boxes=max_boxes,
        bev_size=bev_size,
        bev_range=bev_range,
        scenery=scenery,
    )


def counterfactual_clip(
    seed,
    route: str,
    *,
    start: int = COUNTERFACTUAL_START,
    views=6,
    frames=33,
    height=64,
    width=112,
    fps=12.0,
    num_agents=None,
    look=None,
    max_boxes=MAX_AGENTS,
    bev_size=(64, 64),
    bev_range=(100.0, 100.0),
    scenery=True,
) -> dict:
    """The clip of :func:`generate_clip` with the same arguments, its ego driven along ``route``
    (one of :data:`jaxdrive.data.synth_routes.ROUTES`) from frame ``start`` on: the same town,
    scenery, look and agents, re-rendered; frames before ``start`` are the recorded clip's.
    ``recorded`` gives :func:`generate_clip`'s clip bit for bit. A route the scene cannot drive (off
    the road, out of the map, into an agent, no intersection to branch at) is a ``ValueError``
    (:class:`~jaxdrive.data.synth_routes.UndrivableRoute`) naming the route and the clip's seed. See
    :mod:`jaxdrive.data.synth_routes` for the routes and how traffic reacts.
    """
    _check_args(seed, views, frames, height, width, fps, num_agents, look, max_boxes, bev_size, bev_range)
    if route not in ROUTES:
        raise ValueError(f"route: expected one of {', '.join(ROUTES)}, got {route!r}")
    if route != "recorded" and not (isinstance(start, (int, np.integer)) and 1 <= start < frames):
        raise ValueError(f"start: expected a frame in [1, {frames - 1}] for a clip of {frames} frames, got {start!r}")
    kw = dict(
        views=views,
        frames=frames,
        height=height,
        width=width,
        fps=fps,
        num_agents=num_agents,
        look=look,
        max_boxes=max_boxes,
        scenery=scenery,
    )
    d, rng, ego_xy, ego_yaw, a_xy, a_yaw = _drive(seed, route, start, kw)
    return _render_clip(d, rng, ego_xy, ego_yaw, a_xy, a_yaw, bev_size, bev_range)


def _drive(seed, route, start, kw):
    """The scene of ``seed`` and the ego's and agents' paths along ``route`` (no rendering):
    ``(scene, rng, ego_xy, ego_yaw, agents_xy, agents_yaw)``; UndrivableRoute when it cannot."""
    d, rng = _draw_scene(
        seed,
        kw.get("views", 6),
        kw.get("frames", 33),
        kw.get("height", 64),
        kw.get("width", 112),
        float(kw.get("fps", 12.0)),
        kw.get("num_agents"),
        kw.get("look"),
        kw.get("max_boxes", MAX_AGENTS),
        kw.get("scenery", True),
    )
    rec = d["route"]
    driver = routes.plan(route, rec, d["fps"], int(start), clip=f"seed {seed}")
    if driver is None:
        return d, rng, rec.xy, rec.yaw, d["a_xy"], d["a_yaw"]
    a_xy, a_yaw, ego_xy, ego_yaw = simulate(d["agents"], rec.xy, rec.yaw, d["fps"], driver=driver)
    routes.check_drivable(
        route, f"seed {seed}", rec, driver, ego_xy, ego_yaw, a_xy, a_yaw, d["a_size"][:, :2], d["track_ids"]
    )
    return d, rng, ego_xy, ego_yaw, a_xy, a_yaw


def counterfactual_split(route: str, split: str = "validation") -> str:
    """The dataset split that holds the ``split`` clips' counterfactual renders along ``route``."""
    return f"{split}_route_" + route.replace("-", "_")


def drivable_clips(
    names,
    first_seed: int,
    count: int,
    *,
    start: int = COUNTERFACTUAL_START,
    skip_undrivable: bool = True,
    **clip_kwargs,
) -> dict:
    """``{route: [i, ...]}``: which of the ``count`` clips of seeds ``first_seed + i`` can drive
    each route of ``names`` from frame ``start`` (the routes are driven, nothing is rendered). An
    undrivable clip is left out, or with ``skip_undrivable=False`` a ``ValueError`` naming the
    route and the clip. What :func:`write_synthetic_dataset` checks before writing; the demo keeps
    the routes that every one of its validation scenes can drive."""
    names = routes.parse_routes(names, "counterfactuals", recorded=False)
    out = {}
    for name in names:
        out[name] = []
        for i in range(count):
            try:
                _drive(first_seed + i, name, int(start), clip_kwargs)
                out[name].append(i)
            except routes.UndrivableRoute as e:
                if not skip_undrivable:
                    raise ValueError(f"{e} (validation clip {i}; skip_undrivable leaves it out)") from None
    return out


def write_synthetic_dataset(
    out,
    *,
    train: int,
    validation: int = 0,
    seed: int = 0,
    overwrite: bool = False,
    counterfactuals=(),
    train_counterfactuals=(),
    counterfactual_start: int = COUNTERFACTUAL_START,
    skip_undrivable: bool = False,
    drivable: dict | None = None,
    **clip_kwargs,
):
    """A TFDS dataset of ``train`` (+ ``validation``) synthetic scenes under ``out``, one seed per
    scene (``seed + i``: reproducible, disjoint splits); ``clip_kwargs`` go to :func:`generate_clip`.
    Returns the dataset path.

    ``counterfactuals`` (routes of :data:`jaxdrive.data.synth_routes.ROUTES`, a list or a
    comma-separated string) stores, beside the validation split, each validation clip's
    counterfactual render along each route from frame ``counterfactual_start`` on, in the split
    :func:`counterfactual_split` (same record schema). The metadata's ``counterfactuals`` says which
    validation clip each row belongs to (see :func:`read_counterfactuals`). Every route is driven
    before anything is rendered: a route some validation clip cannot drive is a ``ValueError``
    naming the route and the clip, and nothing is written; with ``skip_undrivable`` that clip is
    left out of that route's split instead (a route no clip can drive is still an error).
    ``drivable``: what :func:`drivable_clips` returned for these routes and validation clips, when
    the caller has it (the demo chooses its routes by it): the routes are then not driven twice.

    ``train_counterfactuals``: the same for the training scenes, in splits ``train_route_<route>``
    (the metadata's ``train_routes``), read by :class:`jaxdrive.data.route_mix.RoutedScenes` so that
    one history is trained with several futures. A training scene that cannot drive a route is
    always left out of that route (it trains on the others); a route no training scene drives is a
    ``ValueError``. The metadata's ``synthesis_seconds`` has each split's rendering time.
    """
    import time

    from jaxdrive.data.tfds_io import write_dataset

    names = routes.parse_routes(counterfactuals, "counterfactuals", recorded=False)
    train_names = routes.parse_routes(train_counterfactuals, "train_counterfactuals", recorded=False)
    if names and not validation:
        raise ValueError(f"counterfactuals: expected validation clips to re-render, got validation={validation}")
    frames = clip_kwargs.get("frames", 33)
    if (names or train_names) and not (
        isinstance(counterfactual_start, (int, np.integer)) and 1 <= counterfactual_start < frames
    ):
        raise ValueError(
            f"counterfactual_start: expected a frame in [1, {frames - 1}] for clips of {frames} "
            f"frames, got {counterfactual_start!r}"
        )
    start = int(counterfactual_start)
    if drivable is None:
        drivable = drivable_clips(
            names, seed + train, validation, start=start, skip_undrivable=skip_undrivable, **clip_kwargs
        )
    elif sorted(drivable) != sorted(names):
        raise ValueError(f"drivable: expected the clips of the routes {names}, got routes {sorted(drivable)}")
    train_drivable = (
        drivable_clips(train_names, seed, train, start=start, skip_undrivable=True, **clip_kwargs)
        if train_names
        else {}
    )
    for option, count, found in [
        ("counterfactuals", validation, drivable),
        ("train_counterfactuals", train, train_drivable),
    ]:
        for name, rows in found.items():
            if not rows:
                raise ValueError(
                    f"{option}: expected route {name!r} to be drivable by at least one of the "
                    f"{count} {'validation' if option == 'counterfactuals' else 'training'} clips, got none"
                )
    seconds: dict[str, float] = {}

    def timed(split, clips):  # each split's rendering time, for the metadata
        seconds[split] = 0.0
        for clip_fn in clips:
            t = time.perf_counter()
            clip = clip_fn()
            seconds[split] = round(seconds[split] + time.perf_counter() - t, 3)
            yield clip

    def scenes(first, count):
        return (lambda i=i: generate_clip(seed + i, **clip_kwargs) for i in range(first, first + count))

    def along(first, rows, name):
        return (lambda r=r: counterfactual_clip(seed + first + r, name, start=start, **clip_kwargs) for r in rows)

    plan = {"train": scenes(0, train)}
    if validation:
        plan["validation"] = scenes(train, validation)
    for name in train_names:
        plan[counterfactual_split(name, "train")] = along(0, train_drivable[name], name)
    for name in names:
        plan[counterfactual_split(name)] = along(train, drivable[name], name)
    splits = {split: timed(split, clips) for split, clips in plan.items()}
    meta = {"source": "synthetic", "seed": seed, **clip_kwargs, "synthesis_seconds": seconds}
    if names or train_names:
        meta["counterfactuals"] = {"start": start}
    if names:
        meta["counterfactuals"]["routes"] = {n: {"split": counterfactual_split(n), "clips": drivable[n]} for n in names}
    if train_names:
        meta["counterfactuals"]["train_routes"] = {
            n: {"split": counterfactual_split(n, "train"), "clips": train_drivable[n]} for n in train_names
        }
    return write_dataset(out, splits, name="jaxdrive_synthetic", overwrite=overwrite, metadata=meta)


def read_counterfactuals(path) -> dict:
    """What a dataset holds of counterfactual routes: ``{"start": frame, "routes": {route: {"split":
    name, "clips": [validation clip index of each row]}}, "train_routes": {the same for the
    training scenes}}`` (each key only where the dataset has such renders); ``{}`` when it holds none."""
    from jaxdrive.data.tfds_io import dataset_info

    return dict(dataset_info(path).get("metadata", {}).get("counterfactuals", {}))
