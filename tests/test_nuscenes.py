"""The nuScenes reader on a tiny fixture in the official format; cross-checked against the devkit."""

import json
import logging
import os
import shutil
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(__file__))

from jaxdrive.data import nuscenes as ns  # noqa: E402
from jaxdrive.data.schema import BEV_CLASSES, CAMERAS, OBJECT_CLASSES, check_clip  # noqa: E402

import nuscenes_fixture as fx  # noqa: E402

STEP = fx.SWEEPS + 1
FRAMES = (fx.KEYFRAMES - 1) * STEP + 1  # CAM_FRONT frames per scene inside the keyframe span


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return fx.write_fixture(str(tmp_path_factory.mktemp("nuscenes")))


@pytest.fixture(scope="module")
def clips(root):
    return {c["meta"]["scene"]: c for c in ns.read_clips(root, frames=FRAMES)}


def _copy(root, tmp_path):
    dst = str(tmp_path / "copy")
    shutil.copytree(root, dst)
    return dst


def _hand_box(scene, inst, t_sample_pair, t, ego_t):
    """Expected ego-frame box of a fixture instance, interpolated by hand."""
    keyed = next(a[3] for a in fx.ANNOTATIONS if a[0] == scene and a[1] == inst)
    (k0, t0), (k1, t1) = t_sample_pair
    a = (t - t0) / (t1 - t0)
    b0, b1 = np.array(keyed[k0]), np.array(keyed[k1])
    centre, wlh = (1 - a) * b0[:3] + a * b1[:3], (1 - a) * b0[3:6] + a * b1[3:6]
    dyaw = (b1[6] - b0[6] + 180) % 360 - 180
    yaw = np.deg2rad(b0[6] + a * dyaw)
    trans, r = fx.ego_pose(scene, ego_t)
    xyz = r.T @ (centre - trans)
    rb = r.T @ fx.rot(yaw)
    return np.array([*xyz, wlh[1], wlh[0], wlh[2], np.arctan2(rb[1, 0], rb[0, 0])])


def test_clips_pass_the_schema(clips):
    assert sorted(clips) == ["scene-0001", "scene-0002"]
    for clip in clips.values():
        sizes = check_clip(clip, source=clip["meta"]["scene"])
        assert (sizes["V"], sizes["F"], sizes["H"], sizes["W"]) == (6, FRAMES, fx.H, fx.W)
        assert clip["bev_map"].shape[1:] == (200, 200, len(BEV_CLASSES))
        assert clip["fps"] == pytest.approx(12.0, rel=1e-3)
        np.testing.assert_allclose(clip["waypoints"][0], 0.0)
    assert clips["scene-0001"]["caption"].endswith("in 6 cameras of a car at boston-seaport during summer day.")
    assert clips["scene-0002"]["caption"].endswith("at singapore-onenorth during winter night.")


def test_time_alignment_picks_the_nearest_sweep(clips):
    clip = clips["scene-0001"]
    for v, ch in enumerate(CAMERAS):
        for f in range(FRAMES):
            j = 3 if (0, ch, f) == fx.DROPPED else f  # CAM_BACK's sweep 4 is missing: 3 is nearest
            assert clip["meta"]["sample_data_tokens"][v][f] == f"sd0_{ch}_{j}"
            np.testing.assert_allclose(clip["video"][v, f].reshape(-1, 3).mean(0), fx.colour(0, v, j), atol=3)
    assert list(clip["meta"]["timestamps"]) == [fx.frame_time(0, "CAM_FRONT", f) for f in range(FRAMES)]


def test_stride_views_resize_and_intrinsics(root):
    (clip, *rest) = list(
        ns.read_clips(
            root, frames=7, stride=2, views=("CAM_BACK", "CAM_FRONT"), image_hw=(8, 16), scenes=["scene-0002"]
        )
    )
    assert rest == [] and clip["video"].shape == (2, 7, 8, 16, 3)
    assert clip["caption"].startswith("This is a driving scene video captured by camera in CAM_BACK, CAM_FRONT ")
    assert clip["meta"]["sample_data_tokens"][1] == [f"sd1_CAM_FRONT_{j}" for j in range(0, 13, 2)]
    # stored 32x16 images, c + 0.5 for the pixel-centre convention, then halved
    np.testing.assert_allclose(clip["intrinsics"][0], [[8.0, 0, 8.4], [0, 8.0, 4.615], [0, 0, 1]], rtol=1e-6)
    np.testing.assert_allclose(clip["intrinsics"][1], [[12.66, 0, 8.4], [0, 12.66, 4.615], [0, 0, 1]], rtol=1e-6)
    np.testing.assert_allclose(clip["cam_to_ego"][0, :3, :3], fx.cam_rotation("CAM_BACK"), atol=1e-6)
    np.testing.assert_allclose(clip["cam_to_ego"][0, :3, 3], [-1.7 + 0.3, 0.0, 1.55], atol=1e-6)


