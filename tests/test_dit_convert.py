"""Imported CogVideoX transformers against diffusers' PyTorch code on tiny random configs
(CogVideoX 1.0 with 3D sin-cos positions as the 2B model, 1.0 with 3D RoPE as the 5B model,
1.5 with a 2x2x2 patch, the ofs embedding and no patch bias), and the loader's errors."""

import ast
import importlib.util
import json
import pathlib

import jax
import numpy as np
import pytest

torch = pytest.importorskip("torch")
diffusers = pytest.importorskip("diffusers")

from jaxdrive.convert import load_diffusers_transformer  # noqa: E402
from jaxdrive.models.dit.conditions import Conditions  # noqa: E402

BASE = dict(
    num_attention_heads=2,
    attention_head_dim=16,
    in_channels=4,
    out_channels=4,
    time_embed_dim=24,
    text_embed_dim=12,
    num_layers=2,
    sample_width=8,
    sample_height=6,
    sample_frames=9,
    patch_size=2,
    max_text_seq_length=5,
)
CASES = {
    "1.0-sincos": (dict(), (4, 6, 10)),
    "1.0-rope": (dict(use_rotary_positional_embeddings=True), (4, 6, 10)),  # grid 3x5 != training 3x4
    "1.5-rope-pt2": (
        dict(use_rotary_positional_embeddings=True, patch_size_t=2, ofs_embed_dim=24, patch_bias=False),
        (4, 6, 8),
    ),
}


def _crop_region_fn():
    """diffusers' pipeline helper, read from its source: importing the pipeline needs transformers."""
    src = pathlib.Path(importlib.util.find_spec("diffusers").origin).parent / "pipelines/cogvideo/pipeline_cogvideox.py"
    fn = next(
        n
        for n in ast.parse(src.read_text()).body
        if isinstance(n, ast.FunctionDef) and n.name == "get_resize_crop_region_for_grid"
    )
    ns = {}
    exec(compile(ast.Module([fn], []), str(src), "exec"), ns)
    return ns["get_resize_crop_region_for_grid"]


def _rotary(cfg, frames, gh, gw):
    """The rotary tables the diffusers CogVideoX pipeline builds (_prepare_rotary_positional_embeddings)."""
    from diffusers.models.embeddings import get_3d_rotary_pos_embed

    p, pt = cfg["patch_size"], cfg.get("patch_size_t")
    base_w, base_h = cfg["sample_width"] // p, cfg["sample_height"] // p
    if pt is None:
        crops = _crop_region_fn()((gh, gw), base_w, base_h)
        return get_3d_rotary_pos_embed(cfg["attention_head_dim"], crops, (gh, gw), frames)
    return get_3d_rotary_pos_embed(
        cfg["attention_head_dim"], None, (gh, gw), (frames + pt - 1) // pt, grid_type="slice", max_size=(base_h, base_w)
    )


def _save(tmp_path, **changes):
    torch.manual_seed(0)
    cfg = dict(BASE, **changes)
    model = diffusers.CogVideoXTransformer3DModel(**cfg).eval()
    with torch.no_grad():  # random weights, not the zero/unit inits
        for p in model.parameters():
            p.add_(0.1 * torch.randn_like(p))
    model.save_pretrained(tmp_path, safe_serialization=True)
    return model, cfg


@pytest.mark.parametrize("case", CASES)
def test_parity_with_diffusers(case, tmp_path):
    changes, (frames, h, w) = CASES[case]
    model, cfg = _save(tmp_path, **changes)
    torch.manual_seed(1)
    x = torch.randn(2, frames, 4, h, w)
    text = torch.randn(2, BASE["max_text_seq_length"], BASE["text_embed_dim"])
    t = torch.tensor([500.0, 37.0])
    kw = {}
    if cfg.get("use_rotary_positional_embeddings"):
        kw["image_rotary_emb"] = _rotary(cfg, frames, h // 2, w // 2)
    if cfg.get("ofs_embed_dim"):
        kw["ofs"] = torch.tensor([2.0, 2.0])
    with torch.no_grad():
        want = model(x, text, t, return_dict=False, **kw)[0].numpy()
    dit, params = load_diffusers_transformer(tmp_path)
    assert dit.config.layout == "full" and dit.config.timestep_scale == 1000.0
    lat = x.numpy().transpose(0, 1, 3, 4, 2)[:, None]  # [B, V = 1, F', h, w, C]
    got = jax.jit(lambda p, lat, s, e: dit.forward(p, lat, s, Conditions(text=e)))(
        params, lat, t.numpy() / 1000.0, text.numpy()
    )
    got = np.asarray(got)[:, 0].transpose(0, 1, 4, 2, 3)
    assert got.shape == want.shape
    assert np.abs(got - want).max() <= 1e-4, np.abs(got - want).max()


def test_unknown_and_missing_tensors_are_listed(tmp_path):
    from safetensors.numpy import load_file, save_file

    _save(tmp_path)
    path = tmp_path / "diffusion_pytorch_model.safetensors"
    sd = load_file(path)
    sd["transformer_blocks.0.attn1.extra.weight"] = np.zeros(3, np.float32)
    del sd["norm_final.bias"]
    save_file(sd, path)
    with pytest.raises(
        ValueError,
        match=r"missing \['norm_final.bias'\], unexpected "
        r"\['transformer_blocks.0.attn1.extra.weight'\]",
    ):
        load_diffusers_transformer(tmp_path)


def test_file_errors_name_the_file(tmp_path):
    _save(tmp_path)
    weights = tmp_path / "diffusion_pytorch_model.safetensors"
    weights.write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{not json")
    with pytest.raises(
        ValueError, match="diffusion_pytorch_model.safetensors: (corrupt|not a complete) safetensors file"
    ):
        load_diffusers_transformer(tmp_path)
    weights.unlink()
    (tmp_path / "diffusion_pytorch_model.bin").write_bytes(b"pickle")
    with pytest.raises(ValueError, match=r"found \['diffusion_pytorch_model.bin'\]: pickled weights are never loaded"):
        load_diffusers_transformer(tmp_path)
    (tmp_path / "config.json").write_text("{")
    with pytest.raises(ValueError, match="config.json: not a valid JSON config"):
        load_diffusers_transformer(tmp_path)
    (tmp_path / "config.json").write_text(json.dumps({"_class_name": "UNet2DConditionModel"}))
    with pytest.raises(ValueError, match="expected _class_name 'CogVideoXTransformer3DModel'"):
        load_diffusers_transformer(tmp_path)


@pytest.mark.slow(seconds=3)
def test_scanned_import_matches(tmp_path):
    _save(tmp_path)
    dit, params = load_diffusers_transformer(tmp_path)
    sdit, sparams = load_diffusers_transformer(tmp_path, scan_layers=True)
    assert "layers_0_2" in sparams and sparams["layers_0_2"]["layer"]["ff"]["fc1"]["kernel"].shape[0] == 2
    rng = np.random.default_rng(0)
    lat = rng.standard_normal((1, 1, 2, 4, 4, 4)).astype(np.float32)
    text = rng.standard_normal((1, 5, 12)).astype(np.float32)
    a = jax.jit(lambda p: dit.forward(p, lat, np.float32([0.3]), Conditions(text=text)))(params)
    b = jax.jit(lambda p: sdit.forward(p, lat, np.float32([0.3]), Conditions(text=text)))(sparams)
    np.testing.assert_allclose(np.asarray(b), np.asarray(a), atol=1e-5)
