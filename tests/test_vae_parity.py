"""The jaxdrive VAE against diffusers' PyTorch ``AutoencoderKLCogVideoX`` on tiny random models.

Weights go through the real import path (``save_pretrained`` -> safetensors ->
``load_diffusers_vae``). Compared, max absolute error <= 1e-4 in fp32:
- ``encode`` / ``decode`` (chunked, the default) with diffusers' ``encode(x).latent_dist.mean`` and
  ``decode(z).sample``, for clips of one chunk and of several (with a remainder in the first);
- the whole-clip pass with diffusers' ``encoder(x)`` / ``decoder(z)`` called on the whole clip;
- spatial tiling with diffusers' ``enable_tiling`` path.

An even number of latent frames is where jaxdrive departs from diffusers on purpose (see
``jaxdrive.models.vae.layers.Upsample3D``): diffusers decodes ``F'`` even into ``4 F'`` frames,
jaxdrive into ``1 + 4 (F' - 1)``; encoding is compared there too.
"""

import functools

import numpy as np
import pytest

torch = pytest.importorskip("torch")
diffusers = pytest.importorskip("diffusers")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from jaxdrive.convert.diffusers_vae import load_diffusers_vae  # noqa: E402

TOL = 1e-4
CONFIGS = {
    # 3 blocks: 4x space, 4x time (CogVideoX's layout, tiny)
    "b3": dict(block_out_channels=(8, 8, 16), latent_channels=4, layers_per_block=1, norm_num_groups=4),
    # 4 blocks, 2 layers, 8 groups, 6 latent channels: 8x space, channel changes in the shortcuts
    "b4": dict(block_out_channels=(8, 16, 16, 24), latent_channels=6, layers_per_block=2, norm_num_groups=8),
    # 2x temporal compression
    "t2": dict(
        block_out_channels=(8, 16, 16),
        latent_channels=4,
        layers_per_block=1,
        norm_num_groups=4,
        temporal_compression_ratio=2,
    ),
}


@pytest.fixture(scope="module")
def tmp_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("vae_parity")


@functools.cache
def _pair(name, root):
    """(diffusers model, jaxdrive vae, params, directory) for CONFIGS[name]."""
    cfg = CONFIGS[name]
    torch.manual_seed(0)
    n = len(cfg["block_out_channels"])
    model = diffusers.AutoencoderKLCogVideoX(
        down_block_types=("CogVideoXDownBlock3D",) * n,
        up_block_types=("CogVideoXUpBlock3D",) * n,
        sample_height=32,
        sample_width=32,
        **cfg,
    ).eval()
    with torch.no_grad():  # non-trivial norm affine parameters, so their mapping is checked too
        for pname, p in model.named_parameters():
            if "norm" in pname:
                p.add_(0.3 * torch.randn_like(p))
    path = f"{root}/{name}"
    model.save_pretrained(path)
    vae, params = load_diffusers_vae(path)
    return model, vae, params, path


def _video(frames, height, width, seed):
    return (
        torch.rand(1 if frames > 17 else 2, 3, frames, height, width, generator=torch.Generator().manual_seed(seed)) * 2
        - 1
    )


def _to_jax(t):  # [B, C, T, H, W] -> [B, T, H, W, C]
    return jnp.asarray(t.numpy().transpose(0, 2, 3, 4, 1))


def _to_np(t):
    return t.numpy().transpose(0, 2, 3, 4, 1)


def _err(a, b):
    return float(np.max(np.abs(np.asarray(a) - b)))


