"""FID's parts against the reference (pytorch-fid): the Fréchet distance, streamed statistics and
the FID Inception network loaded from its weights file (random weights here: nothing is
downloaded; ``fid_reference`` says how pytorch-fid is imported beside the CPU torch wheel)."""

from __future__ import annotations

import numpy as np
import pytest

from jaxdrive.eval.fid import FeatureStats, frechet_distance

torch = pytest.importorskip("torch")


@pytest.fixture(scope="module")
def reference():
    from fid_reference import load_pytorch_fid

    load_pytorch_fid()
    from pytorch_fid.fid_score import calculate_frechet_distance

    return calculate_frechet_distance


def _stats(x):
    return x.mean(0), np.cov(x, rowvar=False)


def test_the_frechet_distance_equals_pytorch_fids_and_a_worked_number(reference):
    rng = np.random.default_rng(0)
    a = rng.normal(size=(300, 64))
    b = rng.normal(size=(200, 64)) @ rng.normal(size=(64, 64)) * 0.3 + 0.2
    ours, theirs = frechet_distance(*_stats(a), *_stats(b)), reference(*_stats(a), *_stats(b))
    assert ours == pytest.approx(theirs, rel=1e-6)
    assert frechet_distance(*_stats(a), *_stats(a)) == pytest.approx(0.0, abs=1e-8)
    # 1-D: (0 - 1)^2 + 1 + 4 - 2 sqrt(1 * 4) = 2
    assert frechet_distance([0.0], [[1.0]], [1.0], [[4.0]]) == pytest.approx(2.0)
    # fewer samples than features (rank-deficient covariances) still agree
    c, d = rng.normal(size=(20, 64)), rng.normal(size=(30, 64)) + 0.5
    assert frechet_distance(*_stats(c), *_stats(d)) == pytest.approx(reference(*_stats(c), *_stats(d)), rel=1e-5)
    with pytest.raises(ValueError, match=r"sigma2: expected shape \[64, 64\] \(mu1 has 64 features\), got \[3, 3\]"):
        frechet_distance(*_stats(a), np.zeros(64), np.eye(3))


def test_streamed_statistics_equal_the_one_shot_mean_and_covariance():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(257, 16)) * 3 + 100.0  # a large mean: the update must not lose it
    stats = FeatureStats(16)
    for lo in range(0, 257, 40):
        stats.add(x[lo : lo + 40])
    mean, cov = _stats(x)
    np.testing.assert_allclose(stats.mean, mean, rtol=1e-12)
    np.testing.assert_allclose(stats.cov, cov, rtol=1e-10, atol=1e-12)
    assert stats.count == 257
    assert stats.fid(FeatureStats(16).add(x)) == pytest.approx(0.0, abs=1e-8)
    with pytest.raises(ValueError, match="samples: expected at least 2 for a covariance, got 1"):
        FeatureStats(16).add(x[:1]).cov
    with pytest.raises(ValueError, match=r"features: expected \[N, 16\], got \[4, 3\]"):
        stats.add(np.zeros((4, 3)))


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    from fid_reference import random_fid_inception

    model, state = random_fid_inception(0)
    path = tmp_path_factory.mktemp("inception") / "pt_inception-random.pth"
    torch.save(state, path)
    return model, path


@pytest.mark.slow(seconds=6)
@pytest.mark.parametrize("hw", [(64, 96), (320, 360)])  # resized up and down to 299
def test_inception_features_match_pytorch_fid(weights, hw):
    from jaxdrive.eval.inception import load_fid_inception

    ref, path = weights
    images = np.random.default_rng(2).integers(0, 256, (2, *hw, 3)).astype(np.uint8)
    with torch.no_grad():  # pytorch-fid takes [0, 1] NCHW and returns pool3 [N, 2048, 1, 1]
        want = ref(torch.from_numpy(images).permute(0, 3, 1, 2).float() / 255.0)[0][:, :, 0, 0].numpy()
    model, params = load_fid_inception(path)
    got = np.asarray(model.features(params, images))
    assert got.shape == (2, 2048)
    assert np.abs(got - want).max() <= 1e-4 * np.abs(want).max()
    np.testing.assert_allclose(np.asarray(model.features(params, images.astype(np.float32))), got, rtol=1e-6)


def test_the_converted_safetensors_load_the_same_and_foreign_files_are_refused(weights, tmp_path, capsys):
    from jaxdrive.cli import main as cli
    from jaxdrive.eval.inception import load_fid_inception

    _, path = weights
    out = tmp_path / "inception.safetensors"
    assert cli(["convert", "inception", "--from", str(path), "--out", str(out)]) == 0
    a, b = load_fid_inception(path)[1], load_fid_inception(out)[1]
    for name in a:
        np.testing.assert_array_equal(np.asarray(a[name]["kernel"]), np.asarray(b[name]["kernel"]))
    state = torch.load(path, weights_only=True)
    other = tmp_path / "other.pth"
    torch.save({k: v for k, v in state.items() if not k.startswith("Mixed_7c")}, other)
    with pytest.raises(
        ValueError,
        match=r"^path .*other.pth: expected the FID Inception's tensor "
        r"'Mixed_7c.branch1x1.conv.weight'",
    ):
        load_fid_inception(other)
    wrong = tmp_path / "wrong.pth"
    torch.save({**state, "Mixed_5b.branch1x1.conv.weight": torch.zeros(64, 192, 3, 3)}, wrong)
    with pytest.raises(
        ValueError,
        match=r"tensor 'Mixed_5b.branch1x1.conv.weight': expected shape "
        r"\[64, 192, 1, 1\], got \[64, 192, 3, 3\]",
    ):
        load_fid_inception(wrong)
    cut = tmp_path / "cut.pth"
    cut.write_bytes(path.read_bytes()[:100_000])
    with pytest.raises(ValueError, match="^path: could not read .*cut.pth as a state dict"):
        load_fid_inception(cut)
    cut_st = tmp_path / "cut.safetensors"
    cut_st.write_bytes(out.read_bytes()[:100_000])
    with pytest.raises(ValueError, match="^path: .*cut.safetensors"):
        load_fid_inception(cut_st)
    assert cli(["convert", "inception", "--from", str(other), "--out", str(tmp_path / "x.safetensors")]) == 2
    assert "--from" in capsys.readouterr().err


