"""Driving beyond the log's controls: traffic tracks, the stitched scene map, the future-controls
predictor (constant-velocity step, rollout, training, ADE / FDE) and controls predicted past the
end of a clip."""

from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdrive.config import PredictorConfig
from jaxdrive.data.scene_map import SceneMap, cut
from jaxdrive.data.synthetic import generate_clip
from jaxdrive.data.traffic import clip_fields, clip_tracks, planar, wrap
from jaxdrive.models.predictor import Predictor, Traffic, constant_velocity, init_params, predict_step, rollout

ROOT = Path(__file__).resolve().parents[1]
SMALL = PredictorConfig(history=4, horizon=3, stride=2, width=32, depth=1, heads=2, map_patch=16)


@pytest.fixture(scope="module")
def clip():
    return generate_clip(3, views=1, frames=40, height=16, width=28)


def _pose(clip, f):
    return jnp.asarray(planar(clip["ego_to_world"][f]), jnp.float32)


def test_tracks_round_trip_to_the_clip_fields_and_follow_ids_through_reordered_slots(clip):
    tr = clip_tracks(clip)
    out = clip_fields(
        tr["ego"], tr["agents"], size=tr["size"], z=tr["z"], classes=tr["classes"], ids=tr["ids"], valid=tr["valid"]
    )
    v = clip["box_valid"]
    np.testing.assert_allclose(out["boxes"][v][:, :6], clip["boxes"][v][:, :6], atol=1e-4)
    np.testing.assert_allclose(wrap(out["boxes"][v][:, 6] - clip["boxes"][v][:, 6]), 0, atol=1e-5)
    np.testing.assert_array_equal(out["box_ids"][v], clip["box_ids"][v])
    np.testing.assert_allclose(out["waypoints"], clip["waypoints"], atol=1e-4)
    np.testing.assert_allclose(out["ego_to_world"], clip["ego_to_world"], atol=1e-9)
    shuffled = {k: np.array(clip[k]) for k in ("ego_to_world", "boxes", "box_classes", "box_ids", "box_valid")}
    perm = np.random.default_rng(0).permutation(v.shape[1])
    for k in ("boxes", "box_classes", "box_ids", "box_valid"):
        shuffled[k][7] = clip[k][7][perm]  # frame 7 lists its boxes in another order
    np.testing.assert_allclose(clip_tracks(shuffled)["agents"], tr["agents"], atol=1e-9)


@pytest.mark.slow(seconds=4)
def test_the_stitched_map_recuts_the_recorded_maps_and_falls_back_off_the_map(clip):
    one = SceneMap.from_clip(clip["bev_map"][:1], clip["ego_to_world"][:1]).device()
    fallback = jnp.zeros(clip["bev_map"].shape[1:], jnp.uint8)
    np.testing.assert_array_equal(np.asarray(cut(one, _pose(clip, 0), fallback)), clip["bev_map"][0])
    scene = SceneMap.from_clip(clip["bev_map"], clip["ego_to_world"])
    for f in (0, 20, 39):  # re-sampled between rotated grids: boundaries move by up to a cell
        agree = (np.asarray(jax.jit(cut)(scene.device(), _pose(clip, f), fallback)) == clip["bev_map"][f]).all(-1)
        assert agree.mean() > 0.85
    far = _pose(clip, 39).at[0].add(500.0)
    ones = jnp.ones_like(fallback)
    np.testing.assert_array_equal(np.asarray(cut(scene.device(), far, ones)), 1)  # all off the map
    assert scene.covers(planar(clip["ego_to_world"])[:, :2]).all()
    # 40 m past the only recorded pose: a lane seen behind goes on straight ahead, nothing else appears
    lane = np.zeros((1, 64, 64, 8), np.uint8)
    lane[0, :, 20:30, 0] = 1
    ahead = cut(
        SceneMap.from_clip(lane, np.eye(4)[None]).device(),
        jnp.array([40.0, 0.0, 0.0]),
        jnp.full((64, 64, 8), 7, jnp.uint8),
    )
    np.testing.assert_array_equal(np.asarray(ahead), lane[0])
    assert not scene.covers(np.asarray([[1e4, 0.0]]))[0]


