"""``train.init_from``: a new run starts from another run's (or a diffusers folder's) parameters,
keeps its own initialisation for what the source lacks, and refuses shapes that differ."""

import json
import logging
from pathlib import Path

import flax.linen as nn
import jax
import numpy as np
import pytest
from flax.traverse_util import flatten_dict

from jaxdrive.config import load_config, to_dict
from jaxdrive.train.checkpoint import Checkpoints
from jaxdrive.train.init_from import merge_params, source_params
from jaxdrive.train.run import CONFIG_FILE, Run

from train_fixtures import write_synthetic

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "configs" / "tiny.py"
SMALL = ["data.views=2", "data.batch_size=2", "model.depth=1", "data.frames=5", "mesh.data=2", "mesh.seq=4"]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return write_synthetic(tmp_path_factory.mktemp("synth") / "data", train=2, frames=5)


def config(dataset, *sets):
    return load_config(TINY, [f"data.path={dataset}", *SMALL, *sets])


@pytest.fixture(scope="module")
def source_run(dataset, tmp_path_factory):
    """A run directory whose EMA differs from its raw parameters (seed 7, not the new runs' 0)."""
    workdir = tmp_path_factory.mktemp("stage1")
    cfg = config(dataset, "train.seed=7")
    state = Run(cfg).init_state()[0]
    state = state.replace(ema=jax.tree_util.tree_map(lambda x: x + 1.0, state.ema))
    ckpts = Checkpoints(workdir, asynchronous=False)
    ckpts.save(3, state, {}, {"step": 3})
    ckpts.close()
    (workdir / CONFIG_FILE).write_text(json.dumps(to_dict(cfg)))
    return workdir, state


def flat(tree):
    return {k: np.asarray(v) for k, v in flatten_dict(jax.device_get(tree), sep="/").items()}


@pytest.mark.slow(seconds=10)
def test_a_later_stage_loads_what_the_source_has_and_keeps_its_own_init_for_the_rest(dataset, source_run, caplog):
    workdir, saved = source_run
    # stage 2 adds a control (boxes: a new encoder, its null, ...) to the stage-1 model
    run = Run(config(dataset, f"train.init_from={workdir}", "model.controls.boxes=true"))
    with caplog.at_level(logging.INFO, logger="jaxdrive.train.run"):
        state = run.init_state()[0]
    logs = [r.getMessage() for r in caplog.records if r.name == "jaxdrive.train.run"]
    fresh = flat(Run(config(dataset, "model.controls.boxes=true")).init_state()[0].params)
    got, ema, raw = flat(state.params), flat(saved.ema), flat(saved.params)
    added = sorted(set(got) - set(ema))
    assert added and any("boxes" in k for k in added)
    for k in ema:
        np.testing.assert_array_equal(got[k], ema[k])  # loaded: the source's EMA
    for k in added:
        np.testing.assert_array_equal(got[k], fresh[k])  # kept: the new run's own init
    np.testing.assert_array_equal(flat(state.ema)[sorted(ema)[0]], ema[sorted(ema)[0]])  # EMA starts there too
    assert any(f"loaded {len(ema)} parameters" in line for line in logs)
    # the raw parameters by choice
    raw_run = Run(config(dataset, f"train.init_from={workdir}", "train.init_from_ema=false"))
    got_raw = flat(raw_run.init_state()[0].params)
    name = sorted(raw)[0]
    np.testing.assert_array_equal(got_raw[name], raw[name])
    assert not np.array_equal(raw[name], ema[name])


def test_a_shape_mismatch_names_the_parameter(dataset, source_run):
    workdir, _ = source_run
    run = Run(config(dataset, f"train.init_from={workdir}", "model.head_dim=32"))
    with pytest.raises(
        ValueError,
        match=r"train.init_from: parameter '.*': expected shape \[.*\] \(the new model\), "
        r"got \[.*\] in ",
    ):
        run.init_state()


