"""User-given routes (``--route``): files, named manoeuvres, the poses they drive, and how they are
placed on and checked against the scene's road map (a turn at the intersection ahead, off-road files
refused, an absent map unchecked)."""

import json

import numpy as np
import pytest

from jaxdrive.generate.route import BRAKING, TURN_RADIUS, load_route


def test_a_json_route_with_times_gives_poses_through_its_points(tmp_path):
    path = tmp_path / "r.json"
    path.write_text(json.dumps({"points": [[0, 0], [5, 0], [10, 1]], "times": [0, 0.5, 1.0]}))
    route = load_route(str(path), duration=2.0)
    poses = route.poses(frames=13, fps=12.0)  # the last point at frame 12
    np.testing.assert_allclose(poses[[0, 6, 12], :2, 3], [[0, 0], [5, 0], [10, 1]], atol=1e-4)
    # objects and bare rows read the same
    path.write_text(json.dumps([{"x": 0, "y": 0, "t": 0}, {"x": 5, "y": 0, "t": 0.5}, {"x": 10, "y": 1, "t": 1}]))
    np.testing.assert_allclose(load_route(str(path), duration=2.0).poses(13, 12.0), poses, atol=1e-6)
    path.write_text(json.dumps([[0, 0], [5, 0], [10, 1]]))  # no times: spread over the clip
    np.testing.assert_allclose(
        load_route(str(path), duration=2.0).poses(13, 12.0)[[0, 6, 12], :2, 3], [[0, 0], [5, 0], [10, 1]], atol=1e-4
    )


def test_a_csv_route(tmp_path):
    path = tmp_path / "r.csv"
    path.write_text("x,y,t\n0,0,0\n4,0,0.5\n8,0.5,1\n")
    route = load_route(str(path), duration=1.0)
    np.testing.assert_allclose(route.points, [[0, 0], [4, 0], [8, 0.5]])
    np.testing.assert_allclose(route.times, [0, 0.5, 1])


def test_named_manoeuvres():
    straight = load_route("straight 5 m/s", duration=2.0).poses(frames=25, fps=12.0)
    np.testing.assert_allclose(straight[:, 0, 3], np.arange(25) * 5 / 12, atol=1e-4)
    np.testing.assert_allclose(straight[:, 1, 3], 0, atol=1e-6)
    # a left turn: a quarter circle of the turn radius, heading +90 degrees at its end, then on along +y
    left = load_route("left turn", duration=6.0)
    end_of_arc = np.argmin(np.abs(left.times - np.pi / 2 * TURN_RADIUS / 8.0))
    np.testing.assert_allclose(left.points[end_of_arc], [TURN_RADIUS, TURN_RADIUS], atol=0.5)
    poses = left.poses(frames=73, fps=12.0)
    yaw = np.arctan2(poses[:, 1, 0], poses[:, 0, 0])
    assert abs(yaw[0]) < 1e-6 and abs(yaw[-1] - np.pi / 2) < 0.01 and poses[-1, 1, 3] > TURN_RADIUS
    right = load_route("Right turn 8 m/s", duration=6.0)
    np.testing.assert_allclose(right.points * [1, -1], left.points, atol=1e-5)
    # a stop: braking distance v^2 / 2a, then standing with the heading kept
    stop = load_route("stop", duration=6.0).poses(frames=73, fps=12.0)
    np.testing.assert_allclose(stop[-1, 0, 3], 10.0**2 / (2 * BRAKING), atol=1e-3)
    np.testing.assert_allclose(stop[-20:, :2, 3], np.broadcast_to(stop[-1, :2, 3], (20, 2)), atol=1e-3)
    np.testing.assert_allclose(stop[-1, :3, :3], np.eye(3), atol=1e-6)


