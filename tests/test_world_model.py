"""jaxdrive.WorldModel: a run loaded for generation (weights, codec and config, no train state),
its checks before anything compiles, and one clip sampled on a mesh whose batch has two shards."""

import json
from pathlib import Path

import numpy as np
import pytest

import jaxdrive
from jaxdrive.world_model import WorldModel

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def _unloaded(**sets) -> WorldModel:
    """A WorldModel of configs/tiny.py with no parameters: what the checks read (nothing they do
    may compile: a compile would fail on the missing parameters, not with the message checked)."""
    import jax

    from jaxdrive.config import load_config
    from jaxdrive.models.latents import LatentCodec
    from jaxdrive.train.common import mesh_from_config, sampling_spec

    config = load_config(CONFIGS / "tiny.py", [f"{k}={v}" for k, v in sets.items()])
    mesh = mesh_from_config(config, jax.devices()[:1])
    return WorldModel(config, sampling_spec(config, mesh, LatentCodec.from_config(config.latents)), None, step=0)


def test_the_top_level_name_is_the_world_model():
    assert jaxdrive.WorldModel is WorldModel
    with pytest.raises(AttributeError, match="no attribute 'WorldMdl'"):
        jaxdrive.WorldMdl  # noqa: B018


@pytest.mark.parametrize(
    "make, missing",
    [
        (lambda p: p / "absent", "not a directory"),
        (lambda p: p, "no config.json"),
        (lambda p: (p / "config.json").write_text("{}") and p, "nothing under"),
    ],
)
def test_from_run_names_the_folder_and_what_it_lacks(tmp_path, make, missing):
    folder = make(tmp_path)
    with pytest.raises(ValueError, match=r"^workdir: expected a run directory") as e:
        WorldModel.from_run(folder)
    assert str(folder) in str(e.value) and missing in str(e.value)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(frames=0), r"^frames: expected an integer >= 1, got 0"),
        (dict(frames=9, strategy="zigzag"), r"^strategy: expected one of .*rollout.*, got 'zigzag'"),
        (dict(frames=9, route="backflip"), r"^route: expected a JSON or CSV file or a manoeuvre"),
        (dict(frames=9, cfg_boxes=2.0), r"^cfg_boxes: expected a model trained with the boxes control"),
        (dict(frames=9, cfg=-1.0), r"^cfg: expected"),
        (dict(frames=9, clips=0), r"^clips: expected an integer >= 1"),
        (dict(frames=9, taps=(-1,)), r"^taps: not an option of strategy 'rollout'"),
        (dict(frames=9, strategy="coarse-fine"), r"^fine_workdir: strategy 'coarse-fine' needs a fine model run"),
        (dict(frames=9, controls="predicted"), r"^controls: 'predicted' needs predictor="),
        (dict(frames=9, source=3), r"^source: expected a split name, a clip record or a list of them, got int"),
    ],
)
def test_generate_rejects_bad_input_before_anything_compiles(kwargs, message):
    model = _unloaded()  # configs/tiny.py: no boxes control
    source = kwargs.pop("source", None)
    with pytest.raises(ValueError, match=message):
        model.generate(source, **kwargs)


@pytest.mark.slow(seconds=20)
def test_one_clip_samples_on_a_mesh_of_two_batch_shards(tiny_dit, tmp_path):
    """The run trained on data 2 x seq 4: one clip is padded to two and the padding dropped."""
    model = WorldModel.from_run(tiny_dit)
    assert dict(zip(model.mesh.axis_names, model.mesh.axis_sizes))["data"] == 2
    g = model.generate(frames=9, strategy="rollout", steps=1, key=0, out=tmp_path / "out")
    assert g.video.shape[:3] == (1, 6, 9) and g.latents.shape[:3] == (1, 6, 9)
    assert g.report["padded_clips"] == 1 and g.report["clips"] == 1
    assert np.isfinite(g.video).all() and np.abs(g.video).max() <= 1.0
    np.testing.assert_array_equal(g.video[0, :, :2], g.recorded[0, :, :2])  # the given frames stay
    written = json.loads((tmp_path / "out" / "report.json").read_text())
    assert written["clips"] == 1 and np.load(tmp_path / "out" / "latents.npy").shape[0] == 1
    # the same clip from the command line, which once refused --clips 1 on this mesh
    from jaxdrive.cli import main as cli

    argv = ["sample", "--workdir", str(tiny_dit), "--strategy", "rollout", "--frames", "9", "--clips", "1"]
    assert cli([*argv, "--steps", "1", "--out", str(tmp_path / "cli"), "--no-progress"]) == 0
    np.testing.assert_array_equal(np.load(tmp_path / "cli" / "latents.npy"), g.latents)
