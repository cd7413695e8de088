"""Counterfactual ground truth: the synthetic world re-rendered along another ego route."""

import numpy as np
import pytest
from test_synthetic import instances_inside_projected_boxes

from jaxdrive.cli import main
from jaxdrive.data.synth_routes import ROUTES
from jaxdrive.data.synthetic import (
    counterfactual_clip,
    counterfactual_split,
    generate_clip,
    read_counterfactuals,
    write_synthetic_dataset,
)
from jaxdrive.data.tfds_io import open_source

KW = dict(views=6, frames=25, height=32, width=56)
START = 8
SEED = 5  # inner lane, straight on: stop, slower, faster and both lane changes are drivable


@pytest.fixture(scope="module")
def recorded():
    return generate_clip(SEED, **KW)


def _ego_xy(clip):
    """The ego's positions in the frame of its first pose (waypoints)."""
    return np.asarray(clip["waypoints"], np.float64)


def test_recorded_route_is_the_stored_clip_bit_for_bit(recorded):
    again = counterfactual_clip(SEED, "recorded", start=START, **KW)
    assert set(again) == set(recorded)
    for key, value in recorded.items():
        assert np.array_equal(np.asarray(again[key]), np.asarray(value)), key


@pytest.mark.parametrize("route", ["stop", "faster", "lane-left"])
def test_routes_share_the_given_frames_and_then_drive_their_way(recorded, route):
    clip = counterfactual_clip(SEED, route, start=START, **KW)
    for key in ("video", "instance_ids", "boxes", "ego_to_world", "bev_map", "waypoints"):
        assert np.array_equal(_first(clip[key], key), _first(recorded[key], key)), key
    for key in ("intrinsics", "cam_to_ego", "box_ids", "box_classes", "box_valid", "caption", "fps"):
        assert np.array_equal(np.asarray(clip[key]), np.asarray(recorded[key])), key
    ego, rec = _ego_xy(clip), _ego_xy(recorded)
    assert not np.array_equal(clip["video"], recorded["video"])
    if route == "stop":
        assert ego[-1, 0] < rec[-1, 0] - 0.5
        steps = np.linalg.norm(np.diff(ego[START - 1 :], axis=0), axis=-1)
        assert np.all(np.diff(steps) <= 1e-6) and steps[-1] < 0.5 * steps[0]  # braking all the way
    elif route == "faster":
        assert ego[-1, 0] > rec[-1, 0] + 0.5
    else:  # one lane (3.5 m) to the left, x forward y left
        assert 1.0 < ego[-1, 1] - rec[-1, 1] <= 3.5 + 1e-6


def _first(x, key):
    """The frames before START of a clip field (frame axis 1 for video / instance ids, else 0)."""
    x = np.asarray(x)
    return x[:, :START] if key in ("video", "instance_ids") else x[:START]


def test_counterfactual_boxes_project_onto_their_own_instance_ids():
    clip = counterfactual_clip(SEED, "faster", start=START, views=6, frames=25, height=48, width=84)
    assert instances_inside_projected_boxes(clip, (START + 4, 24)) > 0


def test_agents_the_ego_never_meets_keep_their_recorded_paths(recorded):
    clip = counterfactual_clip(SEED, "stop", start=START, **KW)

    def world(c):  # agent centres in the world frame [F, N, 2]
        b = np.asarray(c["boxes"], np.float64)[..., :3]
        pts = np.concatenate([b, np.ones(b.shape[:-1] + (1,))], -1)
        return np.einsum("fij,fnj->fni", np.asarray(c["ego_to_world"]), pts)[..., :2]

    valid = recorded["box_valid"][0]
    a, r = world(clip)[:, valid], world(recorded)[:, valid]
    ego = np.asarray(clip["ego_to_world"])[:, None, :2, 3]
    far = np.linalg.norm(r - ego, axis=-1).min(0) > 15.0
    assert far.any()
    np.testing.assert_allclose(a[:, far], r[:, far], atol=1e-4)


def test_a_route_the_scene_cannot_drive_names_the_route_and_the_clip():
    # seed 0 drives in the outer lane: one lane to the right is the kerb
    with pytest.raises(ValueError, match=r"route 'lane-right'.*seed 0.*off the drivable area"):
        counterfactual_clip(0, "lane-right", start=START, **KW)
    with pytest.raises(ValueError, match=r"route 'branch'.*seed 0.*intersection"):
        counterfactual_clip(0, "branch", start=START, **KW)
    with pytest.raises(ValueError, match="route: expected one of"):
        counterfactual_clip(0, "reverse", **KW)
    with pytest.raises(ValueError, match=r"start: expected a frame in \[1, 24\]"):
        counterfactual_clip(0, "stop", start=25, **KW)


def test_branch_takes_the_other_way_at_the_intersection():
    rec = generate_clip(10, **KW)  # turns right at the first cross street
    clip = counterfactual_clip(10, "branch", start=START, **KW)
    yaw_rec = np.arctan2(rec["ego_to_world"][-1, 1, 0], rec["ego_to_world"][-1, 0, 0])
    yaw = np.arctan2(clip["ego_to_world"][-1, 1, 0], clip["ego_to_world"][-1, 0, 0])
    assert yaw_rec < -0.3 and abs(yaw) < 1e-6  # straight on instead


