"""Streaming decode (jaxdrive.models.vae.stream): the parts pushed in any pattern concatenate to
the whole-clip decode, in every streaming mode, with a bounded number of compilations."""

import itertools

import jax
import numpy as np
import pytest
from test_vae import TINY, random_params

from jaxdrive.models.latents import LatentCodec
from jaxdrive.models.vae import CausalVAE, VAEConfig
from jaxdrive.models.vae import stream as vae_stream


def _codec(params, **changes):
    return LatentCodec("vae", 1, 1.0, CausalVAE(VAEConfig(**{**TINY.__dict__, **changes})), params)


@pytest.fixture(scope="module")
def params():
    return random_params(CausalVAE(TINY))


def _latents(frames, h=2, w=2, channels=4, seed=0):
    """Scaled latents [B=1, V=2, F', h, w, C], as the DiT makes them."""
    return np.random.default_rng(seed).normal(size=(1, 2, frames, h, w, channels)).astype(np.float32)


def _parts(total, pattern):
    """Split ``total`` frames: "ones", "uneven" (2, 1, 3, 2, 1, 3, ...), "all" or "zero_first"."""
    sizes = {
        "ones": itertools.repeat(1),
        "uneven": itertools.cycle((2, 1, 3)),
        "all": itertools.repeat(total),
        "zero_first": itertools.chain((0,), itertools.repeat(2)),
    }[pattern]
    out, done = [], 0
    for n in sizes:
        if done == total and out:
            return out
        n = min(n, total - done)
        out.append((done, done + n))
        done += n


def _stream(codec, z, pattern):
    dec = codec.stream_decoder(z.shape[2])
    parts = [dec.push(z[:, :, a:b]) for a, b in _parts(z.shape[2], pattern)]
    parts.append(dec.flush())
    for part in parts:
        assert isinstance(part, np.ndarray) and part.shape[:2] == (1, 2) and part.shape[3:] == (8, 8, 3)
    return parts


@pytest.mark.slow(seconds=5)
@pytest.mark.parametrize("total", [1, 2, 3, 5, 8])
def test_chunked_stream_equals_the_whole_clip_decode(params, total):
    codec = _codec(params)
    z = _latents(total, seed=total)
    whole = np.asarray(codec.decode(params, z))
    assert whole.shape == (1, 2, 1 + 4 * (total - 1), 8, 8, 3)
    for pattern in ("ones", "uneven", "all"):
        parts = _stream(codec, z, pattern)
        np.testing.assert_allclose(np.concatenate(parts, axis=2), whole, rtol=0, atol=1e-5, err_msg=pattern)


def test_chunked_stream_returns_each_chunk_when_it_is_complete(params):
    """5 latent frames in diffusers' chunks (3, 2): nothing until frame 3, then 9 video frames;
    nothing at frame 4, then the last 8; flush returns nothing more."""
    dec = _codec(params).stream_decoder(5)
    z = _latents(5)
    assert [dec.push(z[:, :, i : i + 1]).shape[2] for i in range(5)] == [0, 0, 9, 0, 8]
    assert dec.flush().shape == (1, 2, 0, 8, 8, 3)


def test_the_steady_chunk_sees_the_earlier_latents_through_the_cache(params):
    """The last chunk's frames change when only latent frame 0 changes: the cache carries real
    information, so the equality above tests the cache threading and the first-chunk rule."""
    codec = _codec(params)
    z = _latents(4, seed=3)
    w = z.copy()
    w[:, :, 0] += 1.0
    last = [_stream(codec, x, "ones")[-2] for x in (z, w)]  # chunks (2, 2): the frames of the second
    assert last[0].shape[2] == 8 and np.abs(last[0] - last[1]).max() > 1e-3


@pytest.mark.slow(seconds=13)
def test_tiled_chunked_stream_equals_the_whole_tiled_decode(params):
    """With tiling on (16-pixel tiles, a quarter overlap) and 8 x 28 frames (tiles of 4 and 1
    latent columns), every tile keeps its own cache: the stream equals the whole-clip tiled
    decode."""
    codec = _codec(
        params,
        tiling=True,
        tile_sample_height=16,
        tile_sample_width=16,
        tile_overlap_height=0.25,
        tile_overlap_width=0.25,
    )
    z = _latents(4, h=2, w=7, seed=5)
    whole = np.asarray(codec.decode(params, z))
    assert whole.shape == (1, 2, 13, 8, 28, 3)
    assert codec.vae._tiles(z[0], "tile_latent", True) is not None  # the tiled path runs
    dec = codec.stream_decoder(4)
    parts = [dec.push(z[:, :, a:b]) for a, b in _parts(4, "uneven")] + [dec.flush()]
    assert [p.shape[2] for p in parts] == [5, 0, 8, 0]
    np.testing.assert_allclose(np.concatenate(parts, axis=2), whole, rtol=0, atol=1e-5)


