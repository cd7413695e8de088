"""The DiT's formulas against their references: timestep and sin-cos embeddings and 3D RoPE
against diffusers' functions, Fourier features by a worked number, the host initialisers against
the JAX ones, the token-layout helpers, HTFT and its FIFO buffer, and the caption tokenizer."""

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdrive.models.embeddings import apply_rope, fourier_features, rope_3d, sincos_3d, timestep_embedding
from jaxdrive.models.htft import HTFT, buffer_init, buffer_push, buffer_select
from jaxdrive.models.params import Init, host_init
from jaxdrive.models.tokens import from_sequence, to_sequence


def test_timestep_and_sincos_match_diffusers():
    torch = pytest.importorskip("torch")
    emb = pytest.importorskip("diffusers.models.embeddings")
    t = np.array([0.0, 3.5, 999.0], np.float32)
    want = emb.get_timestep_embedding(torch.tensor(t), 64, flip_sin_to_cos=True, downscale_freq_shift=0).numpy()
    np.testing.assert_allclose(timestep_embedding(t, 64), want, atol=1e-4)  # sin of ~1000 rad in fp32
    want = emb.get_3d_sincos_pos_embed(32, (5, 3), 4, spatial_interpolation_scale=1.875).numpy()
    np.testing.assert_allclose(sincos_3d(4, 3, 5, 32, spatial_scale=1.875), want, atol=1e-6)


def test_rope_3d_matches_diffusers_including_the_crop_region():
    torch = pytest.importorskip("torch")
    emb = pytest.importorskip("diffusers.models.embeddings")
    cos, sin = emb.get_3d_rotary_pos_embed(16, ((0, 0), (3, 4)), (3, 4), 2)
    c, s = rope_3d(2, 3, 4, 16, base=(3, 4))
    np.testing.assert_allclose(c.reshape(-1, 16), cos.numpy(), atol=1e-6)
    np.testing.assert_allclose(s.reshape(-1, 16), sin.numpy(), atol=1e-6)
    x = torch.randn(1, 1, 24, 16)
    want = emb.apply_rotary_emb(x, (cos, sin)).numpy()
    np.testing.assert_allclose(
        apply_rope(jnp.asarray(x.numpy()), c.reshape(-1, 16), s.reshape(-1, 16)), want, atol=1e-5
    )
    # positions spread over the training grid when the grid differs (3 x 5 on a 3 x 4 base)
    c5, _ = rope_3d(1, 3, 5, 16, base=(3, 4))
    assert not np.allclose(c5[0, 1], rope_3d(1, 3, 5, 16)[0][0, 1])


def test_fourier_features_worked_number():
    f = fourier_features(jnp.array([[0.5]]), 2, temperature=100.0)
    # frequencies 100^(0/2) = 1 and 100^(1/2) = 10: [x, sin x, cos x, sin 10x, cos 10x]
    np.testing.assert_allclose(f[0], [0.5, np.sin(0.5), np.cos(0.5), np.sin(5.0), np.cos(5.0)], atol=1e-6)


@pytest.mark.parametrize(
    "init",
    [
        Init("zeros"),
        Init("ones"),
        Init("normal", 0.5),
        Init("xavier", fan_in_axes=2),
        Init("lecun", fan_in_axes=3),
        Init("lecun_truncated", fan_in_axes=3),
    ],
)
def test_host_initialisers_match_the_jax_ones(init):
    shape = (3, 3, 40, 50)
    a = np.asarray(init(jax.random.PRNGKey(0), shape))
    b = init.host(np.random.default_rng(0), shape, len(shape))
    if init.kind in ("zeros", "ones"):
        np.testing.assert_array_equal(a, b)
        return
    assert a.shape == b.shape == shape
    np.testing.assert_allclose(a.std(), b.std(), rtol=0.05)
    if init.kind == "xavier":
        lim = np.sqrt(6 / (3 * 3 + 40 * 50))  # fan in 3 x 3, fan out 40 x 50
        assert np.abs(b).max() <= lim and np.abs(b).max() > 0.95 * lim
    # scanned layers: the leading axis does not change the fans
    c = init.host(np.random.default_rng(0), (7,) + shape, len(shape))
    np.testing.assert_allclose(c.std(), b.std(), rtol=0.05)


def test_truncated_lecun_is_flax_lecun_normal():
    # the VAE's kernels: in JAX bit for bit flax's initialiser; on the host the same truncation
    init, shape = Init("lecun_truncated", fan_in_axes=3), (3, 3, 40, 50)
    key = jax.random.PRNGKey(3)
    np.testing.assert_array_equal(init(key, shape), nn.initializers.lecun_normal()(key, shape))
    b = init.host(np.random.default_rng(0), shape, len(shape))
    bound = 2 / np.sqrt(3 * 3 * 40) / 0.87962566103423978  # 2 std of the untruncated normal
    assert np.abs(b).max() <= bound and np.abs(b).max() > 0.99 * bound
    np.testing.assert_allclose(b.std(), 1 / np.sqrt(3 * 3 * 40), rtol=0.02)