@pytest.mark.parametrize(
    "name, text, match",
    [
        ("one.json", json.dumps([[0, 0]]), "expected at least 2 points, got 1"),
        ("nan.json", json.dumps([[0, 0], [1, float("nan")]]).replace("NaN", "NaN"), "row 2: expected finite values"),
        ("cols.json", json.dumps([[0, 0], [1, 2, 3, 4]]), "row 2: expected 2 values"),
        ("four.json", json.dumps([[0, 0, 0, 0], [1, 2, 3, 4]]), "row 1: expected 2 or 3 values"),
        ("keys.json", json.dumps([{"x": 0, "y": 0}, {"x": 1, "z": 0}]), "row 2: expected keys x, y"),
        ("start.json", json.dumps([[3, 0], [5, 0]]), r"row 1: expected the ego's start"),
        (
            "times.json",
            json.dumps({"points": [[0, 0], [1, 0], [2, 0]], "times": [0, 1, 1]}),
            "row 3: expected times increasing",
        ),
        ("cols.csv", "x,z\n0,0\n1,1\n", "row 1: expected the header 'x,y' or 'x,y,t'"),
        ("inf.csv", "x,y\n0,0\n1,inf\n", "row 3: expected finite values"),
        ("text.csv", "x,y\n0,0\n1,abc\n", "row 3: expected numbers"),
        ("bad.json", "{not json", "expected JSON or a .csv file"),
    ],
)
def test_bad_route_files_are_named_with_their_row(tmp_path, name, text, match):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(ValueError, match=match) as e:
        load_route(str(path), duration=1.0)
    assert str(path) in str(e.value)


def test_an_unknown_route_names_the_choices():
    with pytest.raises(ValueError, match=r"route: expected a JSON or CSV file or a manoeuvre \(straight, left turn"):
        load_route("u-turn", duration=1.0)


# ------------------------------------------------------------------ routes on the scene's road map

FPS, FRAMES = 12.0, 97  # 8 s: a turn at 8 m/s may start up to 64 m ahead


def _town(crosses, *, zeros=False, frames=FRAMES):
    """A clip recorded along the synthetic town's main street (lane y = -1.75, heading +x, 1 m a
    frame) with cross streets at world x = ``crosses``: ``(sample, clip)`` with the fields
    :func:`jaxdrive.generate.future.future_controls` reads; ``zeros``: a map with no road at all."""
    from jaxdrive.data.bev import cell_centres
    from jaxdrive.data.synth_world import road_classes

    poses = np.tile(np.eye(4, dtype=np.float32), (frames, 1, 1))
    poses[:, 0, 3], poses[:, 1, 3] = np.arange(frames), -1.75
    c = cell_centres((64, 64), (100 / 64, 100 / 64))
    bev = np.stack([road_classes(c[..., 0] + p[0, 3], c[..., 1] + p[1, 3], crosses) for p in poses]).astype(np.uint8)
    bev = np.zeros_like(bev) if zeros else bev
    sample = {
        "ego_to_world": poses,
        "boxes": np.zeros((frames, 1, 7), np.float32),
        "box_classes": np.full((frames, 1), -1, np.int32),
        "box_ids": np.full((frames, 1), -1, np.int32),
        "box_valid": np.zeros((frames, 1), bool),
        "bev_map": bev,
        "fps": np.float32(FPS),
        "frame_times": (np.arange(frames) / FPS).astype(np.float32),
    }
    return sample, {"bev_map": bev, "ego_to_world": poses}


def _drive(route, sample, clip, **kw):
    """``future_controls`` with ``route``: ``(world ego poses [F, 4, 4], route_drive, RouteWarnings)``."""
    import warnings

    from jaxdrive.generate.future import future_controls
    from jaxdrive.generate.route import RouteWarning

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        frames = len(sample["ego_to_world"])
        out = future_controls(sample, clip, frames=frames, keep=frames, route=route, **kw)
    return out["ego_to_world"], out["route_drive"], [w for w in caught if issubclass(w.category, RouteWarning)]


def _on_road_truth(poses, crosses, margin=0.9):
    """Whether the ego's centre and points ``margin`` m either side lie on the town's drivable area
    (the analytic layout the map was rasterised from, not the map)."""
    from jaxdrive.data.synth_world import road_classes

    yaw = np.arctan2(poses[:, 1, 0], poses[:, 0, 0])
    normal = np.stack([-np.sin(yaw), np.cos(yaw)], -1)
    pts = poses[None, :, :2, 3] + np.array([-margin, 0, margin])[:, None, None] * normal[None]
    return road_classes(pts[..., 0], pts[..., 1], crosses)[..., 0].all(0)