def test_dataset_stores_counterfactual_splits(tmp_path, capsys):
    out = tmp_path / "cf"
    assert (
        main(
            [
                "data",
                "synth",
                "--out",
                str(out),
                "--scenes",
                "4",
                "--val-fraction",
                "0.5",
                "--views",
                "1",
                "--frames",
                "13",
                "--height",
                "16",
                "--width",
                "28",
                "--seed",
                "3",
                "--counterfactuals",
                "stop,lane-left",
                "--skip-undrivable",
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "validation_route_stop (stop: 2 of 2 validation clips)" in printed
    assert "train_route_stop (stop: 2 of 2 training clips)" in printed and "s a clip" in printed
    meta = read_counterfactuals(out)
    assert meta["start"] == START and set(meta["routes"]) == set(meta["train_routes"]) == {"stop", "lane-left"}
    for key, recorded in [("routes", "validation"), ("train_routes", "train")]:  # the training scenes too
        scenes = open_source(out, recorded)
        for route, row in meta[key].items():
            split = open_source(out, counterfactual_split(route, recorded))
            assert row["split"] == counterfactual_split(route, recorded) and len(split) == len(row["clips"])
            for i, clip_index in enumerate(row["clips"]):
                cf, rec = split[i], scenes[clip_index]
                assert set(cf) == set(rec)
                assert np.array_equal(cf["video"][:, :START], rec["video"][:, :START])
                assert not np.array_equal(cf["waypoints"], rec["waypoints"])


def test_undrivable_routes_write_nothing(tmp_path, capsys):
    with pytest.raises(ValueError, match=r"route 'lane-right'.*validation clip"):
        write_synthetic_dataset(
            tmp_path / "x",
            train=1,
            validation=2,
            seed=0,
            counterfactuals="lane-right",
            views=1,
            frames=13,
            height=16,
            width=28,
        )
    assert not any(tmp_path.iterdir())
    with pytest.raises(ValueError, match="counterfactuals: expected distinct comma-separated routes from stop"):
        write_synthetic_dataset(tmp_path / "y", train=1, validation=1, counterfactuals="recorded", views=1, frames=13)
    assert main(["data", "synth", "--out", str(tmp_path / "z"), "--scenes", "1", "--counterfactuals", "stop"]) == 2
    assert "--counterfactuals: expected a dataset with validation clips" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())
    assert ROUTES[0] == "recorded"


@pytest.fixture(scope="module")
def routes21(tmp_path_factory):
    """One training and two validation scenes of 21 frames (6 views, 32 x 56, as ``clips21``) with
    their ``stop`` and ``lane-left`` renders."""
    return write_synthetic_dataset(
        tmp_path_factory.mktemp("routes21") / "data",
        train=1,
        validation=2,
        seed=7,
        counterfactuals="stop,lane-left",
        views=6,
        frames=21,
        height=32,
        width=56,
    )


@pytest.mark.optimized_xla  # its time is running the sampler and the scores, not compiling
@pytest.mark.slow(seconds=58)
def test_eval_scores_every_route_against_its_render(tiny_dit, routes21, tmp_path, capsys):
    import json

    out = tmp_path / "eval"
    argv = [
        "eval",
        "--workdir",
        str(tiny_dit),
        "--strategies",
        "rollout",
        "--clips",
        "2",
        "--frames",
        "13",
        "--steps",
        "1",
        "--set",
        f"data.path={routes21}",
    ]
    assert main([*argv, "--routes", "recorded,stop,lane-left", "--ego-motion", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "| rollout @ stop | 2-5 |" in printed and "| warp @ lane-left | 2-5 |" in printed
    assert "| stop | rollout | 2-5 |" in printed  # the route-effect table
    report = json.loads((out / "eval.json").read_text())
    rows = report["strategies"]
    assert report["routes"] == ["recorded", "stop", "lane-left"] and report["route_clips"] == [0, 1]
    for name in (
        "rollout",
        "repeat frame 1",
        "warp @ recorded",
        "rollout @ stop",
        "repeat frame 1 @ stop",
        "warp @ stop",
        "rollout @ lane-left",
        "warp @ lane-left",
    ):
        assert list(rows[name]["buckets"]) == ["2-5", "6-8", "9-12", "2-12"], name
    # the baselines are scored against each route's own render: holding frame 1 against the stopping
    # ego's frames differs from holding it against the recorded ones
    assert rows["repeat frame 1 @ stop"]["buckets"]["9-12"]["psnr"] != rows["repeat frame 1"]["buckets"]["9-12"]["psnr"]
    effect = report["route_effect"]
    assert set(effect) == {"stop", "lane-left"} and set(effect["stop"]) == {"rollout"}
    for route in ("stop", "lane-left"):
        for span, row in effect[route]["rollout"].items():
            # by definition: the route's score minus the recorded-route generation's on the same render
            assert np.isfinite(row["psnr"]) and abs(row["ssim"]) <= 2.0
    assert "Route effect" in (out / "eval.md").read_text()
    # route following read from the pixels: every result and each route's render (the ceiling)
    ceiling = report["route_following_ceiling"]
    assert set(ceiling) == {"recorded", "stop", "lane-left"}
    for f in [
        *ceiling.values(),
        *(rows[n]["following"] for n in ("rollout @ stop", "warp @ stop", "repeat frame 1 @ stop")),
    ]:
        assert f["clips"] == 2 and np.isfinite(f["ade"]) and 0 <= f["recognised"] <= 1 and len(f["commanded"]) == 2
    # the commanded manoeuvre is the route's, whoever drives it
    assert rows["rollout @ stop"]["following"]["commanded"] == ceiling["stop"]["commanded"]
    assert ceiling["stop"]["ade"] < rows["repeat frame 1"]["following"]["ade"] + 5.0
    assert "Route following" in (out / "eval.md").read_text() and "| stop | render |" in printed
    assert (out / "routes.png").stat().st_size > 0
    # the model has boxes: one more row with them dropped, against the recorded render
    assert list(rows["rollout (no boxes)"]["buckets"]) == ["2-5", "6-8", "9-12", "2-12"]
    # merged with itself as another model's run: the effects follow the renamed strategies
    merged = tmp_path / "merged"
    assert main(["eval", "--merge", f"{out},{out}", "--out", str(merged)]) == 0
    capsys.readouterr()
    merged_report = json.loads((merged / "eval.json").read_text())
    assert set(merged_report["route_effect"]["stop"]) == {"rollout (run)"}
    assert merged_report["route_following_ceiling"] == ceiling  # the data's, once
    assert "following" in merged_report["strategies"]["rollout @ stop (run)"]
    # bad input, before anything compiles
    for extra, message in (
        (["--routes", "recorded,reverse"], "--routes: expected distinct comma-separated routes"),
        (["--routes", "stop,branch"], "--routes: expected routes stored in"),
        (["--routes", "stop", "--clips", "4"], "--clips: expected at most 2"),
        (["--routes", "stop", "--split", "train"], "--split: expected none with --routes"),
        (["--ego-motion"], "--ego-motion: expected --routes"),
    ):
        assert main([*argv, *extra, "--out", str(tmp_path / "no")]) == 2, extra
        assert message in capsys.readouterr().err, message


def test_eval_routes_on_a_dataset_without_counterfactuals(tiny_dit, tmp_path, capsys):
    assert (
        main(
            [
                "eval",
                "--workdir",
                str(tiny_dit),
                "--clips",
                "2",
                "--frames",
                "13",
                "--steps",
                "1",
                "--routes",
                "recorded,stop",
                "--out",
                str(tmp_path / "no"),
            ]
        )
        == 2
    )
    assert "--routes: expected a dataset with counterfactual routes" in capsys.readouterr().err


def test_drivable_clips_says_which_clips_drive_each_route():
    """What the writer checks and the demo filters its routes with: the listed clips render the
    route, the others are undrivable; with skip_undrivable=False the first undrivable clip is a
    ValueError naming it."""
    from jaxdrive.data.synth_routes import UndrivableRoute
    from jaxdrive.data.synthetic import counterfactual_clip, drivable_clips

    rows = drivable_clips(["lane-right", "stop"], 0, 6, views=1, frames=17, height=32, width=56)
    assert set(rows) == {"lane-right", "stop"}
    assert 0 < len(rows["lane-right"]) < 6, rows  # the outer lane has no lane to its right
    for i in range(6):
        if i in rows["lane-right"]:
            counterfactual_clip(i, "lane-right", views=1, frames=17, height=32, width=56)
        else:
            with pytest.raises(UndrivableRoute):
                counterfactual_clip(i, "lane-right", views=1, frames=17, height=32, width=56)
    with pytest.raises(ValueError, match=r"lane-right.*validation clip \d"):
        drivable_clips(["lane-right"], 0, 6, skip_undrivable=False, views=1, frames=17, height=32, width=56)


def test_a_dataset_written_with_its_drivable_clips_drives_no_route_twice(tmp_path, monkeypatch):
    """The demo chooses its routes by :func:`drivable_clips`; handing the result over skips the
    second drive of every route before rendering (``drivable=``), and the dataset is the same."""
    from jaxdrive.data import synthetic
    from jaxdrive.data.synthetic import drivable_clips, read_counterfactuals, write_synthetic_dataset

    kw = dict(train=1, validation=1, counterfactuals=["stop"], views=1, frames=17, height=32, width=56)
    rows = drivable_clips(["stop"], 1, 1, views=1, frames=17, height=32, width=56)
    monkeypatch.setattr(synthetic, "drivable_clips", lambda *a, **k: pytest.fail("drove the routes again"))
    path = write_synthetic_dataset(tmp_path / "given", drivable=rows, **kw)
    assert read_counterfactuals(path)["routes"]["stop"]["clips"] == rows["stop"]
    with pytest.raises(
        ValueError, match=r"^drivable: expected the clips of the routes \['stop'\], got routes \['slower'\]"
    ):
        write_synthetic_dataset(tmp_path / "wrong", drivable={"slower": [0]}, **kw)
