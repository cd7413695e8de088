"""Counterfactual futures in training: scenes read along routes drawn per clip and epoch."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from jaxdrive.config import load_config
from jaxdrive.data.batch_plan import seeded_rng
from jaxdrive.data.pipeline import make_pipeline
from jaxdrive.data.route_mix import RoutedScenes, open_routed_scenes, parse_route_mix
from jaxdrive.data.synthetic import write_synthetic_dataset

TINY = Path(__file__).resolve().parents[1] / "configs" / "tiny.py"
START = 4  # the first frame the routes change
FRAMES, H, W = 9, 16, 28


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """Two training scenes (seed 3: both drive stop and faster) of 9 frames, one view, with their
    ``stop`` and ``faster`` renders from frame 4."""
    out = tmp_path_factory.mktemp("routes") / "data"
    write_synthetic_dataset(
        out,
        train=2,
        seed=3,
        train_counterfactuals="stop,faster",
        counterfactual_start=START,
        views=1,
        frames=FRAMES,
        height=H,
        width=W,
    )
    return out


def test_the_mix_parses_names_and_weights_and_names_bad_items():
    assert parse_route_mix(("recorded:2", "stop", "branch:0.5")) == {"recorded": 2.0, "stop": 1.0, "branch": 0.5}
    assert parse_route_mix("recorded,stop") == {"recorded": 1.0, "stop": 1.0}
    for bad, match in [
        (("reverse",), "data.routes: expected distinct comma-separated routes"),
        (("stop", "stop:2"), "data.routes: expected distinct"),
        (("stop:0",), "data.routes: expected a weight > 0 after 'route:', got 'stop:0'"),
        (("stop:many",), "data.routes: expected a weight > 0"),
    ]:
        with pytest.raises(ValueError, match=match):
            parse_route_mix(bad)


def test_draws_follow_the_weights_over_the_routes_a_scene_has():
    class Rows(list):  # a stand-in source: row r of route k reads (k, r)
        def __getitem__(self, i):
            return {"which": list.__getitem__(self, i)}

    sources = {"recorded": Rows([("recorded", 0), ("recorded", 1)]), "stop": Rows([("stop", 1)])}
    mix = RoutedScenes(sources, {"stop": [1]}, {"recorded": 1.0, "stop": 3.0})
    assert mix.routes_of(0) == ["recorded"] and mix.routes_of(1) == ["recorded", "stop"]
    draws = [mix.read(1, seeded_rng(0, k))[1] for k in range(2000)]
    assert abs(draws.count("stop") / 2000 - 0.75) < 0.04  # 3 : 1, renormalised over scene 1's routes
    assert {mix.read(0, seeded_rng(0, k))[0]["which"] for k in range(50)} == {("recorded", 0)}  # no stop render
    assert mix.read(1, seeded_rng(0, 7))[0]["which"] in {("recorded", 1), ("stop", 0)}  # row 0 of stop is scene 1


def test_a_batch_holds_two_routes_of_one_scene_with_equal_given_frames(scenes):
    source = open_routed_scenes(scenes, parse_route_mix("recorded,stop,faster"))
    assert len(source) == 2 and list(source.frame_counts) == [FRAMES, FRAMES]
    # a batch of 4 from 2 scenes: each scene twice (two rounds), every sample at frame 0 (clip = bucket)
    for seed in range(20):
        it = iter(
            make_pipeline(
                source,
                {(H, W, FRAMES): 4},
                seed=seed,
                num_threads=0,
                prefetch=0,
                shard_index=0,
                shard_count=1,
                num_epochs=1,
            )
        )
        batch = next(it)
        pairs = [
            (i, j)
            for i in range(4)
            for j in range(i + 1, 4)
            if batch["index"][i] == batch["index"][j] and batch["route"][i] != batch["route"][j]
        ]
        if pairs:
            break
    assert pairs, "no seed in 20 gave one scene two routes in a batch"
    i, j = pairs[0]
    video = np.asarray(batch["video"])  # [B, V, F, H, W, 3]
    np.testing.assert_array_equal(video[i, :, :START], video[j, :, :START])  # the same past
    assert not np.array_equal(video[i, :, START:], video[j, :, START:])  # different futures
    assert not np.array_equal(batch["waypoints"][i], batch["waypoints"][j])
    assert set(batch["route"]) <= {"recorded", "stop", "faster"}


def test_routes_change_across_epochs_and_the_other_draws_stay_those_of_the_scenes(scenes):
    from jaxdrive.data.tfds_io import open_source

    routed = open_routed_scenes(scenes, parse_route_mix("recorded,stop,faster"))
    kw = dict(seed=1, num_threads=0, prefetch=0, shard_index=0, shard_count=1, num_epochs=6, crop="random")
    bucket = {(H, W, FRAMES - 4): 2}  # 5 of 9 frames: a start frame and a crop drawn per sample
    a = list(make_pipeline(routed, bucket, **kw))
    b = list(make_pipeline(open_source(scenes, "train"), bucket, **kw))
    assert len({tuple(x["route"]) for x in a}) > 1  # the route is drawn again each epoch
    for x, y in zip(a, b):
        assert list(x["index"]) == list(y["index"])
        rec = [k for k, r in enumerate(x["route"]) if r == "recorded"]
        np.testing.assert_array_equal(np.asarray(x["video"])[rec], np.asarray(y["video"])[rec])
        assert "route" not in y


def _starts(batches, source):
    """Each sample's (route, start frame): where its first ego pose sits in its scene's render."""
    out = []
    for x in batches:
        for k, route in enumerate(x["route"]):
            clip = source.along(int(x["index"][k]), route)
            e2w = np.asarray(clip["ego_to_world"], np.float32)
            hit = np.flatnonzero(np.all(np.isclose(e2w, np.asarray(x["ego_to_world"])[k, 0], atol=1e-5), (1, 2)))
            out.append((route, int(hit[0])))
    return out


def test_route_parting_starts_counterfactual_windows_with_their_given_frames_before_the_part(scenes):
    """5-frame windows of 9-frame clips parting at frame 4, 2 given frames: a parted window starts
    at frame 0, 1 or 2 (its given frames 2-3 at the latest, before frame 4); a recorded one, or any
    without parting, anywhere in 0-4."""
    source = open_routed_scenes(scenes, parse_route_mix("recorded,stop,faster"))
    assert source.part_frame == START
    with pytest.raises(ValueError, match="route: expected one of scene 0's routes"):
        source.along(0, "branch")
    kw = dict(seed=2, num_threads=0, prefetch=0, shard_index=0, shard_count=1, num_epochs=30)
    bucket = {(H, W, FRAMES - 4): 2}

    def starts(share):
        return _starts(make_pipeline(source, bucket, route_parting=share, given_frames=2, **kw), source)

    always, never, half = starts(1.0), starts(0.0), starts(0.5)
    routed = [t for r, t in always if r != "recorded"]
    assert routed and max(routed) == 2 and set(routed) == {0, 1, 2}
    assert max(t for r, t in always if r == "recorded") > 2  # recorded windows keep their uniform starts
    assert max(t for r, t in never if r != "recorded") > 2
    share = np.mean([t <= 2 for r, t in half if r != "recorded"])
    assert 0.6 < share < 0.95  # 0.5 parted + 0.5 x 3/5 of the uniform starts = 0.8
    for bad in (1.5, -0.1, True, "0.5"):
        with pytest.raises(ValueError, match=f"route_parting: expected a probability in \\[0, 1\\], got {bad!r}"):
            make_pipeline(source, bucket, route_parting=bad, **kw)
    from jaxdrive.data.tfds_io import open_source

    with pytest.raises(ValueError, match="route_parting: expected 0 for a source without counterfactual routes"):
        make_pipeline(open_source(scenes, "train"), bucket, route_parting=0.5, **kw)


def test_a_route_the_training_split_lacks_is_refused_before_anything_compiles(scenes):
    import jax

    from jaxdrive.train.run import Run

    ONE = jax.devices()[:1]
    config = load_config(
        TINY,
        [f"data.path={scenes}", "data.views=1", f"data.frames={FRAMES}", f"data.height={H * 2}", f"data.width={W * 2}"],
    )
    with pytest.raises(
        ValueError,
        match=r"data.routes: expected routes the training split of .* holds "
        r"\(recorded, stop, faster\), got \['branch'\]",
    ):
        Run(
            dataclasses.replace(config, data=dataclasses.replace(config.data, routes=("recorded", "branch"))),
            devices=ONE,
        )
    with pytest.raises(ValueError, match="data.routes: expected distinct comma-separated routes"):
        Run(dataclasses.replace(config, data=dataclasses.replace(config.data, routes=("sideways",))), devices=ONE)
    bare = dataclasses.replace(
        config,
        latents=dataclasses.replace(config.latents, precomputed=True),
        data=dataclasses.replace(config.data, routes=("stop",)),
    )
    with pytest.raises(ValueError, match="data.routes: expected \\(\\) with latents.precomputed"):
        Run(bare, devices=ONE)
    for routes, share, match in [
        (("recorded", "stop"), 2.0, r"data.route_parting: expected a probability in \[0, 1\], got 2.0"),
        (("recorded",), 0.5, r"data.route_parting: expected 0 without a counterfactual route in data.routes"),
    ]:
        with pytest.raises(ValueError, match=match):
            Run(
                dataclasses.replace(config, data=dataclasses.replace(config.data, routes=routes, route_parting=share)),
                devices=ONE,
            )


@pytest.mark.parametrize(
    ("control", "waypoints", "warp", "reference"),
    [("warp", True, True, "warp"), ("warp_only", False, True, "warp"), ("waypoints_cf", True, False, "residual")],
)
def test_the_world_recipes_route_controls_differ_only_in_their_controls(control, waypoints, warp, reference):
    """Part 2's comparison: the warp with the waypoint tokens, the warp alone and the tokens alone
    train on the same counterfactual futures with the same noise on their given frames."""
    from jaxdrive.models.dit.config import check_config

    world = str(Path(TINY).with_name("world.py"))
    cfg = load_config(f"{world}:control={control}")
    both = load_config(f"{world}:control=warp")
    check_config(cfg.model)
    c = cfg.model.controls
    assert (c.waypoints, c.warp, c.reference_frame) == (waypoints, warp, reference)
    assert cfg.data.routes == both.data.routes and "branch" in cfg.data.routes
    assert (cfg.flow.given_noise_max, cfg.flow.given_noise_sample) == (0.7, 0.1)
    assert cfg.data.warp_frame == (cfg.flow.cond_frames - 1 if warp else 0)
    # the recipe as first trained: the tokens alone, recorded futures only, clean given frames
    first = load_config(f"{world}:control=waypoints")
    assert first.data.routes == () and first.flow.given_noise_max == 0.0
    with pytest.raises(ValueError, match="config argument control: expected 'waypoints', 'warp', 'warp_only' or "):
        load_config(f"{world}:control=tokens")


@pytest.mark.slow(seconds=60)
def test_the_world_recipe_with_warp_control_trains_on_routed_scenes_and_samples(tmp_path):
    """``configs/world.py:control=warp`` end to end at one layer: counterfactual futures, the warp
    from the last given frame with the output its correction, noise on the given frames; then a
    rollout through the CLI, each window warping from its own newest given frame."""
    import json

    from jaxdrive.cli import main as cli

    data = tmp_path / "data"
    write_synthetic_dataset(
        data,
        train=2,
        validation=1,
        seed=3,
        train_counterfactuals="stop,faster",
        counterfactual_start=START,
        views=6,
        frames=FRAMES,
        height=32,
        width=56,
    )
    sets = [
        f"data.path={data}",
        "data.routes=[recorded,stop,faster]",
        "model.depth=1",
        "model.final_conv=0",
        "model.controls.text=none",
        "data.frames=5",
        "mesh.data=2",
        "mesh.seq=4",
        "train.checkpoint_every=2",
    ]
    args = [
        "train",
        "--config",
        str(Path(TINY).with_name("world.py")) + ":control=warp",
        "--workdir",
        str(tmp_path / "run"),
        "--steps",
        "2",
        "--no-progress",
    ]
    for s in sets:
        args += ["--set", s]
    assert cli(args) == 0
    out = tmp_path / "sample"
    assert (
        cli(
            [
                "sample",
                "--workdir",
                str(tmp_path / "run"),
                "--strategy",
                "rollout",
                "--frames",
                "9",
                "--steps",
                "2",
                "--out",
                str(out),
                "--no-progress",
            ]
        )
        == 0
    )
    report = json.loads((out / "report.json").read_text())
    assert report["warp"] == {"depth": 20.0, "frame": 1} and report["frames"] == 9