def _traffic(ego, agents, seen):
    n = agents.shape[2]
    return Traffic(
        ego=jnp.asarray(ego, jnp.float32),
        agents=jnp.asarray(agents, jnp.float32),
        seen=jnp.asarray(seen),
        size=jnp.ones((1, n, 3)),
        z=jnp.zeros((1, n)),
        classes=jnp.zeros((1, n), jnp.int32),
        ids=jnp.arange(n, dtype=jnp.int32)[None] + 40,
    )


@pytest.mark.slow(seconds=3)
def test_constant_velocity_moves_each_pose_by_its_last_step_and_a_fresh_predictor_is_that_step():
    ego = np.array([[[0, 0, 0], [0.5, 0, 0.1], [1.5, 0.5, 0.2], [2.5, 1.0, 0.3]]])  # [1, T=4, 3]
    agents = np.zeros((1, 4, 2, 3))
    agents[0, :, 0] = [[10, 0, 1], [10, 1, 1], [10, 2, 1], [10, 3, 1]]
    agents[0, :, 1] = [[5, 5, 0], [5, 5, 0], [6, 5, 0], [7, 5, 0]]
    seen = np.ones((1, 4, 2), bool)
    seen[0, 2, 1] = False  # agent 1 missed the step before the last: it stands
    tr = _traffic(ego, agents, seen)
    cv_ego, cv_agents = jax.jit(constant_velocity)(tr)  # jitted: eagerly each jnp call compiles alone
    np.testing.assert_allclose(cv_ego[0], [3.5, 1.5, 0.3], atol=1e-6)  # worked: + (1.0, 0.5), heading kept
    np.testing.assert_allclose(cv_agents[0], [[10, 4, 1], [7, 5, 0]], atol=1e-6)
    params = init_params(SMALL, jax.random.key(0), bev_size=(32, 32))
    step = jax.jit(lambda p: predict_step(Predictor(SMALL), p, tr, np.zeros((1, 32, 32, 8), np.float32)))
    e, a = step(params)
    np.testing.assert_allclose(e, cv_ego, atol=1e-6)
    np.testing.assert_allclose(a, cv_agents, atol=1e-6)
    # a trained head moves the prediction: the corrections are read, in the ego frame
    bumped = jax.tree_util.tree_map(lambda x: x, params)
    bumped["head"]["bias"] = np.array([1.0, 0.0, 0.0], np.float32)
    e2, _ = step(bumped)
    np.testing.assert_allclose(e2[0, :2] - cv_ego[0, :2], 0.5 * np.array([np.cos(0.3), np.sin(0.3)]), atol=1e-5)


@pytest.mark.slow(seconds=7)
def test_a_720_step_rollout_keeps_the_tracks_and_stays_finite(clip):
    tr = clip_tracks(clip)
    hist = slice(40 - SMALL.history, 40)
    traffic = Traffic(
        ego=jnp.asarray(tr["ego"][hist], jnp.float32)[None],
        agents=jnp.asarray(tr["agents"][hist], jnp.float32)[None],
        seen=jnp.asarray(tr["seen"][hist])[None],
        size=jnp.asarray(tr["size"], jnp.float32)[None],
        z=jnp.asarray(tr["z"], jnp.float32)[None],
        classes=jnp.asarray(np.maximum(tr["classes"], 0))[None],
        ids=jnp.asarray(tr["ids"])[None],
    )
    params = init_params(SMALL, jax.random.key(1), bev_size=clip["bev_map"].shape[1:3])
    rng = np.random.default_rng(2)  # NumPy noise: eager jax.random compiles a program per shape
    params = jax.tree_util.tree_map(lambda x: np.asarray(x) + 0.05 * rng.standard_normal(x.shape, np.float32), params)
    scene = SceneMap.from_clip(clip["bev_map"], clip["ego_to_world"]).device()
    run = jax.jit(lambda p, t, b: rollout(Predictor(SMALL), p, t, 720, bev=b, scene=scene))
    ego, agents, last = run(params, traffic, jnp.asarray(clip["bev_map"][-1:], jnp.float32))
    assert ego.shape == (1, 720, 3) and agents.shape == (1, 720, 20, 3)
    assert np.isfinite(np.asarray(ego)).all() and np.isfinite(np.asarray(agents)).all()
    np.testing.assert_array_equal(last.ids, traffic.ids)
    np.testing.assert_array_equal(last.classes, traffic.classes)
    np.testing.assert_array_equal(last.seen[:, -1], traffic.seen[:, -1])
    absent = ~np.asarray(traffic.seen[0, -1])
    np.testing.assert_array_equal(
        np.asarray(agents)[0][:, absent], np.asarray(traffic.agents)[0, -1, absent][None].repeat(720, 0)
    )  # absent slots are not moved


