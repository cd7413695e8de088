"""Frame fidelity (jaxdrive.eval.frames): worked PSNR / SSIM numbers and the baselines."""

import numpy as np
import pytest

from jaxdrive.eval.frames import FrameScores, clip_quality, noise_like, psnr, ssim


def _clip(seed=0, views=2, frames=5, hw=(24, 32)):
    """A smooth video in [-1, 1] whose content moves one pixel a frame."""
    rng = np.random.default_rng(seed)
    base = rng.uniform(-0.8, 0.8, (views, 1, hw[0] // 4, hw[1] // 4 + frames, 3)).repeat(4, 2).repeat(4, 3)
    return np.concatenate([base[:, :, :, f : f + hw[1]] for f in range(frames)], axis=1).astype(np.float32)


def test_psnr_worked_number_and_ssim_of_identical_images():
    a = np.zeros((1, 8, 8, 3), np.float32)
    b = a + 0.2  # in [0, 1] the error is 0.1: MSE 0.01 -> PSNR = -10 log10(0.01) = 20 dB
    assert float(psnr(a, b)[0]) == pytest.approx(20.0, abs=1e-4)
    x = _clip()[0]
    np.testing.assert_allclose(np.asarray(ssim(x, x)), 1.0, atol=1e-5)
    assert float(np.asarray(ssim(x, -x)).max()) < 0.2


def test_psnr_and_ssim_keep_leading_axes():
    v = _clip(views=2, frames=3)
    assert psnr(v, v * 0.9).shape == (2, 3) and ssim(v, v * 0.9).shape == (2, 3)


def test_clip_quality_scores_the_generated_frames_against_the_baselines():
    rec = _clip(frames=6)
    q = clip_quality(rec, rec, cond_frames=2, window=4)
    assert [r["kind"] for r in q["per_frame"]] == ["condition"] * 2 + ["generated"] * 4
    assert q["first_window"]["frames"] == [2, 3] and q["all_generated"]["frames"] == [2, 3, 4, 5]
    # a perfect generator: 100 dB (capped) and SSIM 1; the baselines are far below it
    assert q["first_window"]["psnr"] == 100.0 and q["first_window"]["ssim"] == pytest.approx(1.0, abs=1e-5)
    assert q["first_window"]["repeat_psnr"] < 40 and q["first_window"]["noise_psnr"] < q["first_window"]["repeat_psnr"]
    # the repeat baseline is exactly the last condition frame held still
    held = np.concatenate([rec[:, :2], np.repeat(rec[:, 1:2], 4, 1)], 1)
    q_held = clip_quality(held, rec, cond_frames=2)
    for row in q_held["per_frame"]:
        assert row["psnr"] == pytest.approx(row["repeat_psnr"]) and row["ssim"] == pytest.approx(row["repeat_ssim"])
    # a noise generator scores like the noise baseline, far below the perfect one
    q_noise = clip_quality(noise_like(rec, seed=0), rec, cond_frames=2)
    assert q_noise["all_generated"]["psnr"] == pytest.approx(q_noise["all_generated"]["noise_psnr"])


def test_clip_quality_rejects_bad_input():
    rec = _clip(frames=4)
    with pytest.raises(ValueError, match=r"recorded: expected the shape of generated \[2, 4, 24, 32, 3\], got"):
        clip_quality(rec, rec[:, :3], cond_frames=1)
    with pytest.raises(ValueError, match=r"cond_frames: expected fewer than the clip's 4 frames, got 4"):
        clip_quality(rec, rec, cond_frames=4)
    with pytest.raises(ValueError, match=r"window: expected more than cond_frames = 2 frames, got 2"):
        clip_quality(rec, rec, cond_frames=2, window=2)
    with pytest.raises(ValueError, match=r"generated: expected 4 or 5 dimensions"):
        clip_quality(rec[0, 0], rec[0, 0], cond_frames=1)


def test_frame_scores_part_by_part_equal_the_whole_clip_and_give_a_horizon_curve():
    rec = _clip(frames=9)
    gen = rec + np.linspace(0.0, 0.4, 9, dtype=np.float32)[None, :, None, None, None]  # drifts more each frame
    whole = clip_quality(gen, rec, cond_frames=2, window=5)
    parts = FrameScores(rec, cond_frames=2)
    for lo, hi in ((0, 2), (2, 5), (5, 6), (6, 9)):
        parts.add(gen[:, lo:hi])
    q = parts.result(window=5, every=3)
    for a, b in zip(q["per_frame"], whole["per_frame"], strict=True):
        assert a["kind"] == b["kind"] and {k: a[k] for k in a if k != "kind"} == pytest.approx(
            {k: b[k] for k in b if k != "kind"}, rel=1e-5
        )
    assert q["first_window"]["frames"] == whole["first_window"]["frames"] == [2, 3, 4]
    assert q["first_window"]["psnr"] == pytest.approx(whole["first_window"]["psnr"], rel=1e-5)
    assert [h["frames"] for h in q["horizon"]] == [[2, 3, 4], [5, 6, 7], [8]]
    # the drift grows, so quality falls along the horizon
    assert q["horizon"][0]["psnr"] > q["horizon"][1]["psnr"] > q["horizon"][2]["psnr"]
    assert q["horizon"][0]["psnr"] == pytest.approx(np.mean([whole["per_frame"][f]["psnr"] for f in (2, 3, 4)]))


def test_frame_scores_reject_bad_parts():
    rec = _clip(frames=4)
    scores = FrameScores(rec, cond_frames=1)
    with pytest.raises(
        ValueError,
        match=r"generated: expected the next frames \[V, n, H, W, 3\] of a clip shaped "
        r"\[2, 4, 24, 32, 3\] \(frames 0..3 left\), got shape \[2, 5, 24, 32, 3\]",
    ):
        scores.add(np.concatenate([rec, rec[:, :1]], 1))
    with pytest.raises(ValueError, match=r"generated: expected frames beyond the 1 given ones, got 1 frames"):
        scores.add(rec[:, :1]).result()
    with pytest.raises(ValueError, match=r"recorded: expected 5 dimensions"):
        FrameScores(rec[0], cond_frames=1)
