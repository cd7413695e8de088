import numpy as np
import pytest

from jaxdrive import geometry
from jaxdrive.data import schema
from jaxdrive.data.synthetic import generate_clip

SMALL = dict(frames=5, height=32, width=56)


def _hull(points):
    """Convex hull (counter-clockwise) of 2D points, monotone chain."""
    pts = sorted(map(tuple, np.asarray(points, np.float64)))

    def half(seq):
        out = []
        for p in seq:
            while (
                len(out) >= 2
                and ((out[-1][0] - out[-2][0]) * (p[1] - out[-2][1]) - (out[-1][1] - out[-2][1]) * (p[0] - out[-2][0]))
                <= 0
            ):
                out.pop()
            out.append(p)
        return out

    lower, upper = half(pts), half(pts[::-1])
    return np.array(lower[:-1] + upper[:-1])


def _outside_distance(hull, pts):
    """Max over edges of the signed distance outside the CCW hull (<= 0 inside)."""
    a, b = hull, np.roll(hull, -1, axis=0)
    edge = b - a
    normal = np.stack([edge[:, 1], -edge[:, 0]], -1) / np.linalg.norm(edge, axis=-1, keepdims=True)
    return ((pts[:, None, :] - a[None]) * normal[None]).sum(-1).max(-1)


def _project(clip, boxes, view):
    corners = geometry.box_corners(boxes)
    cam = geometry.ego_to_camera(corners, clip["cam_to_ego"][view])
    pix, depth = geometry.project_to_image(cam, clip["intrinsics"][view])
    return np.asarray(pix), np.asarray(depth)


def _agent_raycast(clip, view, frame):
    """Independent per-pixel nearest-agent ray cast (ego frame, slab test) -> track id map."""
    _, _, height, width = clip["instance_ids"].shape
    k = clip["intrinsics"][view].astype(np.float64)
    c2e = clip["cam_to_ego"][view].astype(np.float64)
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    d_cam = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones_like(u)], -1)
    d_ego = d_cam @ c2e[:3, :3].T
    best = np.full((height, width), np.inf)
    ids = np.full((height, width), -1)
    for box, tid, ok in zip(clip["boxes"][frame], clip["box_ids"][frame], clip["box_valid"][frame]):
        if not ok:
            continue
        box = box.astype(np.float64)
        c, s = np.cos(box[6]), np.sin(box[6])
        rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        o = (c2e[:3, 3] - box[:3]) @ rot
        d = d_ego @ rot
        with np.errstate(divide="ignore", invalid="ignore"):
            ta = (-box[3:6] / 2 - o) / d
            tb = (box[3:6] / 2 - o) / d
        tn = np.nanmax(np.fmin(ta, tb), -1)
        tf = np.nanmin(np.fmax(ta, tb), -1)
        hit = (tn <= tf) & (tn > 0.05) & (tn < best)
        best[hit], ids[hit] = tn[hit], tid
    return ids


@pytest.fixture(scope="module")
def clip6():
    return generate_clip(3, views=6, **SMALL)


def test_schema_and_determinism(clip6):
    sizes = schema.check_clip(clip6, source="synthetic")
    assert sizes["V"] == 6 and sizes["F"] == 5 and sizes["H"] == 32 and sizes["W"] == 56
    again = generate_clip(3, views=6, **SMALL)
    for name in schema.CLIP_FIELDS:
        np.testing.assert_array_equal(clip6[name], again[name], err_msg=name)
    assert clip6["caption"] == again["caption"] and clip6["fps"] == again["fps"]
    other = generate_clip(4, views=6, **SMALL)
    assert not np.array_equal(clip6["video"], other["video"])
    assert not np.array_equal(clip6["ego_to_world"], other["ego_to_world"])


def test_cameras_follow_nuscenes_rig(clip6):
    k = clip6["intrinsics"]
    np.testing.assert_allclose(k[:, 0, 2], 28.0)
    np.testing.assert_allclose(k[:, 1, 2], 16.0)
    forward = clip6["cam_to_ego"][:, :3, 2]  # camera z axis in the ego frame
    yaw = np.degrees(np.arctan2(forward[:, 1], forward[:, 0]))
    np.testing.assert_allclose(yaw, [0, -55, -110, 180, 110, 55], atol=1e-4)
    np.testing.assert_allclose(clip6["cam_to_ego"][:, :3, 1], np.tile([0, 0, -1], (6, 1)), atol=1e-6)
    assert np.all(np.abs(clip6["cam_to_ego"][:, 2, 3] - 1.5) < 0.1)