def test_the_name_map_renames_source_paths():
    new = {"blocks_0": {"kernel": np.zeros((2, 3), np.float32)}, "head": {"bias": np.zeros(3, np.float32)}}
    source = {"layers_0": {"kernel": np.ones((2, 3), np.float32)}, "extra": {"w": np.ones(1, np.float32)}}
    with pytest.raises(ValueError, match=r"found none of its 2 names .* rename them with train.init_map"):
        merge_params(new, source)
    merged, report = merge_params(new, source, name_map=(r"^layers_(\d+)=blocks_\1",))
    np.testing.assert_array_equal(merged["blocks_0"]["kernel"], 1.0)
    np.testing.assert_array_equal(merged["head"]["bias"], 0.0)
    assert report.loaded == ("blocks_0/kernel",) and report.kept == ("head/bias",) and report.unused == ("extra/w",)
    with pytest.raises(ValueError, match=r"train.init_map: expected 'regex=replacement' entries, got 'layers'"):
        merge_params(new, source, name_map=("layers",))


def test_layers_move_between_scanned_runs_of_other_bounds_and_unrolled_layers():
    # STAGE stage 2 adds an HTFT layer after layer 1, which splits the scanned run 0..3 in two
    layer = lambda i: np.full((2, 3), i, np.float32)
    source = {
        "layers_0_4": {"kernel": np.stack([layer(i) for i in range(4)])},
        "head": {"bias": np.ones(3, np.float32)},
    }
    new = {
        "layers_0_2": {"kernel": np.zeros((2, 2, 3), np.float32)},
        "layers_2": {"kernel": np.zeros((2, 3), np.float32)},
        "layers_3_5": {"kernel": np.zeros((2, 2, 3), np.float32)},
        "head": {"bias": np.zeros(3, np.float32)},
    }
    merged, report = merge_params(new, source)
    np.testing.assert_array_equal(merged["layers_0_2"]["kernel"], np.stack([layer(0), layer(1)]))
    np.testing.assert_array_equal(merged["layers_2"]["kernel"], layer(2))
    # a run the source has only part of (layer 4) keeps its initialisation
    np.testing.assert_array_equal(merged["layers_3_5"]["kernel"], 0.0)
    assert report.loaded == ("layers_0_2/kernel", "layers_2/kernel", "head/bias")
    assert report.kept == ("layers_3_5/kernel",) and report.unused == ()
    # and back: unrolled layers into a scanned run
    unrolled = {f"layers_{i}": {"kernel": layer(i)} for i in range(4)}
    merged, report = merge_params({"layers_1_4": {"kernel": np.zeros((3, 2, 3), np.float32)}}, unrolled)
    np.testing.assert_array_equal(merged["layers_1_4"]["kernel"], np.stack([layer(i) for i in (1, 2, 3)]))
    assert report.unused == ("layers_0/kernel",)


def test_bad_sources_fail_before_compiling(dataset, tmp_path):
    with pytest.raises(ValueError, match=r"train.init_from: expected a run directory .* \(not a directory\)"):
        Run(config(dataset, f"train.init_from={tmp_path / 'missing'}"))
    with pytest.raises(ValueError, match=r"train.init_map: expected a regular expression"):
        Run(config(dataset, "train.init_map=a(=x"))
    from jaxdrive.parallel import make_mesh

    with pytest.raises(ValueError, match=r"expected a jaxdrive run directory .* or a diffusers transformer folder"):
        source_params(tmp_path, mesh=make_mesh(data=8))


def test_a_diffusers_folder_is_a_source(tmp_path):
    torch = pytest.importorskip("torch")
    diffusers = pytest.importorskip("diffusers")
    torch.manual_seed(0)
    model = diffusers.CogVideoXTransformer3DModel(
        num_attention_heads=2,
        attention_head_dim=16,
        in_channels=4,
        out_channels=4,
        time_embed_dim=24,
        text_embed_dim=12,
        num_layers=1,
        sample_width=8,
        sample_height=6,
        sample_frames=9,
        patch_size=2,
        max_text_seq_length=5,
    )
    model.save_pretrained(tmp_path, safe_serialization=True)
    from jaxdrive.convert import load_diffusers_transformer
    from jaxdrive.parallel import make_mesh

    dit, want = load_diffusers_transformer(tmp_path)
    got = source_params(tmp_path, mesh=make_mesh(data=8))
    for k, v in flat(want).items():
        np.testing.assert_array_equal(flat(got)[k], v)
    # a LongDWM-style fine model: the imported layers plus a warp input the folder has not
    fine = dit.config.replace(controls=dict(warp=True))
    from jaxdrive.models.dit import DiT

    new = nn.unbox(DiT(fine).init_params(0))
    merged, report = merge_params(new, got, source_name=str(tmp_path))
    assert report.kept and all("warp" in k for k in report.kept) and not report.unused