def test_box_interpolation_worked_example():
    def ann(x, yaw_deg, w):
        return {
            "translation": [x, 2.0 * x, 1.0],
            "size": [w, 4.0, 1.5],
            "rotation": fx.quat_from_matrix(fx.rot(np.deg2rad(yaw_deg))),
        }

    track = [(1_000_000, ann(10.0, 170.0, 2.0)), (1_500_000, ann(20.0, -170.0, 3.0))]
    centre, wlh, yaw = ns._box_at(track, 1_250_000)  # midway: the linear midpoint
    np.testing.assert_allclose(centre, [15.0, 30.0, 1.0])
    np.testing.assert_allclose(wlh, [2.5, 4.0, 1.5])
    assert abs(abs(yaw) - np.pi) < 1e-9  # 170 -> -170 goes through 180, not through 0
    centre, _, yaw = ns._box_at(track, 1_375_000)
    assert np.rad2deg(yaw) == pytest.approx(-175.0) and centre[0] == pytest.approx(17.5)
    assert ns._box_at(track, 999_999) is None and ns._box_at(track, 1_500_001) is None
    assert ns._box_at(track, 1_500_000)[2] == pytest.approx(np.deg2rad(-170.0))


def test_boxes_in_the_ego_frame_by_hand(clips):
    clip = clips["scene-0001"]
    car = clip["meta"]["instance_tokens"].index("inst_car")
    t_s = [int(fx.T0[0] + k * 500000) for k in range(fx.KEYFRAMES)]
    for f in (0, 3, 6, 10):  # keyframe (at its sample time), sweeps, keyframe, sweep after the +-pi wrap
        k = f // STEP
        t = t_s[k] if f % STEP == 0 else fx.frame_time(0, "CAM_FRONT", f)
        pair = ((k, t_s[k]), (k + 1, t_s[k + 1])) if k + 1 < fx.KEYFRAMES else ((k - 1, t_s[k - 1]), (k, t_s[k]))
        want = _hand_box(0, "car", pair, t, fx.frame_time(0, "CAM_FRONT", f))
        slot = list(clip["box_ids"][f]).index(car)
        got = clip["boxes"][f, slot]
        np.testing.assert_allclose(got[:6], want[:6], atol=1e-4)
        assert abs((got[6] - want[6] + np.pi) % (2 * np.pi) - np.pi) < 1e-5
    trans0, r0 = fx.ego_pose(0, fx.frame_time(0, "CAM_FRONT", 0))
    trans, _ = fx.ego_pose(0, fx.frame_time(0, "CAM_FRONT", FRAMES - 1))
    np.testing.assert_allclose(clip["waypoints"][-1], (r0.T @ (trans - trans0))[:2], atol=1e-5)


def test_classes_ids_and_an_instance_appearing_mid_scene(clips, root, caplog):
    clip = clips["scene-0001"]
    insts = clip["meta"]["instance_tokens"]
    assert sorted(insts) == ["inst_car", "inst_ped"]  # the dog (animal) is dropped
    valid = clip["box_valid"]
    assert list(valid.sum(1)) == [1] * STEP + [2] * (FRAMES - STEP)  # ped: from its first keyframe on
    for f in range(FRAMES):
        for n in np.flatnonzero(valid[f]):
            name = insts[clip["box_ids"][f, n]]
            assert OBJECT_CLASSES[clip["box_classes"][f, n]] == {"inst_car": "car", "inst_ped": "pedestrian"}[name]
    assert np.all(clip["box_ids"][~valid] == -1) and np.all(clip["boxes"][~valid] == 0)
    other = clips["scene-0002"]
    got = {
        other["meta"]["instance_tokens"][i]: OBJECT_CLASSES[c]
        for i, c in zip(other["box_ids"][0], other["box_classes"][0])
    }
    assert got == {"inst_truck": "truck", "inst_cone": "traffic_cone"}
    with caplog.at_level(logging.INFO, logger="jaxdrive.data.nuscenes"):
        list(ns.read_clips(root, frames=FRAMES, scenes=["scene-0001"]))
    assert "dropped 2 annotations" in caplog.text and "'animal': 2" in caplog.text
    assert "4 CAM_FRONT sweeps outside the keyframe span" in caplog.text


