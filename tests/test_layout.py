"""The projected layout control (``controls.layout``, :mod:`jaxdrive.models.dit.layout`) and the box
corners' normalised range (``model.box_range``, ``model.box_freqs``): the rasterisation against
the synthetic world's instance ids and worked numbers, the zero-initialised gate, guidance's drop,
and bad input."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdrive import geometry
from jaxdrive.config import Config, override, to_dict
from jaxdrive.data.synthetic import generate_clip
from jaxdrive.models.dit import DiT
from jaxdrive.models.dit.conditions import Conditions
from jaxdrive.models.dit.controls import box_corner_features
from jaxdrive.models.dit.inputs import example_inputs
from jaxdrive.models.dit.layout import box_hits, camera_rays, layout_canvas
from jaxdrive.models.dit.presets import preset
from jaxdrive.train.run import CONFIG_FILE, load_run_config

from control_fixtures import measured
from dit_fixtures import conditions, forward_fn, max_rel, params_for, perturb, split_inputs

LAYOUT = preset("tiny", depth=1, controls=dict(layout=True))
# jitted, as the model runs them (the grids and class count static): called eagerly, each of their
# operations compiled its own program per shape, 162 in the worked-numbers test alone
rays = jax.jit(camera_rays, static_argnums=(2, 3, 4))
hits = jax.jit(box_hits)
canvas_of = jax.jit(layout_canvas, static_argnums=(5, 6), static_argnames=("num_classes", "bev_range", "samples"))
SHAPES = (("batch", 2), ("views", 2), ("frames", 2), ("height", 8), ("width", 8))


def _front_camera(size=90, focal=90.0):
    """One camera at (1, 0, 1.5) m in the ego frame looking along +x; ``size`` square pixels."""
    k = np.array([[focal, 0, size / 2], [0, focal, size / 2], [0, 0, 1]], np.float32)
    pose = np.eye(4, dtype=np.float32)
    pose[:3, :3] = np.stack([[0, -1, 0], [0, 0, -1], [1, 0, 0]], axis=1)  # columns: right, down, forward
    pose[:3, 3] = (1.0, 0.0, 1.5)
    return k[None, None], pose[None, None]


def test_layout_matches_the_synthetic_worlds_instance_ids():
    """Each box's drawn silhouette (nearest box in front) against its instance mask, one ray per
    stored pixel. Measured over seeds 0-2 (2 frames, 6 views, 64 x 112, no scenery): IoU 1.000
    mean and min over all 30 (box, frame, view) masks of >= 10 pixels, and every pixel's box id
    equal to the instance id: the world's renderer ray casts the same boxes, so the two agree up
    to float rounding at silhouette edges."""
    ious, agree = [], []
    for seed in (0, 1, 2):
        clip = generate_clip(seed, views=6, frames=2, height=64, width=112, scenery=False)
        origin, dirs = rays(clip["intrinsics"][None], clip["cam_to_ego"][None], (64, 112), (64, 112))
        _, owner = hits(clip["boxes"][None], clip["box_valid"][None], origin, dirs)
        owner = np.asarray(owner[0])  # [F, V, H, W]
        ids = np.where(
            owner >= 0,
            np.take_along_axis(clip["box_ids"][:, None, None, None, :], np.maximum(owner, 0)[..., None], -1)[..., 0],
            -1,
        )
        inst = np.moveaxis(clip["instance_ids"], 0, 1)  # [F, V, H, W]
        agree.append(np.mean(ids == inst))
        for i in np.unique(inst[inst >= 0]):
            for f, v in zip(*np.nonzero((inst == i).sum((2, 3)) >= 10)):
                a, b = ids[f, v] == i, inst[f, v] == i
                ious.append((a & b).sum() / (a | b).sum())
    assert len(ious) == 30
    assert np.mean(ious) > 0.99 and np.min(ious) > 0.95, (np.mean(ious), np.min(ious))
    assert min(agree) > 0.999


@pytest.mark.slow(seconds=3)
def test_one_box_and_one_road_cell_worked_numbers():
    """A 2 m cube 10 m ahead of the ego at camera height: its near face lies at depth 9 m and
    spans 90 * 1 / 9 = 10 pixels either side of the centre, so pixels 35..54 (centres 35.5..54.5)
    in both directions: 400 pixels, as :mod:`jaxdrive.geometry` projects its corners. Turned by
    90 degrees a 4 x 2 m box spans 90 * 2 / 9 = 20 pixels either side: columns 25..64."""
    k, pose = _front_camera()
    origin, dirs = rays(k, pose, (90, 90), (90, 90))
    box = np.array([[[[11.0, 0.0, 1.5, 2.0, 2.0, 2.0, 0.0]]]], np.float32)
    depth, owner = hits(box, np.ones((1, 1, 1), bool), origin, dirs)
    mask = np.asarray(owner[0, 0, 0]) == 0
    rows, cols = np.nonzero(mask)
    assert mask.sum() == 400 and (rows.min(), rows.max(), cols.min(), cols.max()) == (35, 54, 35, 54)
    np.testing.assert_allclose(np.asarray(depth[0, 0, 0])[mask], 9.0, rtol=1e-5)
    px, _ = geometry.project_to_image(geometry.ego_to_camera(geometry.box_corners(box[0, 0]), pose[0]), k[0])
    np.testing.assert_allclose([px[..., 0].min(), px[..., 0].max()], [35.0, 55.0], atol=1e-4)
    turned = np.array([[[[11.0, 0.0, 1.5, 4.0, 2.0, 2.0, np.pi / 2]]]], np.float32)
    _, owner = hits(turned, np.ones((1, 1, 1), bool), origin, dirs)
    cols = np.nonzero(np.asarray(owner[0, 0, 0]) == 0)[1]
    assert (cols.min(), cols.max()) == (25, 64)

    # the road: ray (row 58, column 45) meets the ground 10 m ahead of the camera, x = 11 m,
    # y = -0.056 m: BEV cell (floor(32 - 11 / 1.5625), floor(32 + 0.056 / 1.5625)) = (24, 32) of a
    # 64 x 64 map over 100 m. That cell (x in (10.94, 12.5], y in (-1.56, 0]) is seen by rows 57
    # (x = 11.8) and 58 (x = 11.0), columns 45..57 and 45..58: 27 pixels.
    bev = np.zeros((1, 1, 64, 64, 8), np.float32)
    bev[0, 0, 24, 32, 1] = 1.0
    canvas = canvas_of(
        box,
        np.full((1, 1, 1), 3, np.int32),
        np.zeros((1, 1, 1), bool),
        k,
        pose,
        (90, 90),
        (90, 90),
        num_classes=10,
        bev_map=bev,
    )
    road = np.asarray(canvas[0, 0, 0, ..., 11 + 1])
    assert road.sum() == 27 and road[58, 45] == 1 and road[57, 57] == 1 and road[57, 58] == 0
    assert set(np.nonzero(road)[0]) == {57, 58}
    # with the box there (class 3): one-hot class, near channel 1 / 9, and the box hides the road
    canvas = canvas_of(
        box,
        np.full((1, 1, 1), 3, np.int32),
        np.ones((1, 1, 1), bool),
        k,
        pose,
        (90, 90),
        (45, 45),
        num_classes=10,
        bev_map=bev,
        samples=2,
    )
    c = np.asarray(canvas[0, 0, 0])  # [45, 45, 19]; 2 x 2 rays a cell
    assert c.shape == (45, 45, 19) and c[..., 3].sum() == 100 and c[20, 20, 3] == 1 and c[..., :3].sum() == 0
    np.testing.assert_allclose(c[20, 20, 10], 1 / 9, rtol=1e-5)
    assert c[17, 20, 3] == 0.5  # half a cell: rows 34 (out), 35 (in)


def test_box_range_worked_numbers_and_bad_input():
    """A corner 25.6 m ahead with MagicDrive's +-51.2 m is 0.5: features (0.5, sin 0.5, cos 0.5,
    sin 5, cos 5) for two frequencies 1 and 100^(1/2) = 10."""
    corners = np.zeros((8, 3), np.float32)
    corners[:, 0] = 25.6
    f = np.asarray(box_corner_features(corners, 51.2, 2, 100.0))
    assert f.shape == (24 * 5,)
    np.testing.assert_allclose(f[:3], [0.5, 0.0, 0.0], atol=1e-7)
    np.testing.assert_allclose(f[24:28], [np.sin(0.5), np.cos(0.5), np.sin(5.0), np.cos(5.0)], rtol=1e-5)
    raw = np.asarray(box_corner_features(corners, None, 2, 100.0))
    assert raw[0] == pytest.approx(25.6)
    assert preset("tiny").box_range == 51.2 and preset("tiny").box_freqs == 8
    for bad in (0.0, -51.2, float("inf"), True):
        with pytest.raises(ValueError, match=r"box_range: expected a positive number"):
            preset("tiny", box_range=bad)
    with pytest.raises(ValueError, match=r"box_range: expected a positive number"):
        box_corner_features(corners, -1.0, 2, 100.0)
    for bad in (0, -2, 2.5):
        with pytest.raises(ValueError, match=r"box_freqs: expected an integer >= 1"):
            preset("tiny", box_freqs=bad)
    with pytest.raises(ValueError, match=r"controls.layout_samples: expected an integer >= 1, got 0"):
        preset("tiny", controls=dict(layout=True, layout_samples=0))
    with pytest.raises(ValueError, match=r"controls.layout_bev_range: expected two positive extents"):
        preset("tiny", controls=dict(layout=True, layout_bev_range=(0.0, 100.0)))
    assert override(Config(), "model.box_range=none").model.box_range is None
    assert override(Config(), "model.controls.layout=true").model.controls.layout


def test_layout_bad_input():
    """Refused by the checks the DiT runs first (``Conditions.check``), before anything compiles."""
    lat, sig, text, kw = split_inputs(example_inputs(LAYOUT, **dict(SHAPES)))
    check = lambda kw: conditions(text, kw).check(LAYOUT, lat, sig)
    check(kw)
    with pytest.raises(ValueError, match=r"intrinsics: the projected layout .* expected intrinsics and cam_to_ego"):
        check({k: v for k, v in kw.items() if k not in ("intrinsics", "cam_to_ego")})
    with pytest.raises(ValueError, match=r"bev_map: the layout .* expected 5 frames as the boxes, got 2"):
        check(dict(kw, bev_map=kw["bev_map"][:, :2]))
    with pytest.raises(ValueError, match=r"bev_map: this DiT takes no map"):
        conditions(text, kw).check(preset("tiny", depth=1, controls=dict(boxes=True)), lat, sig)
    with pytest.raises(ValueError, match=r"grid_hw: expected \(height, width\)"):
        camera_rays(kw["intrinsics"], kw["cam_to_ego"], (64, 64), (8,))
    with pytest.raises(ValueError, match=r"cam_to_ego: expected shape \[2, 2, 4, 4\]"):
        camera_rays(kw["intrinsics"], kw["cam_to_ego"][:, :1], (64, 64), (8, 8))


@pytest.mark.slow(seconds=14)
def test_layout_gate_starts_closed_gradients_reach_the_encoder_and_guidance_drops_it():
    """At initialisation the zero gate leaves the output as without the layout (exactly); the
    gate's gradient is non-zero, and once the gate is open the gradients reach every
    convolution and the temporal downsampling, other boxes move the output, and the boxes' drop
    (classifier-free guidance) gives the model without the layout."""
    lat, sig, text, kw = split_inputs(example_inputs(LAYOUT, **dict(SHAPES)))
    kw["drop"] = {"boxes": np.zeros(2, bool)}  # one input structure with and without drops
    fwd = forward_fn(LAYOUT)
    params = params_for(LAYOUT, SHAPES)  # everything perturbed but the zero gate
    assert float(jnp.abs(params["layout_gate"]["kernel"]).max()) == 0.0
    without = {k: v for k, v in kw.items() if k not in ("boxes", "box_classes", "box_valid")}
    base = fwd(params, lat, sig, text, kw)
    np.testing.assert_array_equal(base, fwd(params, lat, sig, text, without))
    _, _, _, other = split_inputs(example_inputs(LAYOUT, seed=3, **dict(SHAPES)))
    moved = {**kw, "boxes": other["boxes"], "box_classes": other["box_classes"]}
    np.testing.assert_array_equal(base, fwd(params, lat, sig, text, moved))

    dit = DiT(LAYOUT)
    grad = jax.jit(jax.grad(lambda p, kw: jnp.sum(dit.forward(p, lat, sig, conditions(text, kw)) * jnp.cos(lat))))
    g = grad(params, kw)
    assert float(jnp.abs(g["layout_gate"]["kernel"]).max()) > 0
    opened = perturb(params, scale=0.05, skip=tuple(k for k in params if k != "layout_gate"))
    g = grad(opened, kw)
    for path in (("conv_in", "kernel"), ("conv_out", "kernel"), ("layout_down", "Dense_0", "kernel")):
        leaf = g["layout_embed"]
        for part in path:
            leaf = leaf[part]
        assert float(jnp.abs(leaf).max()) > 0, path
    live = fwd(opened, lat, sig, text, kw)
    assert max_rel(fwd(opened, lat, sig, text, moved), live) > 1e-4
    dropped = fwd(opened, lat, sig, text, dict(kw, drop={"boxes": np.array([True, False])}))
    alone = fwd(opened, lat, sig, text, without)
    np.testing.assert_allclose(dropped[0], alone[0], atol=1e-6)
    np.testing.assert_allclose(dropped[1], live[1], atol=1e-6)
    assert max_rel(dropped[0], live[0]) > 1e-4


@pytest.mark.slow(seconds=7)
def test_a_window_sampled_without_its_box_inputs_is_the_model_without_the_layout():
    """What ``jaxdrive eval --routes`` does for its "no boxes" row: the box inputs left out of a
    window's controls change the sample of a model whose layout gate is open, and a boxes drop set
    in the controls gives the same sample (the samplers honour ``controls.drop``'s values; they
    once read only its names, the bug that made the row equal the recorded-route row)."""
    from jaxdrive.generate.windows import WindowModel, sample_window

    lat, sig, text, kw = split_inputs(example_inputs(LAYOUT, **dict(SHAPES)))
    params = params_for(LAYOUT, SHAPES)
    params = perturb(params, scale=0.05, skip=tuple(k for k in params if k != "layout_gate"))
    model = WindowModel(DiT(LAYOUT), params, window=2, cond_frames=1, steps=2)
    controls = conditions(text, kw)
    mask = np.zeros(lat.shape[0:1] + lat.shape[2:3], bool)
    mask[:, 0] = True
    sample = lambda c: np.asarray(sample_window(model, params, lat, mask, c, jax.random.key(0)))
    full = sample(controls)
    assert max_rel(sample(controls.replace(boxes=None, box_classes=None, box_valid=None)), full) > 1e-4
    np.testing.assert_array_equal(
        sample(controls.with_drops(["boxes"], True, lat.shape[0])),
        sample(controls.replace(boxes=None, box_classes=None, box_valid=None)),
    )


def test_the_layout_pathway_learns_where_the_boxes_are():
    """The layout toy of ``jaxdrive bench controls`` (:mod:`jaxdrive.bench.controls`): a box
    6-12 m ahead of a front camera appears in the generated frame where it covers the cells, the
    layout alone says where. After 30 Adam steps the flow loss with the true boxes is below 0.4
    times that with the boxes shuffled between the clips (measured 0.131 against 0.885, a ratio
    of 0.15); it fails if the pathway is cut: the gate, the convolutions or the canvas."""
    row = measured("layout")
    assert row["loss_true"] < 0.4 * row["loss_shuffled"], row


def test_batches_feed_the_layout_and_old_runs_keep_raw_metres(tmp_path):
    """A pipeline batch gives a layout-only model the boxes, the cameras and the BEV map, and the
    batch's box drop; a run config saved before ``model.box_range`` existed loads with raw metres."""
    ex = example_inputs(LAYOUT, **dict(SHAPES))["cond"]
    batch = {k: np.asarray(v) for k, v in ex.given().items()}
    batch["drop"] = {n: np.array([True, False]) for n in ("text", "camera", "trajectory", "boxes", "map")}
    cond = Conditions.from_batch(batch, LAYOUT)
    assert all(getattr(cond, k) is not None for k in ("boxes", "box_valid", "intrinsics", "cam_to_ego", "bev_map"))
    assert sorted(cond.drop) == ["boxes", "text"]
    np.testing.assert_array_equal(cond.drop["boxes"], [True, False])

    saved = to_dict(Config())
    (tmp_path / CONFIG_FILE).write_text(json.dumps(saved))
    assert load_run_config(tmp_path).model.box_range == 51.2
    del saved["model"]["box_range"]
    (tmp_path / CONFIG_FILE).write_text(json.dumps(saved))
    assert load_run_config(tmp_path).model.box_range is None