@pytest.mark.slow(seconds=12)
def test_ade_and_fde_of_constant_velocity_under_constant_acceleration_match_the_worked_numbers():
    """x = 0.1 f^2 at 1 fps: constant velocity from frame r misses (r + k) by 0.1 (k^2 + k) m,
    whatever r: FDE 0.2 m at 1 s and 0.6 m at 2 s, ADE at 2 s (0.2 + 0.6) / 2 = 0.4 m."""
    from jaxdrive.eval.motion import motion_errors

    frames = 9
    e2w = np.tile(np.eye(4), (frames, 1, 1))
    e2w[:, 0, 3] = 0.1 * np.arange(frames) ** 2
    clip = {
        "ego_to_world": e2w,
        "boxes": np.zeros((frames, 2, 7), np.float32),
        "box_classes": np.zeros((frames, 2), np.int32),
        "box_ids": np.full((frames, 2), -1, np.int32),
        "box_valid": np.zeros((frames, 2), bool),
        "bev_map": np.zeros((frames, 32, 32, 8), np.uint8),
        "fps": 1.0,
    }
    cfg = PredictorConfig(history=2, horizon=1, stride=1, width=16, depth=1, heads=2, map_patch=16, max_agents=2)
    params = init_params(cfg, jax.random.key(0), bev_size=(32, 32))
    scores = motion_errors(params, cfg, [clip], horizons=(1.0, 2.0))
    ego = scores["horizons"]
    assert ego["1s"]["ego"]["cv_fde"] == pytest.approx(0.2, abs=1e-3)
    assert ego["2s"]["ego"]["cv_fde"] == pytest.approx(0.6, abs=1e-3)
    assert ego["2s"]["ego"]["cv_ade"] == pytest.approx(0.4, abs=1e-3)
    assert ego["2s"]["ego"]["ade"] == pytest.approx(0.4, abs=1e-3)  # a fresh predictor is the baseline
    assert scores["windows"] == 6  # starts 0..5: 2 history + 2 future steps in 9 frames


@pytest.fixture(scope="module")
def data(clips21):
    return clips21


@pytest.fixture(scope="module")
def predictor_run(data, tmp_path_factory):
    from jaxdrive.cli import main as cli

    work = tmp_path_factory.mktemp("predictor") / "run"
    args = [
        "train",
        "--config",
        str(ROOT / "configs" / "predictor.py") + ":size=tiny",
        "--workdir",
        str(work),
        "--steps",
        "6",
        "--no-progress",
    ]
    for s in (
        f"data.path={data}",
        "data.batch_size=4",
        "train.log_every=2",
        "train.checkpoint_every=3",
        "predictor.width=32",
        "predictor.history=4",
        "predictor.horizon=3",
    ):
        args += ["--set", s]
    assert cli(args) == 0
    return work