@pytest.mark.parametrize("name, side", [("left turn", 1), ("right turn", -1)])
def test_a_turn_starts_at_the_intersection_ahead_and_stays_on_the_road(name, side):
    from jaxdrive.data.synth_world import ROAD
    from jaxdrive.generate.route import TURN_RADIUS

    sample, clip = _town([40.0])
    route = load_route(name, duration=(FRAMES - 1) / FPS)
    where_it_is = route.poses(FRAMES, FPS)  # the manoeuvre alone: mid-block, off the road
    assert not _on_road_truth(sample["ego_to_world"][0].astype(np.float64) @ where_it_is, [40.0]).all()
    poses, drive, warned = _drive(route, sample, clip)
    poses = poses.astype(np.float64)
    assert warned == [] and drive["start_at"] == "intersection" and drive["map_checked"]
    assert drive["off_road"] is False and drive["off_road_metres"] == 0.0 and drive["off_road_from"] is None
    assert _on_road_truth(poses, [40.0]).all()
    # straight on along the lane until the start, then the arc: into the cross street, heading across
    start = drive["start"]
    assert start["y"] == 0.0 and 40.0 - ROAD - TURN_RADIUS < start["x"] < 40.0 - ROAD
    assert start["frame"] == int(start["x"] / 8.0 * FPS) and start["time"] == pytest.approx(start["x"] / 8.0, abs=1e-3)
    before = poses[: start["frame"] + 1]
    np.testing.assert_allclose(before[:, 1, 3], -1.75, atol=0.05)
    np.testing.assert_allclose(before[:, 0, 3], np.arange(len(before)) * 8.0 / FPS, atol=0.05)
    yaw = np.arctan2(poses[-1, 1, 0], poses[-1, 0, 0])
    assert abs(yaw - side * np.pi / 2) < 0.05 and abs(poses[-1, 0, 3] - 40.0) < ROAD


def test_without_an_intersection_in_reach_a_turn_starts_where_the_clip_is_with_one_warning():
    from jaxdrive.data.scene_map import SceneMap
    from jaxdrive.generate.route import drive_on_map

    frames = 49  # 4 s: the turn may start up to 32 m ahead; the cross street is farther
    sample, clip = _town([75.0], frames=frames)
    route = load_route("left turn", duration=(frames - 1) / FPS)
    poses, drive, warned = _drive(route, sample, clip)
    np.testing.assert_allclose(poses, sample["ego_to_world"][0] @ route.poses(frames, FPS), atol=1e-4)  # as before
    assert drive["start"] == {"frame": 0, "time": 0.0, "x": 0.0, "y": 0.0} and drive["start_at"] == "clip"
    assert drive["off_road"] and drive["off_road_metres"] > 3 and drive["off_road_from"]["frame"] > 0
    assert len(warned) == 1
    assert "no intersection within the 32 m" in str(warned[0].message) and "leaves the road" in str(warned[0].message)
    # the clips of one run share the warnings given: a second clip adds none
    scene = SceneMap.from_clip(clip["bev_map"], clip["ego_to_world"])
    given = {"no intersection"}
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        drive_on_map(route, sample["ego_to_world"][0], scene, frames, FPS, warned=given)
    assert caught == []


def test_a_turn_that_drives_beyond_the_scene_map_still_runs_with_one_warning(tmp_path):
    """The map reaches 50 m from the recorded path: a turn at 12 m/s for 8 s leaves it up the cross
    street. A named manoeuvre always runs (with its map controls blank there); a file does not."""
    sample, clip = _town([20.0])
    route = load_route("left turn 12 m/s", duration=(FRAMES - 1) / FPS)
    poses, drive, warned = _drive(route, sample, clip)
    assert drive["start_at"] == "intersection" and drive["off_road"] is False
    beyond = drive["beyond_map_from"]
    assert 50.0 < beyond["y"] < 50.0 + 12.0 / FPS + 1.0  # ~50 m from the recorded path (ego frame)
    assert beyond["frame"] == int(np.argmax(poses[:, 1, 3] - (-1.75) > 50.0))
    assert _on_road_truth(poses[: beyond["frame"]].astype(np.float64), [20.0]).all()
    assert len(warned) == 1 and (
        f"beyond the scene's map (the BEV maps the clip recorded) from frame {beyond['frame']}"
        in str(warned[0].message)
    )
    on_map, drive, warned = _drive(load_route("left turn", duration=3.0), *_town([20.0], frames=37))
    assert drive["beyond_map_from"] is None and warned == []
    far = tmp_path / "far.csv"  # the same path as a file is refused, unless allowed
    np.savetxt(far, poses[::8, :2, 3] - poses[0, :2, 3], delimiter=",", header="x,y", comments="")
    with pytest.raises(ValueError, match=rf"route {far} row \d+: expected a point on the scene's map"):
        _drive(load_route(str(far), duration=(FRAMES - 1) / FPS), sample, clip)
    _, drive, warned = _drive(load_route(str(far), duration=(FRAMES - 1) / FPS), sample, clip, allow_off_road=True)
    assert drive["beyond_map_from"] is not None and len(warned) == 1