@pytest.mark.parametrize("seed", [0, 1, 2, 5])
def test_instance_pixels_lie_inside_projected_boxes(seed):
    clip = generate_clip(seed, views=6, frames=5, height=48, width=84, num_agents=16)
    assert instances_inside_projected_boxes(clip, (0, 4)) > 0


def instances_inside_projected_boxes(clip, frames) -> int:
    """Assert that every pixel of each box's track id lies within 1 pixel of the box's projected
    hull (boxes wholly in front of the camera); return how many (frame, view, box) were checked."""
    checked = 0
    for frame in frames:
        for view in range(clip["video"].shape[0]):
            ids = clip["instance_ids"][view, frame]
            valid = clip["box_valid"][frame]
            pix, depth = _project(clip, clip["boxes"][frame][valid], view)
            for b, tid in enumerate(clip["box_ids"][frame][valid]):
                rows, cols = np.nonzero(ids == tid)
                if depth[b].min() <= 0.1 or not len(rows):
                    continue
                centres = np.stack([cols + 0.5, rows + 0.5], -1)
                assert _outside_distance(_hull(pix[b]), centres).max() <= 1.0, (frame, view, tid)
                checked += 1
    return checked


@pytest.mark.parametrize("seed", [0, 7])
def test_agent_occlusion_matches_an_independent_ray_cast(seed):
    # Without scenery, agents are hidden only by nearer agents: the id map must equal an
    # independent nearest-hit ray cast of the clip's own boxes (up to float32 edge pixels).
    clip = generate_clip(seed, views=6, frames=3, height=40, width=70, num_agents=20, scenery=False)
    labelled, mismatched = 0, 0
    for frame in range(3):
        for view in range(6):
            ref = _agent_raycast(clip, view, frame)
            got = clip["instance_ids"][view, frame]
            labelled += (ref >= 0).sum()
            mismatched += (ref != got).sum()
    assert labelled > 50
    assert mismatched <= max(2, 0.01 * labelled), (mismatched, labelled)


def test_nearer_agent_wins():
    # Where a box lies entirely nearer than another and their projections overlap, no pixel of the
    # farther box lies inside the nearer one's projection.
    seen = 0
    for seed in range(6):
        clip = generate_clip(seed, views=6, frames=3, height=40, width=70, num_agents=20, scenery=False)
        for frame in range(3):
            for view in range(6):
                ids = clip["instance_ids"][view, frame]
                valid = clip["box_valid"][frame]
                pix, depth = _project(clip, clip["boxes"][frame][valid], view)
                tids = clip["box_ids"][frame][valid]
                front = np.flatnonzero(depth.min(-1) > 0.1)
                for i in front:
                    near_pixels = (ids == tids[i]).sum()
                    for j in front:
                        if i == j or depth[i].max() >= depth[j].min() or near_pixels == 0:
                            continue
                        rows, cols = np.nonzero(ids == tids[j])
                        centres = np.stack([cols + 0.5, rows + 0.5], -1)
                        inside = _outside_distance(_hull(pix[i]), centres) < -1.0
                        assert not inside.any(), (seed, frame, view, tids[i], tids[j])
                        seen += bool((_outside_distance(_hull(pix[i]), pix[j]) < -1.0).any())
        if seen:
            break
    assert seen > 0


def test_clearly_visible_agent_has_pixels():
    found = 0
    for seed in range(6):
        clip = generate_clip(seed, views=1, frames=1, height=48, width=84, num_agents=20, scenery=False)
        valid = clip["box_valid"][0]
        boxes, tids = clip["boxes"][0][valid], clip["box_ids"][0][valid]
        pix, depth = _project(clip, boxes, 0)
        for b in range(len(boxes)):
            centre = pix[b].mean(0)
            others = [
                j
                for j in range(len(boxes))
                if j != b and depth[j].min() < depth[b].max() and (_outside_distance(_hull(pix[j]), pix[b]) < 2.0).any()
            ]
            if depth[b].min() > 2.0 and 10 < centre[0] < 74 and 8 < centre[1] < 40 and not others:
                assert (clip["instance_ids"][0, 0] == tids[b]).sum() > 0, (seed, tids[b])
                found += 1
    assert found > 0