@pytest.fixture(scope="module")
def i3d_weights(tmp_path_factory):
    """cd-fvd's ``InceptionI3d(400)`` (its pure-torch ``pytorch_i3d.py``, loaded by its path) with
    random weights and batch-norm statistics."""
    from fid_reference import load_cd_fvd_i3d

    module = load_cd_fvd_i3d()
    net = module.InceptionI3d(400, in_channels=3)
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for name, t in net.state_dict().items():
            if name.endswith("num_batches_tracked"):
                continue
            if name.endswith("conv3d.weight"):
                t.copy_(torch.randn(t.shape, generator=gen) * (2.0 / t[0].numel()) ** 0.5)
            elif name.endswith("running_var"):
                t.copy_(torch.rand(t.shape, generator=gen) + 0.5)
            elif name.endswith("bn.weight"):
                t.copy_(torch.rand(t.shape, generator=gen) * 0.5 + 0.75)
            else:
                t.copy_(torch.randn(t.shape, generator=gen) * 0.1)
    net.eval()
    path = tmp_path_factory.mktemp("i3d") / "i3d_random_400.pt"
    torch.save(net.state_dict(), path)
    return net, path


@pytest.mark.optimized_xla
@pytest.mark.slow(seconds=12)
def test_i3d_logits_match_cd_fvd(i3d_weights, tmp_path):
    from jaxdrive.cli import main as cli
    from jaxdrive.eval.i3d import load_i3d

    net, path = i3d_weights
    videos = np.random.default_rng(3).integers(0, 256, (2, 16, 48, 80, 3)).astype(np.uint8)
    # cd-fvd's preprocess_i3d: frames resized to 224 x 224 (bilinear, no antialias), [-1, 1], NCTHW
    x = torch.from_numpy(videos).float().flatten(end_dim=1).permute(0, 3, 1, 2)
    x = torch.nn.functional.interpolate(x, size=(224, 224), mode="bilinear", align_corners=False)
    x = 2.0 * x.view(2, 16, 3, 224, 224).transpose(1, 2) / 255.0 - 1
    with torch.no_grad():
        want = net(x).numpy()
    model, params = load_i3d(path)
    got = np.asarray(model.logits(params, videos))
    assert got.shape == (2, 400)
    assert np.abs(got - want).max() <= 1e-4 * np.abs(want).max()
    out = tmp_path / "i3d.safetensors"
    assert cli(["convert", "i3d", "--from", str(path), "--out", str(out)]) == 0
    np.testing.assert_array_equal(
        np.asarray(load_i3d(out)[1]["logits"]["shift"]), np.asarray(params["logits"]["shift"])
    )
    with pytest.raises(ValueError, match=r"^path .*: expected the I3D tensor 'Conv3d_1a_7x7.conv3d.weight'"):
        load_i3d(_other_network(tmp_path))
    with pytest.raises(ValueError, match=r"videos: expected at least 9 frames \(FVD uses 16\), got 4"):
        model.logits(params, videos[:, :4])


def _other_network(tmp_path):
    """A state dict of another network (the FID Inception's first convolution)."""
    path = tmp_path / "other.pth"
    torch.save({"Conv2d_1a_3x3.conv.weight": torch.zeros(32, 3, 3, 3)}, path)
    return path


def test_features_extracted_sharded_over_the_mesh_equal_the_single_device_ones():
    import jax
    from jax.sharding import PartitionSpec as P

    from jaxdrive.eval.features import extract, stats_of

    mesh = jax.make_mesh((4, 2), ("data", "seq"))
    seen = []

    features = jax.jit(lambda scale, x: x.reshape(x.shape[0], -1)[:, :3] * scale)

    def fn(scale, x):
        seen.append(getattr(x, "sharding", None))
        return features(scale, x)

    items = np.random.default_rng(4).normal(size=(13, 2, 5)).astype(np.float32)
    want = items.reshape(13, -1)[:, :3] * 2.0
    np.testing.assert_allclose(extract(fn, 2.0, items, batch_size=3, mesh=mesh), want, rtol=1e-6)
    assert len(seen) == 4 and all(s.spec == P(("data",)) and s.mesh == mesh for s in seen)  # 4 + 4 + 4 + 1 padded
    np.testing.assert_allclose(extract(fn, 2.0, items, batch_size=5), want, rtol=1e-6)
    stats = stats_of(fn, 2.0, items, dim=3, batch_size=2, mesh=mesh)
    np.testing.assert_allclose(stats.cov, np.cov(want, rowvar=False), rtol=1e-5)