# (config, frames): one encode chunk; four with the remainder in the first; two (4 blocks, 8x space);
# 2x temporal compression over two encode and four decode chunks
@pytest.mark.slow(seconds=15)
@pytest.mark.parametrize("name,frames", [("b3", 9), ("b3", 33), ("b4", 17), ("t2", 17)])
def test_chunked_encode_decode_match_diffusers(tmp_dir, name, frames):
    model, vae, params, _ = _pair(name, str(tmp_dir))
    s = vae.config.spatial_compression
    x = _video(frames, 2 * s, 3 * s, frames)
    with torch.no_grad():
        mean = model.encode(x).latent_dist.mean
        video = model.decode(mean).sample
    z = vae.encode(params, _to_jax(x))
    assert z.shape == _to_np(mean).shape == (x.shape[0], vae.latent_frames(frames), 2, 3, vae.config.latent_channels)
    assert _err(z, _to_np(mean)) <= TOL
    out = vae.decode(params, jnp.asarray(_to_np(mean)))
    assert out.shape == (x.shape[0], frames, 2 * s, 3 * s, 3)
    assert _err(out, _to_np(video)) <= TOL


@pytest.mark.slow(seconds=6)
@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_whole_clip_matches_diffusers_encoder_and_decoder(tmp_dir, name):
    model, vae, params, _ = _pair(name, str(tmp_dir))
    frames, s = 1 + 4 * vae.config.temporal_compression, vae.config.spatial_compression
    x = _video(frames, 2 * s, 2 * s, 1)
    with torch.no_grad():
        moments = model.encoder(x)[0]
        latents = moments[:, : vae.config.latent_channels]
        video = model.decoder(latents)[0]
        chunked = model.decode(latents).sample
    mean, logvar = vae.posterior(params, _to_jax(x), mode="whole")
    c = vae.config.latent_channels
    assert _err(mean, _to_np(moments)[..., :c]) <= TOL
    assert _err(logvar, np.clip(_to_np(moments)[..., c:], -30, 20)) <= TOL
    out = vae.decode(params, jnp.asarray(_to_np(latents)), mode="whole")
    assert _err(out, _to_np(video)) <= TOL
    # GroupNorm statistics span time, so the two passes really differ: the chunked default is
    # not the whole-clip pass under another name
    assert np.max(np.abs(_to_np(video) - _to_np(chunked))) > 100 * TOL


@pytest.mark.slow(seconds=11)
def test_tiled_encode_decode_match_diffusers(tmp_dir):
    model, _, _, path = _pair("b3", str(tmp_dir))
    tile = dict(tile_sample_height=16, tile_sample_width=16, tile_overlap_height=0.25, tile_overlap_width=0.25)
    model.enable_tiling(
        tile_sample_min_height=16,
        tile_sample_min_width=16,
        tile_overlap_factor_height=0.25,
        tile_overlap_factor_width=0.25,
    )
    try:
        vae, params = load_diffusers_vae(path, tiling=True, **tile)
        x = torch.rand(1, 3, 9, 40, 28, generator=torch.Generator().manual_seed(2)) * 2 - 1
        with torch.no_grad():
            mean = model.encode(x).latent_dist.mean
            video = model.decode(mean).sample
    finally:
        model.disable_tiling()
    assert _err(vae.encode(params, _to_jax(x)), _to_np(mean)) <= TOL
    z = jnp.asarray(_to_np(mean))
    assert _err(vae.decode(params, z), _to_np(video)) <= TOL
    assert _err(vae.decode(params, z, tiled=False), _to_np(video)) > 100 * TOL  # tiling was used


@pytest.mark.slow(seconds=4)
@pytest.mark.parametrize("frames", [5, 13])
def test_even_latent_count_keeps_the_frame_correspondence(tmp_dir, frames):
    model, vae, params, _ = _pair("b3", str(tmp_dir))
    x = torch.rand(1, 3, frames, 8, 8, generator=torch.Generator().manual_seed(3)) * 2 - 1
    with torch.no_grad():
        mean = model.encode(x).latent_dist.mean
        theirs = model.decode(mean).sample
    z = vae.encode(params, _to_jax(x))
    assert _err(z, _to_np(mean)) <= TOL  # encoding agrees
    latents = z.shape[1]
    assert latents % 2 == 0
    assert theirs.shape[2] == 4 * latents  # diffusers: 4 F' frames
    assert vae.decode(params, z).shape[1] == frames == vae.video_frames(latents)  # jaxdrive: 1 + 4k