def test_waypoints_and_poses(clip6):
    np.testing.assert_array_equal(clip6["waypoints"][0], [0.0, 0.0])
    first = np.linalg.inv(clip6["ego_to_world"][0])
    rel = first @ clip6["ego_to_world"][:, :, 3].T
    np.testing.assert_allclose(clip6["waypoints"], rel[:2].T, atol=1e-4)
    pose = clip6["ego_to_world"]
    np.testing.assert_allclose(
        pose[:, :3, :3] @ np.swapaxes(pose[:, :3, :3], 1, 2), np.tile(np.eye(3), (5, 1, 1)), atol=1e-9
    )
    np.testing.assert_allclose(pose[:, 2, 3], 0.0)


def test_bev_has_road_under_the_ego():
    for seed in range(4):
        clip = generate_clip(seed, views=1, frames=9, height=16, width=28, bev_size=(40, 48))
        bev = clip["bev_map"]
        assert bev.shape == (9, 40, 48, 8)
        drivable = schema.BEV_CLASSES.index("drivable_area")
        assert (bev[:, 19:21, 23:25, drivable] == 1).all()
        assert set(np.unique(bev)) <= {0, 1}
        walk = schema.BEV_CLASSES.index("walkway")
        assert bev[..., walk].any() and not bev[..., drivable].all()


def test_boxes_ids_and_classes(clip6):
    valid = clip6["box_valid"]
    assert 3 <= valid[0].sum() <= 20
    assert (valid == valid[:1]).all()
    np.testing.assert_array_equal(clip6["box_ids"], np.broadcast_to(clip6["box_ids"][:1], valid.shape))
    ids = clip6["box_ids"][0][valid[0]]
    assert len(set(ids.tolist())) == len(ids) and (ids >= 0).all()
    assert set(clip6["box_classes"][valid].tolist()) <= set(range(len(schema.OBJECT_CLASSES)))
    assert (clip6["boxes"][valid][:, 3:6] > 0).all()
    # Boxes stand on the road: centre height = half the box height.
    np.testing.assert_allclose(clip6["boxes"][valid][:, 2], clip6["boxes"][valid][:, 5] / 2, atol=1e-4)
    seen = set(np.unique(clip6["instance_ids"]).tolist()) - {-1}
    assert seen <= set(ids.tolist())


def test_looks_differ():
    day = generate_clip(11, views=1, look="day", **SMALL)
    night = generate_clip(11, views=1, look="night", **SMALL)
    rain = generate_clip(11, views=1, look="rain", **SMALL)
    assert night["video"].mean() < 0.6 * day["video"].mean()
    assert not np.array_equal(rain["video"], day["video"])
    assert "night" in night["caption"] and "night" not in day["caption"]
    np.testing.assert_array_equal(day["instance_ids"], night["instance_ids"])


def test_single_front_view():
    one = generate_clip(3, views=1, look="day", **SMALL)
    six = generate_clip(3, views=6, look="day", **SMALL)
    assert one["video"].shape == (1, 5, 32, 56, 3)
    np.testing.assert_array_equal(one["cam_to_ego"][0], six["cam_to_ego"][0])
    np.testing.assert_array_equal(one["video"][0], six["video"][0])
    assert "CAM_FRONT" in one["caption"]


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(views=3), "views"),
        (dict(frames=0), "frames"),
        (dict(height=4), "height"),
        (dict(width=7), "width"),
        (dict(fps=0.0), "fps"),
        (dict(look="dusk"), "look"),
        (dict(num_agents=21), "num_agents"),
        (dict(num_agents=-1), "num_agents"),
        (dict(bev_size=(0, 8)), "bev_size"),
        (dict(seed=-1), "seed"),
        (dict(seed=1.5), "seed"),
    ],
)
def test_bad_arguments_name_the_argument(kwargs, name):
    kwargs = {"seed": 0, **kwargs}
    with pytest.raises(ValueError, match=name):
        generate_clip(kwargs.pop("seed"), **kwargs)
