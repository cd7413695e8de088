"""Guidance a run samples with: the recipe's ``sample.cfg``, the per-control scales of
``--cfg-boxes`` / ``--cfg-route`` and the checks that refuse them before anything compiles."""

from __future__ import annotations

import json
from pathlib import Path

import jax
import numpy as np
import pytest

from jaxdrive.cli import main as cli
from jaxdrive.config import load_config, to_dict
from jaxdrive.config_checks import check_sections
from jaxdrive.generate.guidance import CONTROLS, check_controls, sampler_guidance
from jaxdrive.models.dit.conditions import Conditions

ROOT = Path(__file__).resolve().parents[1]


def tiny(*sets):
    return load_config(ROOT / "configs" / "tiny.py", list(sets))


@pytest.mark.parametrize(
    "name, cfg",
    [
        ("mila.py:size=tiny,stage=3", 3.0),
        ("mila.py:stage=1", 3.0),
        ("magicdrive_v2.py:size=tiny,stage=1", 2.0),
        ("magicdrive_v2.py", 2.0),
        ("longdwm.py:size=tiny,role=fine", 1.0),
        ("stage.py:size=tiny,stage=1", 1.0),
        ("tiny.py", 1.0),
    ],
)
def test_each_recipe_carries_its_guidance(name, cfg):
    config = load_config(ROOT / "configs" / name)
    check_sections(config)
    assert config.sample.cfg == cfg


def test_a_negative_sample_cfg_is_refused():
    with pytest.raises(ValueError, match=r"sample.cfg: expected values in \[0.0, inf\), got -1"):
        check_sections(tiny("sample.cfg=-1"))


def test_route_is_every_condition_the_trajectory_drop_nulls():
    assert CONTROLS == {"boxes": ("boxes",), "route": ("trajectory", "waypoints", "warp")}


@pytest.mark.parametrize(
    "sets, scales, match",
    [
        ((), {"boxes": 2.0}, r"--cfg-boxes: expected a model trained with the boxes control .* got a model without it"),
        (("model.controls.waypoints=false",), {"route": 2.0}, "--cfg-route: expected a model trained with the route"),
        (
            ("model.controls.boxes=true", "data.drop_prob=0"),
            {"boxes": 2.0},
            r"--cfg-boxes: expected a model trained with condition drops \(data.drop_prob > 0\)",
        ),
        ((), {"route": -1.0}, r"--cfg-route: expected values in \[0.0, inf\), got -1"),
        ((), {"route": float("nan")}, r"--cfg-route: expected values in \[0.0, inf\), got NaN"),
        ((), {"lanes": 2.0}, r"control_guidance: expected controls from \['boxes', 'route'\], got \['lanes'\]"),
    ],
)
def test_per_control_guidance_needs_a_control_the_model_trained_with(sets, scales, match):
    config = tiny(*sets)
    with pytest.raises(ValueError, match=match):
        check_controls(config.model, config.data.drop_prob, scales, option=lambda c: f"--cfg-{c}")


def test_per_control_variants_null_only_their_control():
    config = tiny("model.controls.boxes=true")
    assert check_controls(config.model, config.data.drop_prob, {"route": 3, "boxes": None}) == (("route", 3.0),)
    cond = Conditions()
    names = ["text", "camera", "waypoints", "boxes"]
    out = sampler_guidance(cond, names, 2, 2.0, (("route", 3.0), ("boxes", 0.5)))
    assert out["guidance_scale"] == 2.0
    assert not any(np.asarray(v).any() for v in out["cond"].drop.values())
    assert all(np.asarray(v).all() for v in out["null_cond"].drop.values())
    for control, off in (("route", "waypoints"), ("boxes", "boxes")):
        scale, without = out["control_guidance"][control]
        assert {n for n, v in without.drop.items() if np.asarray(v).all()} == {off}
    assert sampler_guidance(cond, names, 2, 1.0) == {"cond": cond}  # no guidance: one forward
    assert "null_cond" not in sampler_guidance(cond, names, 2, 1.0, (("route", 3.0),))