def _copy_with(src, dst, *, drop=(), add=None, config=None):
    """A copy of the diffusers directory ``src`` with tensors dropped/added or the config changed."""
    import json
    import shutil

    from safetensors.numpy import load_file, save_file

    shutil.copytree(src, dst)
    weights = f"{dst}/diffusion_pytorch_model.safetensors"
    tensors = {k: v for k, v in load_file(weights).items() if k not in drop}
    tensors.update(add or {})
    save_file(tensors, weights)
    if config:
        cfg = json.loads(open(f"{dst}/config.json").read())
        cfg.update(config)
        open(f"{dst}/config.json", "w").write(json.dumps(cfg))
    return dst


def test_import_errors_name_the_file_and_the_keys(tmp_dir, tmp_path):
    _, _, _, path = _pair("b3", str(tmp_dir))
    dropped = "decoder.mid_block.resnets.0.norm1.conv_y.conv.weight"
    bad = _copy_with(
        path, tmp_path / "keys", drop=[dropped], add={"encoder.extra.weight": np.zeros((2, 2), np.float32)}
    )
    with pytest.raises(ValueError, match=r"diffusion_pytorch_model.safetensors: weights do not match") as e:
        load_diffusers_vae(bad)
    assert "unknown keys (1): ['encoder.extra.weight']" in str(
        e.value
    ) and "decoder/mid_block_resnets_0/norm1/conv_y/kernel" in str(e.value)
    wrong = _copy_with(path, tmp_path / "shape", add={"encoder.conv_in.conv.bias": np.zeros((5,), np.float32)})
    with pytest.raises(ValueError, match=r"shape mismatches .*encoder/conv_in/bias: expected \[8\], got \[5\]"):
        load_diffusers_vae(wrong)
    # a truncated file
    broken = _copy_with(path, tmp_path / "truncated")
    data = (broken / "diffusion_pytorch_model.safetensors").read_bytes()
    (broken / "diffusion_pytorch_model.safetensors").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"truncated/diffusion_pytorch_model.safetensors: not a complete"):
        load_diffusers_vae(broken)
    # a garbled header
    (broken / "diffusion_pytorch_model.safetensors").write_bytes(data[:8] + b"{x" + data[10:])
    with pytest.raises(ValueError, match=r"diffusion_pytorch_model.safetensors: corrupt safetensors file"):
        load_diffusers_vae(broken)
    # pickled weights are refused, not loaded
    (broken / "diffusion_pytorch_model.safetensors").unlink()
    (broken / "diffusion_pytorch_model.bin").write_bytes(b"pickle")
    with pytest.raises(ValueError, match=r"pickled weights are never loaded"):
        load_diffusers_vae(broken)
    other = _copy_with(path, tmp_path / "class", config={"_class_name": "AutoencoderKL"})
    with pytest.raises(ValueError, match=r"config.json: expected _class_name 'AutoencoderKLCogVideoX'"):
        load_diffusers_vae(other)
    quant = _copy_with(path, tmp_path / "quant", config={"use_quant_conv": True})
    with pytest.raises(ValueError, match=r"use_quant_conv: expected False"):
        load_diffusers_vae(quant)


def test_convert_command_writes_a_loadable_model(tmp_dir, tmp_path, capsys):
    from jaxdrive.cli import main
    from jaxdrive.models.pretrained import load_pretrained

    model, vae, params, path = _pair("b3", str(tmp_dir))
    assert main(["convert", "vae", str(path), str(tmp_path / "out")]) == 0
    assert "wrote the VAE" in capsys.readouterr().out
    loaded, restored = load_pretrained(tmp_path / "out")
    assert loaded.config == vae.config
    for a, b in zip(jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(restored)):
        np.testing.assert_array_equal(a, b)
    assert main(["convert", "vae", str(tmp_path / "nowhere"), str(tmp_path / "out2")]) == 2
    assert "error: path: expected a diffusers directory" in capsys.readouterr().err
