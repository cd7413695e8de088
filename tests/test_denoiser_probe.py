"""jaxdrive.eval.denoiser_probe: the latent PSNR, its worked number, and a run's clean-data estimate
per level beside its baselines on both splits."""

import numpy as np
import pytest

from jaxdrive.eval.denoiser_probe import check_levels, latent_psnr, probe_run


def test_latent_psnr_worked_number_and_mask():
    target = np.zeros((1, 2, 3, 4, 4, 2))
    estimate = np.zeros_like(target)
    estimate[:, :, 1] = 0.2  # MSE 0.04 on frame 1: 10 log10(4 / 0.04) = 20 dB
    estimate[:, :, 2] = 5.0  # frame 2 is masked out
    mask = np.array([[False, True, False]])
    assert latent_psnr(estimate, target, mask) == pytest.approx(20.0)
    assert latent_psnr(target, target, mask) == float("inf")


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ((np.zeros((1, 2, 3, 4, 4, 2)), np.zeros((1, 2, 3, 4, 4, 1)), np.ones((1, 3), bool)), "estimate: expected"),
        ((np.zeros((1, 2, 3, 4, 4, 2)), np.zeros((1, 2, 3, 4, 4, 2)), np.ones((1, 2), bool)), "mask: expected [B, F]"),
        ((np.zeros((1, 2, 3, 4, 4, 2)), np.zeros((1, 2, 3, 4, 4, 2)), np.zeros((1, 3), bool)), "at least one frame"),
    ],
)
def test_latent_psnr_refuses_mismatched_inputs(args, message):
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("]", r"\]")):
        latent_psnr(*args)


@pytest.mark.parametrize("levels", [(), (0.0,), (1.5,), (0.5, -0.1)])
def test_check_levels_refuses_levels_outside_0_1(levels):
    with pytest.raises(ValueError, match=r"levels: expected noise levels in \(0, 1\]"):
        check_levels(levels)


def test_probe_of_an_untrained_residual_model_is_the_repeat_baseline(tiny_dit):
    """configs/tiny.py predicts the change from the newest given frame with a zero-initialised
    output: after its one step (EMA weights) its estimate at every level is that frame, on both
    splits, so the probe's estimate and its repeat baseline must agree; the levels, the windows
    and the splits come back as asked."""
    res = probe_run(tiny_dit, levels=(1.0, 0.1), batches=2)
    assert set(res) == {"train", "validation"}
    for split, r in res.items():
        assert r["windows"] == 4, (split, r)  # 2 batches of the run's 2 clips
        assert r["warp"] is None  # no warp control
        assert np.isfinite(r["repeat"])
        for level in (1.0, 0.1):
            assert r["levels"][level] == pytest.approx(r["repeat"], abs=0.01), (split, level, r)
        # the renders draw no token grid (about 1); the estimates (the given frame) the same
        assert 0.8 < r["grid_clean"] < 1.2, r
        assert r["grid"][1.0] == pytest.approx(r["grid"][0.1], abs=1e-3), r
        assert r["grid_warp"] is None
    # the splits are different clips: their baselines differ
    assert abs(res["train"]["repeat"] - res["validation"]["repeat"]) > 0.1


def test_probe_refuses_unknown_splits_and_batches_before_reading_the_run(tmp_path):
    with pytest.raises(ValueError, match="splits: expected names from"):
        probe_run(tmp_path / "no-run", splits=("test",))
    with pytest.raises(ValueError, match="batches"):
        probe_run(tmp_path / "no-run", batches=0)


def test_probe_of_an_untrained_warp_correction_is_the_warp_baseline(tiny_warp_dit):
    """A warp-guided model whose output corrects the warp (configs/world.py:control=warp's
    controls): one step in, its estimate is the warp at every level, and the warp baseline the
    probe reports is that same number, apart from repeating the last given frame."""
    res = probe_run(tiny_warp_dit, levels=(1.0,), batches=1, splits=("validation",))
    r = res["validation"]
    assert r["warp"] is not None and r["levels"][1.0] == pytest.approx(r["warp"], abs=0.01), r
    assert r["grid"][1.0] == pytest.approx(r["grid_warp"], abs=1e-3), r  # the warp's own grid
    assert abs(r["warp"] - r["repeat"]) > 0.05, r


def test_the_command_line_prints_the_psnr_and_the_token_grid_tables(tiny_warp_dit, capsys):
    from jaxdrive.eval.denoiser_probe import main

    assert main(["--workdir", str(tiny_warp_dit), "--levels", "1", "--batches", "1", "--splits", "validation"]) == 0
    out = capsys.readouterr().out
    psnr, grid = out.split("token grid of the decoded estimate")
    assert "| split | windows | level 1 | repeat | warp |" in psnr
    assert "| split | windows | level 1 | clean | warp |" in grid
    row = [line for line in grid.splitlines() if line.startswith("| validation |")]
    assert len(row) == 1 and len(row[0].split("|")) == 7, row  # split, windows, level 1, clean, warp