def test_sequence_layout_round_trip():
    x = jnp.arange(2 * 3 * 4 * 5 * 2 * 1).reshape(2, 3, 4, 5, 2, 1)
    seq = to_sequence(x, (2, 1, 3))  # [B, S F V, H, Dh], S major
    assert seq.shape == (2, 60, 2, 1)
    np.testing.assert_array_equal(seq[0, 1, :, 0], x[0, 0, 0, 1, :, 0])  # token s F V + f V + v: (0, 0, 1)
    np.testing.assert_array_equal(from_sequence(seq, x.shape, (2, 1, 3)), x)


def test_htft_starts_as_identity_and_attends_to_the_buffer():
    f = jax.random.normal(jax.random.PRNGKey(0), (2, 1, 4, 3, 16))
    buf = buffer_init({5: (2, 4, 3, 16)}, size=10, steps=2)
    frames = [jax.random.normal(jax.random.PRNGKey(i + 1), (2, 2, 4, 3, 16)) for i in range(13)]
    for k, fr in enumerate(frames[:6]):
        buf = buffer_push(buf, {5: fr})
    assert buf["data"][5].shape == (2, 2, 10, 4, 3, 16)  # [steps, B, N, S, V, D], preallocated
    past, mask = buffer_select(buf, (-1, -5, -10))
    np.testing.assert_array_equal(past[5][:, :, 0], frames[5])  # every step's features of frame -1
    np.testing.assert_array_equal(past[5][:, :, 1], frames[1])
    np.testing.assert_array_equal(mask, [[True, True, False]] * 2)  # only 6 frames pushed so far
    for fr in frames[6:]:  # 13 pushed: the ring wrapped around
        buf = buffer_push(buf, {5: fr})
    past, mask = buffer_select(buf, (-1, -5, -10))
    for i, o in enumerate((-1, -5, -10)):
        np.testing.assert_array_equal(past[5][:, :, i], frames[13 + o])
    assert bool(mask.all()) and buf["data"][5].shape[2] == 10
    mod = HTFT(16, 2, 8, groups=4)
    p0, m0 = past[5][0], mask
    variables = nn.unbox(host_init(mod, f, p0, m0))
    apply = jax.jit(mod.apply)
    np.testing.assert_array_equal(apply(variables, f, p0, m0), f)  # zero-initialised Linear
    trained = jax.tree_util.tree_map(lambda x: x + 0.1, variables)
    out = apply(trained, f, p0, m0)
    assert float(jnp.abs(out - f).max()) > 1e-3
    # an empty slot is not attended to: its content does not matter
    m1 = m0.at[:, 2].set(False)
    np.testing.assert_allclose(apply(trained, f, p0.at[:, 2].set(100.0), m1), apply(trained, f, p0, m1), atol=1e-6)
    with pytest.raises(ValueError, match=r"offsets: expected offsets in \[-10, -1\]"):
        buffer_select(buf, (-11,))


def test_caption_tokenizer_reads_the_template_fields():
    from jaxdrive.data.schema import caption
    from jaxdrive.data.text import caption_fields, tokenize_captions

    cap = caption(sensor="6 surround cameras", location="boston-seaport", season="winter", daytime="night")
    assert caption_fields(cap) == [
        (0, "6"),
        (0, "surround"),
        (0, "cameras"),
        (1, "boston"),
        (1, "seaport"),
        (2, "winter"),
        (3, "night"),
    ]
    assert caption_fields("a sunny road") == [(4, "a"), (4, "sunny"), (4, "road")]
    ids, mask = tokenize_captions([cap, cap.replace("winter", "summer"), "x"], vocab=4096, max_len=8)
    assert ids.shape == (3, 8) and ids.dtype == np.int32 and mask.sum(1).tolist() == [7, 7, 1]
    assert (ids[0] != ids[1]).sum() == 1 and ((ids >= 0) & (ids < 4096)).all()
    np.testing.assert_array_equal(tokenize_captions([cap], vocab=4096, max_len=8)[0][0], ids[0])  # stable
    # the season's token lies in the season field's id range
    buckets = 4095 // 5
    assert 1 + 2 * buckets <= ids[0, 5] < 1 + 3 * buckets


def test_precompute_t5_without_transformers_is_a_clear_error(monkeypatch, tmp_path):
    import sys

    from jaxdrive.data.text import precompute_t5

    monkeypatch.setitem(sys.modules, "transformers", None)
    with pytest.raises(ImportError, match="needs the packages 'transformers' and 'torch'"):
        precompute_t5(["a"], tmp_path)