def test_bev_map_against_the_map_geometry(clips, root, caplog):
    clip = clips["scene-0001"]
    hm, wm, res = 200, 200, 0.5
    for f in (0, FRAMES - 1):
        e2w = clip["ego_to_world"][f]
        yaw = np.arctan2(e2w[1, 0], e2w[0, 0])
        r, c = np.meshgrid(np.arange(hm), np.arange(wm), indexing="ij")
        x, y = (hm / 2 - r - 0.5) * res, (wm / 2 - c - 0.5) * res
        gx = e2w[0, 3] + np.cos(yaw) * x - np.sin(yaw) * y
        gy = e2w[1, 3] + np.sin(yaw) * x + np.cos(yaw) * y

        def rect(x0, x1, y0, y1):
            return (gx > x0) & (gx < x1) & (gy > y0) & (gy < y1)

        drivable = rect(500, 700, 1500, 1700) & ~rect(590, 596, 1610, 1616)
        bev = clip["bev_map"][f]
        np.testing.assert_array_equal(bev[..., BEV_CLASSES.index("drivable_area")], drivable)
        np.testing.assert_array_equal(bev[..., BEV_CLASSES.index("walkway")], rect(600, 620, 1615, 1620))
        np.testing.assert_array_equal(bev[..., BEV_CLASSES.index("ped_crossing")], rect(560, 565, 1590, 1620))
        lane = bev[..., BEV_CLASSES.index("lane_divider")].astype(bool)
        near = (np.abs(gx - 580) < res * 0.75) & (gy > 1580 - res) & (gy < 1640 + res)
        assert lane.sum() >= 60 / res and not np.any(lane & ~near)
        assert bev[..., BEV_CLASSES.index("road_divider")].sum() >= 2 * 50 / res - 2
        assert not bev[..., BEV_CLASSES.index("stop_line")].any()
    assert not clips["scene-0002"]["bev_map"].any()
    with caplog.at_level(logging.WARNING, logger="jaxdrive.data.nuscenes"):
        assert len(list(ns.read_clips(root, frames=4, scenes=["scene-0002"]))) == 3
    assert caplog.text.count("no map expansion") == 1 and "singapore-onenorth.json" in caplog.text


def test_too_long_clip_names_the_scene(root, caplog):
    with pytest.raises(ValueError, match=rf"scene 'scene-0002': has {FRAMES} CAM_FRONT frames.*needs {FRAMES + 1}"):
        next(ns.read_clips(root, frames=FRAMES + 1, scenes=["scene-0002"]))
    with caplog.at_level(logging.WARNING, logger="jaxdrive.data.nuscenes"):
        assert list(ns.read_clips(root, frames=5, stride=4)) == []  # spans 17 frames
    assert "scene 'scene-0001': has 13 CAM_FRONT frames, a clip of frames=5 with stride=4 needs 17" in caplog.text
    assert "2 of 2 scenes left out" in caplog.text


def test_missing_table_field_and_image_name_the_file(root, tmp_path):
    bad = _copy(root, tmp_path)
    os.remove(os.path.join(bad, "v1.0-mini", "ego_pose.json"))
    with pytest.raises(ValueError, match=r"ego_pose\.json: expected the nuScenes table 'ego_pose'"):
        ns.load_tables(bad, "v1.0-mini")
    bad = _copy(root, tmp_path / "b")
    path = os.path.join(bad, "v1.0-mini", "sample_data.json")
    with open(path) as f:
        records = json.load(f)
    del records[5]["timestamp"]
    with open(path, "w") as f:
        json.dump(records, f)
    with pytest.raises(ValueError, match=r"sample_data\.json: record .*expected field 'timestamp'"):
        ns.load_tables(bad, "v1.0-mini")
    records[5]["timestamp"] = 0
    records[5]["ego_pose_token"] = "nope"
    with open(path, "w") as f:
        json.dump(records, f)
    with pytest.raises(ValueError, match=r"sample_data\.json: record .*ego_pose\.json, got 'nope'"):
        list(ns.read_clips(bad, frames=4))
    bad = _copy(root, tmp_path / "c")
    name = f"sweeps/CAM_FRONT_LEFT/n015-0__CAM_FRONT_LEFT__{fx.frame_time(0, 'CAM_FRONT_LEFT', 2)}.jpg"
    os.remove(os.path.join(bad, name))
    with pytest.raises(ValueError, match=name):
        list(ns.read_clips(bad, frames=FRAMES, scenes=["scene-0001"]))
    with pytest.raises(ValueError, match="scenes: expected names"):
        list(ns.read_clips(root, frames=4, scenes=["scene-9999"]))


# ------------------------------------------------------------------ against the official devkit