@pytest.mark.slow(seconds=10)
def test_the_predictor_trains_resumes_and_scores_its_validation_split(predictor_run, data):
    from jaxdrive.cli import main as cli
    from jaxdrive.train.predictor_run import load_future_predictor

    rows = [json.loads(line) for line in (predictor_run / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [2, 4, 6] and all(np.isfinite(r["loss"]) for r in rows)
    motion = json.loads((predictor_run / "motion.json").read_text())
    assert set(motion["horizons"]) == {"1s"} and motion["windows"] >= 1  # 21 frames: 1 s fits, 2 s does not
    p = load_future_predictor(predictor_run)
    assert p.step_seconds == pytest.approx(2 / 12) and p.config.history == 4
    assert (
        cli(
            [
                "train",
                "--config",
                str(ROOT / "configs" / "predictor.py") + ":size=tiny",
                "--workdir",
                str(predictor_run),
                "--steps",
                "8",
                "--no-progress",
                "--set",
                f"data.path={data}",
                "--set",
                "data.batch_size=4",
                "--set",
                "train.log_every=2",
                "--set",
                "predictor.width=32",
                "--set",
                "predictor.history=4",
                "--set",
                "predictor.horizon=3",
            ]
        )
        == 0
    )
    rows = [json.loads(line) for line in (predictor_run / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [2, 4, 6, 8]  # resumed at 6, not restarted


@pytest.mark.slow(seconds=20)
def test_a_signal_saves_the_predictor_and_the_same_command_resumes(data, tmp_path):
    import os
    import signal

    from jaxdrive.config import load_config
    from jaxdrive.train.predictor_run import train_predictor

    config = load_config(
        str(ROOT / "configs" / "predictor.py") + ":size=tiny",
        [
            f"data.path={data}",
            "data.batch_size=2",
            "predictor.width=32",
            "predictor.history=4",
            "predictor.horizon=3",
            "train.steps=4",
            "train.checkpoint_every=0",
        ],
    )
    stop = lambda step, metrics: os.kill(os.getpid(), signal.SIGTERM) if step == 2 else None
    part = train_predictor(config, tmp_path / "run", progress=False, on_step=stop)
    assert part["status"] == "interrupted" and part["step"] == 2 and "motion" not in part
    rest = train_predictor(config, tmp_path / "run", progress=False)
    assert rest["status"] == "done" and rest["step"] == 4


@pytest.mark.parametrize(
    "sets, match",
    [
        (
            ["predictor.width=30", "predictor.heads=4"],
            "predictor.width: expected a multiple of predictor.heads = 4, got 30",
        ),
        (["predictor.history=1"], "predictor.history: expected"),
        (["predictor.horizon=40"], "data.path: expected clips of at least 95 frames"),
    ],
)
def test_bad_predictor_configs_are_refused(data, tmp_path, sets, match):
    from jaxdrive.config import load_config
    from jaxdrive.train.predictor_run import train_predictor

    config = load_config(str(ROOT / "configs" / "predictor.py") + ":size=tiny", [f"data.path={data}", *sets])
    with pytest.raises(ValueError, match=match):
        train_predictor(config, tmp_path / "run", progress=False)


def _sample(clip, frames):
    from jaxdrive.data.transforms import sample_clip

    return sample_clip(clip, size=(16, 28), frames=frames)


@pytest.mark.slow(seconds=3)
def test_controls_past_the_log_continue_the_clip_and_a_route_moves_only_the_ego(clip, tmp_path):
    from jaxdrive.generate.future import FuturePredictor, future_controls
    from jaxdrive.generate.route import load_route

    fresh = FuturePredictor(SMALL, init_params(SMALL, jax.random.key(0)), step_seconds=1 / 12)
    s = _sample(clip, 20)
    out = future_controls(s, clip, frames=50, keep=20, predictor=fresh)
    assert out["predicted_from"] == 20 and out["video"].shape[1] == 20
    for k in ("boxes", "box_classes", "box_ids", "box_valid", "bev_map", "waypoints", "ego_to_world"):
        assert len(out[k]) == 50, k
        np.testing.assert_array_equal(out[k][:20], s[k][:20])  # recorded frames untouched
    present = s["box_valid"][19]
    np.testing.assert_array_equal(
        out["box_ids"][20:, present], np.broadcast_to(s["box_ids"][19, present], (30, present.sum()))
    )
    ego = planar(out["ego_to_world"].astype(np.float64))
    step = ego[19, :2] - ego[18, :2]  # a fresh predictor: constant velocity, frame by frame
    np.testing.assert_allclose(ego[20:, :2] - ego[19:-1, :2], np.broadcast_to(step, (30, 2)), atol=1e-3)
    assert np.isfinite(out["boxes"]).all() and out["bev_map"].dtype == np.uint8
    np.testing.assert_allclose(out["frame_times"][20:] - out["frame_times"][19:-1], 1 / 12, atol=1e-6)
    with pytest.raises(ValueError, match=r"frames: expected at most 20 frames .* pass --predictor RUN"):
        future_controls(s, clip, frames=30, keep=20)
    # a route: the ego follows it from frame 0; the recorded agents stay where they were in the world
    route = load_route("straight 3 m/s", duration=19 / 12)
    routed = future_controls(s, clip, frames=20, keep=20, route=route)
    np.testing.assert_allclose(routed["waypoints"][:, 0], np.arange(20) * 0.25, atol=1e-2)
    world = lambda c: clip_tracks({k: c[k] for k in ("ego_to_world", "boxes", "box_classes", "box_ids", "box_valid")})[
        "agents"
    ]
    np.testing.assert_allclose(world(routed)[:, present], world(s)[:, present], atol=1e-3)
    far = tmp_path / "far.csv"
    far.write_text("x,y\n0,0\n10,0\n900,0\n")
    with pytest.raises(
        ValueError,
        match=rf"route {far} row 4: expected a point on the scene's map .* "
        r"got \(900.0, 0.0\)",
    ):
        future_controls(s, clip, frames=20, keep=20, route=load_route(str(far), duration=19 / 12))
    from jaxdrive.generate.route import RouteWarning  # a manoeuvre always runs, beyond the map too

    with pytest.warns(RouteWarning, match=r"manoeuvre 'straight': it drives beyond the scene's map .* from frame"):
        fast = future_controls(s, clip, frames=20, keep=20, route=load_route("straight 300 m/s", duration=19 / 12))
    assert 0 < fast["route_drive"]["beyond_map_from"]["frame"] < 20 and np.isfinite(fast["bev_map"]).all()


@pytest.mark.optimized_xla
@pytest.mark.slow(seconds=26)
def test_a_six_view_generation_runs_past_the_end_of_the_recorded_controls(tiny_dit, predictor_run, tmp_path, capsys):
    from PIL import Image

    from jaxdrive.cli import main as cli

    out = tmp_path / "long"
    assert (
        cli(
            [
                "sample",
                "--workdir",
                str(tiny_dit),
                "--strategy",
                "rollout",
                "--frames",
                "25",
                "--steps",
                "1",
                "--predictor",
                str(predictor_run),
                "--out",
                str(out),
                "--no-progress",
            ]
        )
        == 0
    )
    report = json.loads((out / "report.json").read_text())
    assert report["frames"] == 25 and report["views"] == 6  # the clip records 21 frames
    assert report["controls"] == {"mode": "recorded", "predictor": str(predictor_run), "recorded_frames": 21}
    assert np.isfinite(np.load(out / "latents.npy")).all()
    grid = np.asarray(Image.open(out / "frames.png"))
    assert grid.shape[1] > 3 * 56 * 2  # the BEV panel before the 3 x 2 view mosaic
    capsys.readouterr()
    assert (
        cli(
            [
                "sample",
                "--workdir",
                str(tiny_dit),
                "--strategy",
                "rollout",
                "--frames",
                "9",
                "--controls",
                "predicted",
                "--out",
                str(tmp_path / "no"),
            ]
        )
        == 2
    )
    assert "--controls: 'predicted' needs --predictor RUN" in capsys.readouterr().err
    assert (
        cli(
            [
                "sample",
                "--workdir",
                str(tiny_dit),
                "--strategy",
                "rollout",
                "--frames",
                "33",
                "--out",
                str(tmp_path / "no"),
            ]
        )
        == 2
    )
    assert "frames: expected at most 21 frames" in capsys.readouterr().err