@pytest.fixture
def fake_transformers(monkeypatch):
    """A stand-in for transformers' tokenizer and T5 encoder: token i of a caption's words has id
    i + 1, the encoder returns the id in every feature (masked by the attention mask)."""
    import sys
    import types

    torch = pytest.importorskip("torch")

    class Tok:
        @classmethod
        def from_pretrained(cls, path, **kw):
            assert kw.get("local_files_only")
            return cls()

        def __call__(self, texts, padding, max_length, truncation, add_special_tokens, return_tensors):
            ids = torch.zeros(len(texts), max_length, dtype=torch.long)
            att = torch.zeros(len(texts), max_length, dtype=torch.long)
            for i, t in enumerate(texts):
                n = min(len(t.split()), max_length)
                ids[i, :n] = torch.arange(1, n + 1)
                att[i, :n] = 1
            return types.SimpleNamespace(input_ids=ids, attention_mask=att)

    class Enc(torch.nn.Module):
        config = types.SimpleNamespace(d_model=3)

        @classmethod
        def from_pretrained(cls, path, **kw):
            assert kw.get("use_safetensors") and kw.get("local_files_only")
            return cls()

        def forward(self, ids, attention_mask):
            return (ids[..., None].float().repeat(1, 1, 3) * attention_mask[..., None],)

    fake = types.ModuleType("transformers")
    fake.AutoTokenizer, fake.T5EncoderModel = Tok, Enc
    monkeypatch.setitem(sys.modules, "transformers", fake)


def test_precompute_t5_pads_batches_and_masks(fake_transformers, tmp_path):
    """The batching, padding and mask plumbing around transformers' T5 classes."""
    from jaxdrive.data.text import precompute_t5

    emb, mask = precompute_t5(["a b c", "d", "e f"], tmp_path, max_length=4, batch_size=2)
    assert emb.shape == (3, 4, 3) and emb.dtype == np.float32
    np.testing.assert_array_equal(mask, [[1, 1, 1, 0], [1, 0, 0, 0], [1, 1, 0, 0]])
    np.testing.assert_array_equal(emb[0, :, 0], [1, 2, 3, 0])


def test_text_embed_command_writes_the_captions_of_a_dataset(fake_transformers, tmp_path):
    from jaxdrive.cli import main

    data, enc, out = tmp_path / "synth", tmp_path / "t5", tmp_path / "emb.npz"
    enc.mkdir()
    assert (
        main(
            [
                "data",
                "synth",
                "--out",
                str(data),
                "--scenes",
                "3",
                "--frames",
                "5",
                "--height",
                "16",
                "--width",
                "32",
                "--val-fraction",
                "0",
            ]
        )
        == 0
    )
    assert (
        main(
            [
                "data",
                "text-embed",
                "--dataset",
                str(data),
                "--encoder",
                str(enc),
                "--out",
                str(out),
                "--max-length",
                "40",
            ]
        )
        == 0
    )
    got = np.load(out)
    caps = list(got["captions"])
    assert 1 <= len(caps) <= 3 and caps == sorted(set(caps)) and caps[0].startswith("This is a driving scene")
    assert got["embeddings"].shape == (len(caps), 40, 3) and got["mask"].shape == (len(caps), 40)
    assert got["mask"][0].sum() == len(caps[0].split())


def test_dense_flattens_tokens_and_its_bias_gradient_is_exact_single_and_sharded():
    """Dense runs its matmul on [tokens, features] when only the batch axis is sharded, and its bias
    gradient is a contraction with ones: the same output and gradients as the plain 5D formula."""
    from jax.sharding import AxisType, NamedSharding
    from jax.sharding import PartitionSpec as P

    from jaxdrive.models.layers import Dense

    x = jax.random.normal(jax.random.key(0), (4, 3, 8, 2, 16))
    ct = jax.random.normal(jax.random.key(1), (4, 3, 8, 2, 24))
    layer = Dense(24, ("embed", "mlp"))
    params = layer.init(jax.random.key(2), x)
    plain = lambda p, x: jnp.einsum("abcdn,nu->abcdu", x, p["params"]["kernel"]) + p["params"]["bias"]
    loss = lambda f: jax.jit(jax.value_and_grad(lambda p, x: jnp.sum(f(p, x) * ct), argnums=(0, 1)))
    want, (wp, wx) = loss(plain)(nn.unbox(params), x)
    got, (gp, gx) = loss(lambda p, x: layer.apply(p, x))(params, x)
    assert abs(float(got - want)) <= 1e-4 * abs(float(want))
    np.testing.assert_allclose(nn.unbox(gp)["params"]["bias"], wp["params"]["bias"], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(nn.unbox(gp)["params"]["kernel"], wp["params"]["kernel"], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(gx, wx, rtol=1e-5, atol=1e-5)
    for shape, spec in (
        ((4, 1, 2, 1), P(("data", "fsdp"), None, None, None, None)),  # batch only: flat
        ((2, 1, 4, 1), P(("data", "fsdp"), None, "seq", None, None)),
    ):  # tokens too: 5D
        mesh = jax.make_mesh(shape, ("data", "fsdp", "seq", "tensor"), axis_types=(AxisType.Explicit,) * 4)
        with jax.set_mesh(mesh):
            xs = jax.device_put(x, NamedSharding(mesh, spec))
            got, (gp, gx) = loss(lambda p, x: layer.apply(p, x))(params, xs)
        assert abs(float(got - want)) <= 1e-4 * abs(float(want))
        np.testing.assert_allclose(nn.unbox(gp)["params"]["bias"], wp["params"]["bias"], rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(gx, wx, rtol=1e-5, atol=1e-5)