def test_against_the_devkit(root, clips):
    nuscenes = pytest.importorskip("nuscenes.nuscenes")
    from pyquaternion import Quaternion

    nusc = nuscenes.NuScenes(version="v1.0-mini", dataroot=root, verbose=False)
    checked = 0
    for clip in clips.values():
        toks = clip["meta"]["sample_data_tokens"]
        for v in range(len(CAMERAS)):
            cs = nusc.get("calibrated_sensor", nusc.get("sample_data", toks[v][0])["calibrated_sensor_token"])
            np.testing.assert_allclose(
                clip["cam_to_ego"][v, :3, :3], Quaternion(cs["rotation"]).rotation_matrix, atol=1e-6
            )
            np.testing.assert_allclose(clip["cam_to_ego"][v, :3, 3], cs["translation"], atol=1e-6)
            k = np.array(cs["camera_intrinsic"])
            k[:2, 2] += 0.5
            np.testing.assert_allclose(clip["intrinsics"][v], k, rtol=1e-6)
        for f, tok in enumerate(toks[0]):
            sd = nusc.get("sample_data", tok)
            pose = nusc.get("ego_pose", sd["ego_pose_token"])
            np.testing.assert_allclose(
                clip["ego_to_world"][f, :3, :3], Quaternion(pose["rotation"]).rotation_matrix, atol=1e-12
            )
            np.testing.assert_allclose(clip["ego_to_world"][f, :3, 3], pose["translation"], atol=1e-9)
            if sd["is_key_frame"]:
                boxes = [nusc.get_box(a) for a in nusc.get("sample", sd["sample_token"])["anns"]]
            else:
                boxes = nusc.get_boxes(tok)
            theirs = {}
            for box in boxes:
                box.translate(-np.array(pose["translation"]))
                box.rotate(Quaternion(pose["rotation"]).inverse)
                inst = nusc.get("sample_annotation", box.token)["instance_token"]
                theirs[inst] = box
            ours = {
                clip["meta"]["instance_tokens"][i]: b
                for i, b, ok in zip(clip["box_ids"][f], clip["boxes"][f], clip["box_valid"][f])
                if ok
            }
            # ours: the devkit's boxes of mapped classes, less (in sweeps) the ones it could not interpolate
            sample = nusc.get("sample", sd["sample_token"])
            prev = {
                nusc.get("sample_annotation", a)["instance_token"]
                for a in (nusc.get("sample", sample["prev"])["anns"] if sample["prev"] else [])
            }
            want = {
                i for i, b in theirs.items() if b.name in ns.CATEGORY_TO_CLASS and (sd["is_key_frame"] or i in prev)
            }
            assert set(ours) == want, (clip["meta"]["scene"], f)
            for inst, b in ours.items():
                ref = theirs[inst]
                np.testing.assert_allclose(b[:3], ref.center, atol=1e-4)
                np.testing.assert_allclose(b[3:6], [ref.wlh[1], ref.wlh[0], ref.wlh[2]], atol=1e-5)
                # heading = direction of the box's x axis in the ego xy plane. (pyquaternion's
                # yaw_pitch_roll[0] uses w*z - x*y and differs by ~1e-5 once the ego pitches and rolls.)
                rm = ref.orientation.rotation_matrix
                yaw = np.arctan2(rm[1, 0], rm[0, 0])
                assert abs((b[6] - yaw + np.pi) % (2 * np.pi) - np.pi) < 1e-5
                checked += 1
    assert checked == FRAMES + (FRAMES - STEP) + 2 * FRAMES  # car, ped from keyframe 1 on, truck, cone


def test_an_unreadable_image_is_named_or_its_clip_skipped_and_counted(root, tmp_path, caplog):
    bad = _copy(root, tmp_path)
    clean = list(ns.read_clips(root, frames=4))  # 3 clips per scene
    tables = ns.load_tables(root)
    token = clean[1]["meta"]["sample_data_tokens"][2][0]  # scene 1, clip 2, third view, first frame
    path = os.path.join(bad, tables["sample_data"][token]["filename"])
    with open(path, "rb") as f:
        jpeg = f.read()
    with open(path, "wb") as f:
        f.write(jpeg[: len(jpeg) // 2])  # a truncated JPEG
    with pytest.raises(ValueError, match=rf"^{path}: expected a readable image"):
        list(ns.read_clips(bad, frames=4))
    uses = [any(token in row for row in c["meta"]["sample_data_tokens"]) for c in clean]
    skipped = []
    with caplog.at_level(logging.WARNING, logger="jaxdrive.data.nuscenes"):
        got = list(ns.read_clips(bad, frames=4, skip_bad_records=True, skipped=skipped))
    assert skipped == [("scene-0001", 4 * i, path) for i, u in enumerate(uses[:3]) if u] and len(skipped) >= 1
    kept = [c for c, u in zip(clean, uses) if not u]  # every other clip, unchanged
    assert [c["meta"]["scene"] for c in got] == [c["meta"]["scene"] for c in kept]
    for a, b in zip(got, kept):
        np.testing.assert_array_equal(a["video"], b["video"])
        np.testing.assert_array_equal(a["boxes"], b["boxes"])
    assert caplog.text.count(path) == 1
    assert f"{len(skipped)} clips left out: a camera image could not be read" in caplog.text
    with pytest.raises(ValueError, match="skip_bad_records: expected True or False, got 'yes'"):
        next(ns.read_clips(root, frames=4, skip_bad_records="yes"))
