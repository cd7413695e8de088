"""``jaxdrive bench controls``: every control pathway of the DiT learns its toy (the true control
gives a lower flow loss than the control shuffled between clips), and the command's output and
bad input."""

import json

import numpy as np
import pytest

from jaxdrive.bench import controls

from control_fixtures import STEPS, measured

# Loss ratio (true / shuffled control) each pathway must beat after STEPS = 30 Adam steps, seed 0.
# Measured (ratio at 30 steps; at 60, the bench's default, in brackets): boxes 0.952 (0.934),
# layout 0.148 (0.050), map 0.021 (0.0003), waypoints 0.767 (0.135), trajectory 0.932 (0.977),
# warp 0.222 (0.036), camera 0.183 (0.025). A cut pathway (its input zeroed) gives the same output
# for both controls, a ratio of 1 exactly: zeroing the layout encoder's features or the box
# tokens made these tests fail (ratio 1.0). Box cross-attention learns slowest (each image token
# has to find its box through one attention token: the case for the layout), and the
# trajectory encoder's learning of the lateral sign depends on the draw (30 steps, seeds 1 / 2:
# 0.927 / 1.001), so theirs are the loosest bounds that a cut still fails.
BOUNDS = {"boxes": 0.99, "layout": 0.4, "map": 0.2, "waypoints": 0.9, "trajectory": 0.97, "warp": 0.5, "camera": 0.5}


@pytest.mark.slow(seconds=10)
@pytest.mark.parametrize("pathway", controls.PATHWAYS)
def test_the_true_control_beats_a_shuffled_one(pathway):
    row = measured(pathway)
    assert row["steps"] == STEPS and row["pathway"] == pathway
    assert row["loss_true"] < BOUNDS[pathway] * row["loss_shuffled"], row
    assert row["moved"] > 0 and row["follow"] > 0, row
    assert row["loss_true"] < row["loss_repeat"], row  # training helped: the untrained model repeats


def test_toys_change_only_what_the_control_decides():
    """Frame 0 is the given frame; frame 1's change is the one the module docstring gives; the
    shuffled targets follow the previous clip's control."""
    for pathway in controls.PATHWAYS:
        x, cond = controls.toy_clips(pathway, np.random.default_rng(0), 4)
        assert x.shape == (4, 1, 2, controls.H, controls.W, controls.CHANNELS)
        np.testing.assert_array_equal(cond.cond_latents, x)
        assert cond.cond_mask.tolist() == [[True, False]] * 4
        assert controls.shuffled_target(pathway, x).shape == x[:, :, 1].shape
        rolled = controls.shuffled(pathway, cond)
        for name in controls.FIELDS[pathway]:
            np.testing.assert_array_equal(getattr(rolled, name), np.roll(getattr(cond, name), 1, 0))
    x, cond = controls.toy_clips("waypoints", np.random.default_rng(1), 4)
    sign = np.sign(cond.waypoints[:, 1, 1])[:, None, None, None, None]
    np.testing.assert_array_equal(x[:, :, 1], sign * x[:, :, 0])
    np.testing.assert_array_equal(controls.shuffled_target("waypoints", x), np.roll(sign, 1, 0) * x[:, :, 0])
    x, cond = controls.toy_clips("warp", np.random.default_rng(1), 3)
    np.testing.assert_array_equal(cond.warp, x)
    np.testing.assert_array_equal(controls.shuffled_target("warp", x), np.roll(x[:, :, 1], 1, 0))
    x, cond = controls.toy_clips("map", np.random.default_rng(1), 3)  # road blocks on the token grid
    change = x[:, 0, 1] - x[:, 0, 0]
    road = cond.bev_map[:, 1, ::8, ::8, 0]  # one BEV cell per block
    np.testing.assert_allclose(
        change, np.broadcast_to(2 * np.repeat(np.repeat(road, 2, 1), 2, 2)[..., None], change.shape), atol=1e-5
    )
    x, cond = controls.toy_clips("camera", np.random.default_rng(1), 64)
    change = x[:, 0, 1] - x[:, 0, 0]
    assert set(np.unique(np.round(change, 5))) == {0.0, 2.0}
    yaw = np.degrees(np.arctan2(cond.cam_to_ego[:, 0, 1, 2], cond.cam_to_ego[:, 0, 0, 2]))  # optical axis
    half_fov = np.degrees(np.arctan(controls.W * 4 / cond.intrinsics[:, 0, 0, 0]))
    np.testing.assert_array_equal(change[:, 0, 0, 0] > 1, np.abs(yaw) <= half_fov)


def test_cli_prints_the_table_and_json_lines_and_refuses_bad_options(capsys):
    from jaxdrive.cli import main

    assert main(["bench", "controls", "--steps", "2", "--pathways", "warp"]) == 0
    out = capsys.readouterr().out
    rows = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    assert len(rows) == 1 and rows[0]["bench"] == "controls" and rows[0]["pathway"] == "warp"
    assert rows[0]["figure"] == "control_ratio" and rows[0]["steps"] == 2
    assert rows[0]["value"] == pytest.approx(rows[0]["loss_true"] / rows[0]["loss_shuffled"], rel=1e-2)
    header = next(line for line in out.splitlines() if line.startswith("pathway"))
    assert header.split() == [
        "pathway",
        "steps",
        "loss_repeat",
        "loss_true",
        "loss_shuffled",
        "ratio",
        "moved",
        "follow",
    ]
    for argv, message in (
        (["--pathways", "lidar"], r"--pathways: expected names from .*, got \['lidar'\]"),
        (["--steps", "0"], r"--steps: expected an integer >= 1, got 0"),
        (["--batch", "-1"], r"--batch: expected an integer >= 1, got -1"),
        (["--clips", "1"], r"--clips: expected at least 2 clips"),
        (["--lr", "0"], r"--lr: expected a positive learning rate, got 0.0"),
    ):
        with pytest.raises(ValueError, match=message):
            controls.main(argv)
        assert main(["bench", "controls", *argv]) == 2
        assert "jaxdrive bench: error: --" in capsys.readouterr().err