@pytest.mark.slow(seconds=5)
def test_frame_wise_stream_equals_the_whole_clip_decode(params):
    codec = _codec(params, mode="frame_wise")
    z = _latents(5, seed=7)
    whole = np.asarray(codec.decode(params, z))
    assert whole.shape == (1, 2, 5, 8, 8, 3)
    for pattern in ("ones", "zero_first"):
        dec = codec.stream_decoder(5)
        sizes = [dec.push(z[:, :, a:b]).shape[2] for a, b in _parts(5, pattern)]
        assert sizes == [b - a for a, b in _parts(5, pattern)]  # every frame decodes at once
        parts = _stream(codec, z, pattern)
        np.testing.assert_allclose(np.concatenate(parts, axis=2), whole, rtol=0, atol=1e-5)


def test_space_to_depth_stream_is_exact():
    codec = LatentCodec("space_to_depth", 4, 0.5)
    z = _latents(6, channels=48, seed=2)
    whole = np.asarray(codec.decode(None, z))
    for pattern in ("ones", "uneven", "all", "zero_first"):
        np.testing.assert_array_equal(np.concatenate(_stream(codec, z, pattern), axis=2), whole)


def test_long_stream_compiles_twice_and_keeps_a_fixed_cache(params):
    """21 latent frames (81 video frames) one at a time: one trace for the first chunk and one
    for the steady chunk, and the cache keeps its shapes from chunk to chunk."""
    codec = _codec(params)
    vae_stream._decode_chunk.clear_cache()
    dec = codec.stream_decoder(21)
    z = _latents(21, seed=4)
    shapes, frames = [], 0
    for i in range(21):
        frames += dec.push(z[:, :, i : i + 1]).shape[2]
        if dec._cache is not None:
            shapes.append(jax.tree_util.tree_map(np.shape, dec._cache))
    dec.flush()
    assert frames == 81
    assert vae_stream._decode_chunk._cache_size() == 2
    assert all(s == shapes[0] for s in shapes)


def test_whole_mode_cannot_stream(params):
    with pytest.raises(ValueError, match=r"latents.vae_mode: expected one of \['chunked', 'frame_wise'\].*got 'whole'"):
        _codec(params, mode="whole").stream_decoder(5)


@pytest.mark.parametrize("codec_kind", ["vae", "space_to_depth"])
def test_bad_pushes(params, codec_kind):
    codec = _codec(params) if codec_kind == "vae" else LatentCodec("space_to_depth", 2, 1.0)
    c = codec.channels
    with pytest.raises(ValueError, match="total_latent_frames: expected an integer >= 1, got 0"):
        codec.stream_decoder(0)
    dec = codec.stream_decoder(3)
    with pytest.raises(ValueError, match="latents: expected 6 dimensions"):
        dec.push(np.zeros((1, 2, 2, 2, c), np.float32))
    with pytest.raises(ValueError, match=f"latents: expected {c} channels"):
        dec.push(np.zeros((1, 1, 1, 2, 2, c + 1), np.float32))
    with pytest.raises(ValueError, match="latents: expected a floating dtype"):
        dec.push(np.zeros((1, 1, 1, 2, 2, c), np.int32))
    with pytest.raises(ValueError, match=r"latents: expected at most 3 more latent frames .* got 4"):
        dec.push(np.zeros((1, 1, 4, 2, 2, c), np.float32))
    dec.push(np.zeros((1, 1, 2, 2, 2, c), np.float32))
    with pytest.raises(ValueError, match=r"latents: expected shape \[1, 1, \*, 2, 2, "):
        dec.push(np.zeros((1, 1, 1, 2, 4, c), np.float32))
    with pytest.raises(ValueError, match="total_latent_frames: expected all 3 latent frames pushed before flush"):
        dec.flush()
    dec.push(np.zeros((1, 1, 1, 2, 2, c), np.float32))
    with pytest.raises(ValueError, match=r"latents: expected at most 0 more latent frames .* got 1"):
        dec.push(np.zeros((1, 1, 1, 2, 2, c), np.float32))
    dec.flush()
    with pytest.raises(ValueError, match="latents: expected no push after flush"):
        dec.push(np.zeros((1, 1, 0, 2, 2, c), np.float32))