def _off_road_file(tmp_path):
    path = tmp_path / "into_the_buildings.csv"  # straight on, then across the verge at about 20 m
    path.write_text("x,y,t\n0,0,0\n10,0,1\n20,12,2\n30,24,3\n")
    return path


def test_an_off_road_route_file_is_refused_before_anything_compiles_unless_allowed(tmp_path, monkeypatch):
    import jaxdrive.generate.future as future
    from jaxdrive.world_model import controls_hook

    path = _off_road_file(tmp_path)
    sample, clip = _town([200.0])
    cuts = []
    real_cut = future._cut_all
    monkeypatch.setattr(future, "_cut_all", lambda *a: cuts.append(1) or real_cut(*a))  # the first jitted call

    def hook(allow):
        plan = dict(route=str(path), frames=FRAMES, controls="recorded", allow_off_road=allow)
        drives = []
        return controls_hook(plan, (100.0, 100.0), None, 1, {}, drives), drives

    refused, _ = hook(False)
    with pytest.raises(
        ValueError,
        match=r"got [0-9.]+ m off the road from frame (\d+) \(t = [0-9.]+ s\) at "
        r"\([0-9.]+, [0-9.]+\) m; pass --allow-off-road",
    ) as e:
        refused(dict(sample), clip, "validation clip 0")
    assert f"route {path}: expected a path on the road of the scene's map (at most 3 m off it" in str(e.value)
    frame = int(e.value.args[0].split(" from frame ")[1].split()[0])
    assert 12 <= frame <= 24 and cuts == []  # it leaves the 7 m half-road between 10 m and 20 m ahead
    allowed, drives = hook(True)
    with pytest.warns(UserWarning, match="driven off the road"):
        out = allowed(dict(sample), clip, "validation clip 0")
    assert "route_drive" not in out and len(out["ego_to_world"]) == FRAMES and cuts == [1]
    assert drives[0]["off_road"] and drives[0]["off_road_from"]["frame"] == frame
    assert drives[0]["off_road_metres"] > 3 and drives[0]["start_at"] == "clip"


def test_allow_off_road_belongs_to_a_route(tmp_path, capsys):
    from jaxdrive.cli import main as cli

    assert cli(["sample", "--workdir", str(tmp_path), "--allow-off-road"]) == 2
    assert "--allow-off-road: expected only with --strategy and --route" in capsys.readouterr().err


def test_a_map_without_road_leaves_the_route_unchecked_with_one_warning(tmp_path):
    frames = 49  # 4 s: the turn below stays on the seen map
    sample, clip = _town([200.0], zeros=True, frames=frames)
    route = load_route(str(_off_road_file(tmp_path)), duration=(frames - 1) / FPS)
    _, drive, warned = _drive(route, sample, clip)  # not refused: nothing says it is off the road
    assert len(warned) == 1 and "unchecked: the scene's map has no road" in str(warned[0].message)
    assert drive["map_checked"] is False and drive["off_road"] is False
    turn = load_route("left turn", duration=(frames - 1) / FPS)
    poses, drive, warned = _drive(turn, sample, clip)  # and a turn is driven from where the clip is
    assert drive["start_at"] == "clip" and len(warned) == 1
    np.testing.assert_allclose(poses, sample["ego_to_world"][0] @ turn.poses(frames, FPS), atol=1e-4)


@pytest.mark.parametrize(
    "kw, match",
    [
        ({"start": np.eye(3)}, r"start: expected a finite ego pose \[4, 4\], got shape \[3, 3\]"),
        ({"frames": 1}, "frames: expected at least 2 frames to drive, got 1"),
        ({"fps": 0.0}, "fps: expected a positive frame rate, got 0.0"),
        ({"max_off_road": -1.0}, r"max_off_road: expected metres >= 0, got -1.0"),
    ],
)
def test_bad_arguments_to_drive_on_map_are_named(kw, match):
    from jaxdrive.data.scene_map import SceneMap
    from jaxdrive.generate.route import drive_on_map

    sample, clip = _town([40.0], frames=5)
    args = {"start": np.eye(4), "frames": 5, "fps": FPS, **kw}
    scene = SceneMap.from_clip(clip["bev_map"], clip["ego_to_world"])
    with pytest.raises(ValueError, match=match):
        drive_on_map(
            load_route("straight", duration=0.3), args.pop("start"), scene, args.pop("frames"), args.pop("fps"), **args
        )
    with pytest.raises(ValueError, match=r"classes: expected names from drivable_area, .* got \['road'\]"):
        scene.on_road(np.zeros((1, 2)), classes=("road",))