def test_mila_stage1_trains_the_box_encoder_when_boxes_are_on():
    import flax.linen as nn

    from jaxdrive.models.dit import DiT
    from jaxdrive.models.dit.inputs import example_inputs
    from jaxdrive.train.optim import trainable_labels

    def labels(*sets):
        config = load_config(f"{ROOT / 'configs' / 'mila.py'}:size=tiny,stage=1", list(sets))
        m = config.model
        params = jax.eval_shape(lambda: nn.unbox(DiT(m).init(jax.random.PRNGKey(0), **example_inputs(m))["params"]))
        flat = jax.tree_util.tree_flatten_with_path(trainable_labels(params, config.optim.trainable))[0]
        return {jax.tree_util.keystr(p, simple=True, separator="/"): v for p, v in flat}

    off, on = labels(), labels("model.controls.boxes=true")
    assert not any(k.startswith("boxes") for k in off)
    boxes = {k: v for k, v in on.items() if k.startswith("boxes_")}
    assert boxes and set(boxes.values()) == {"train"}
    assert {k: v for k, v in on.items() if not k.startswith("boxes_")} == off  # the rest as before
    assert any(k.startswith("camera_embed/") and v == "train" for k, v in off.items())
    assert "freeze" in off.values()


def test_magicdrive_tiny_takes_its_own_control_scheme():
    m = load_config(ROOT / "configs" / "magicdrive_v2.py", []).model  # paper size, for reference
    for stage in (1, 2, 3):
        t = load_config(f"{ROOT / 'configs' / 'magicdrive_v2.py'}:size=tiny,stage={stage}").model
        assert t.multiview == m.multiview == "cross_view"
        for name in ("camera", "trajectory", "boxes", "map", "waypoints"):
            assert getattr(t.controls, name) == getattr(m.controls, name), name


# ------------------------------------------------------------------- the CLI, before anything compiles
@pytest.fixture(scope="module")
def config_only_run(tmp_path_factory):
    """A run directory holding only config.json (tiny, boxes off, 2 views): every check below has
    to fire before a checkpoint is read or anything compiles."""
    workdir = tmp_path_factory.mktemp("config_only")
    config = tiny("data.views=2", "mesh.data=2", "mesh.seq=4", f"data.path={workdir / 'no_data'}")
    (workdir / "config.json").write_text(json.dumps(to_dict(config)))
    return workdir


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--cfg", "-2"], "--cfg: expected values in [0.0, inf), got -2"),
        (["--cfg-route", "-1"], "--cfg-route: expected values in [0.0, inf), got -1"),
        (["--cfg-boxes", "2"], "--cfg-boxes: expected a model trained with the boxes control"),
        (
            ["--cfg-route", "2", "--set", "data.drop_prob=0"],
            "--cfg-route: expected a model trained with condition drops",
        ),
        (["--set", "sample.cfg=-1"], "sample.cfg: expected values in [0.0, inf), got -1"),
    ],
)
@pytest.mark.parametrize("command", ["sample", "sample --strategy rollout", "eval"])
def test_bad_guidance_is_refused_by_the_cli_before_anything_compiles(
    config_only_run, tmp_path, capsys, command, extra, message
):
    argv = command.split() + ["--workdir", str(config_only_run), "--frames", "9", "--out", str(tmp_path / "o"), *extra]
    assert cli(argv) == 2
    assert message in capsys.readouterr().err


def test_eval_says_frames_is_required(config_only_run, tmp_path, capsys):
    assert cli(["eval", "--workdir", str(config_only_run), "--out", str(tmp_path / "o")]) == 2
    assert "--frames: required with --workdir" in capsys.readouterr().err
    for bad in ("1,x", "2,2", "1,-4"):
        assert (
            cli(
                ["eval", "--workdir", str(config_only_run), "--frames", "9", "--cfg", bad, "--out", str(tmp_path / "o")]
            )
            == 2
        )
        assert "--cfg: expected" in capsys.readouterr().err, bad


def test_demo_refuses_a_negative_cfg_before_training(tmp_path, capsys):
    assert cli(["demo", "--workdir", str(tmp_path / "demo"), "--cfg", "-2", "--steps", "1"]) == 2
    assert "--cfg: expected values in [0.0, inf), got -2" in capsys.readouterr().err
    assert not (tmp_path / "demo").exists()
