"""``jaxdrive eval``: horizon buckets, the per-bucket scores (PSNR / SSIM, FID and FVD through
their feature functions) and the command's outputs on a tiny run."""

from __future__ import annotations

import json

import numpy as np
import pytest

from jaxdrive.eval.compare import parse_buckets, score


def test_horizon_buckets_default_to_thirds_and_must_lie_in_the_generated_frames():
    assert parse_buckets(None, 2, 26) == [(2, 10), (10, 18), (18, 26), (2, 26)]  # + the whole span
    assert parse_buckets("2-12,13-25", 2, 26) == [(2, 13), (13, 26), (2, 26)]
    assert parse_buckets("2-25", 2, 26) == [(2, 26)]
    with pytest.raises(
        ValueError,
        match=r"^buckets: expected ranges within the generated frames 2-25, got 13-40 "
        r"\(clips shorter than the horizon buckets\)",
    ):
        parse_buckets("2-12,13-40", 2, 26)
    with pytest.raises(ValueError, match="^buckets: expected ranges like 2-12,13-24, got 'early'"):
        parse_buckets("early", 2, 26)


def _colour_features(images):
    """A stand-in feature function: each image's mean colour and spread (what FID needs of one)."""
    x = np.asarray(images, np.float64).reshape(len(images), -1, 3)
    return np.concatenate([x.mean(1), x.std(1)], 1)


def test_scores_are_perfect_for_the_recorded_clip_and_fall_for_another():
    rng = np.random.default_rng(0)
    recorded = np.clip(rng.normal(size=(2, 2, 20, 16, 16, 3)) * 0.3, -1, 1).astype(np.float32)
    buckets = [(2, 18), (18, 20)]
    kw = dict(fid_features=_colour_features, fvd_features=lambda v: _colour_features(v.reshape(len(v), -1, 3)))
    same = score(recorded, recorded, buckets, **kw)
    assert same["2-17"]["psnr"] == 100.0 and same["2-17"]["ssim"] == pytest.approx(1.0, abs=1e-5)
    assert same["2-17"]["fid"] == pytest.approx(0.0, abs=1e-6) and same["2-17"]["fvd"] == pytest.approx(0.0, abs=1e-6)
    assert len(same["2-17"]["fid_per_view"]) == 2
    assert same["18-19"]["fvd"] is None  # 2 frames: no 16-frame window
    brighter = np.clip(recorded + 0.4, -1, 1)
    other = score(brighter, recorded, buckets, **kw)
    assert other["2-17"]["psnr"] < 20 and other["2-17"]["fid"] > 0.05 and other["2-17"]["fvd"] > 0.05


@pytest.mark.optimized_xla  # its time is running the sampler and the scores, not compiling
@pytest.mark.slow(seconds=19)
def test_eval_scores_strategies_and_writes_its_outputs(tiny_dit, tmp_path, capsys):
    from jaxdrive.cli import main as cli

    out = tmp_path / "eval"
    assert (
        cli(
            [
                "eval",
                "--workdir",
                str(tiny_dit),
                "--strategies",
                "rollout",
                "--clips",
                "2",
                "--frames",
                "13",
                "--steps",
                "1",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "| rollout | 2-5 |" in printed and "quality_vs_horizon.png" in printed
    report = json.loads((out / "eval.json").read_text())
    buckets = report["strategies"]["rollout"]["buckets"]
    assert list(buckets) == ["2-5", "6-8", "9-12", "2-12"] and report["clips"] == 2 and report["views"] == 6
    repeat = report["strategies"]["repeat frame 1"]["buckets"]  # the baseline: the last given frame held
    assert list(repeat) == list(buckets) and all(0 < b["ssim"] <= 1 for b in repeat.values())
    assert all(np.isfinite(b["psnr"]) and 0 < b["ssim"] <= 1 for b in buckets.values())
    assert (out / "eval.md").read_text().startswith("| strategy | frames | PSNR | SSIM |")
    assert (out / "quality_vs_horizon.png").stat().st_size > 1000
    for args, message in (
        (["--clips", "1", "--inception", str(tmp_path / "x.pth")], "--clips: expected at least 2 with --inception"),
        (["--frames", "40"], "--frames: expected at most 21 frames"),
        (["--strategies", "rollout,sideways"], "--strategies: expected names from rollout"),
        (["--inception", str(tmp_path / "missing.pth")], "--inception: expected a weights file"),
    ):
        base = {"--clips": "2", "--frames": "13"}
        for k, v in zip(args[::2], args[1::2]):
            base[k] = v
        argv = ["eval", "--workdir", str(tiny_dit), "--steps", "1", "--out", str(tmp_path / "no")]
        for k, v in base.items():
            argv += [k, v]
        assert cli(argv) == 2, args
        assert message in capsys.readouterr().err, message


@pytest.mark.slow(seconds=10)
def test_eval_scores_a_folder_of_mp4s_against_the_dataset(clips21, segmenter_run, tmp_path, capsys):
    from jaxdrive.cli import main as cli
    from jaxdrive.data.tfds_io import open_source
    from jaxdrive.data.transforms import sample_clip
    from jaxdrive.media import write_mp4

    source = open_source(clips21, "train")
    clips = [sample_clip(source[i], size=(32, 56), frames=13)["video"] for i in range(2)]
    for i, video in enumerate(clips):  # the recorded clips themselves, through H.264
        write_mp4(tmp_path / "same" / f"clip{i}" / "sample.mp4", video)
        write_mp4(tmp_path / "swapped" / f"clip{i}" / "sample.mp4", clips[1 - i])
    scores = {}
    for name in ("same", "swapped"):
        out = tmp_path / f"eval_{name}"
        assert (
            cli(
                [
                    "eval",
                    "--videos",
                    str(tmp_path / name),
                    "--data",
                    str(clips21),
                    "--split",
                    "train",
                    "--given",
                    "2",
                    "--segmenter",
                    str(segmenter_run),
                    "--out",
                    str(out),
                ]
            )
            == 0
        )
        report = json.loads((out / "eval.json").read_text())
        assert report["clips"] == 2 and report["frames"] == 13 and report["views"] == 6
        scores[name] = report["strategies"]["videos"]["buckets"]
        ceiling = report["recorded_controllability"]
    assert "| videos | 2-5 |" in capsys.readouterr().out
    for span, row in scores["same"].items():
        assert row["psnr"] > 30 and row["miou"] > ceiling[span]["miou"] - 0.1, (span, row)
        assert scores["swapped"][span]["psnr"] < row["psnr"] - 10 and scores["swapped"][span]["miou"] < row["miou"]
    for args, message in (
        (["--videos", str(tmp_path / "none"), "--data", str(clips21)], "--videos: expected a folder with .mp4 files"),
        (["--videos", str(tmp_path / "same"), "--workdir", str(tmp_path)], "--workdir / --videos: expected one"),
        (
            ["--videos", str(tmp_path / "same"), "--data", str(clips21), "--split", "train", "--given", "13"],
            "--given: expected fewer than the videos' 13 frames, got 13",
        ),
        (["--videos", str(tmp_path / "same")], "--data: expected the dataset the videos continue"),
    ):
        assert cli(["eval", *args, "--out", str(tmp_path / "no")]) == 2, args
        assert message in capsys.readouterr().err, message


def test_eval_merges_strategies_of_different_runs_into_one_table(tmp_path, capsys):
    from jaxdrive.cli import main as cli
    from jaxdrive.eval.compare import write_outputs

    row = lambda psnr, a, b: {"frames": [a, b], "psnr": psnr, "ssim": 0.5, "miou": 0.2}
    run = lambda psnr: {
        "seconds": 1.0,
        "sequential_sampler_calls": 3,
        "peak_device_bytes": 2**20,
        "buckets": {"2-5": row(psnr, 2, 5), "6-8": row(psnr - 1, 6, 8)},
    }
    ceiling = {"2-5": {"frames": [2, 5], "miou": 0.6}, "6-8": {"frames": [6, 8], "miou": 0.6}}
    meta = {"clips": 2, "frames": 9, "views": 6, "segmenter": "seg", "shuffle_boxes": False, "split": None}
    write_outputs(
        {"rollout": run(20.0), "repeat frame 1": run(15.0)},
        tmp_path / "a",
        meta={**meta, "workdir": "runs/mila3"},
        ceiling=ceiling,
    )
    write_outputs(
        {"rollout": run(18.0), "streaming": run(19.0), "repeat frame 1": run(15.0)},
        tmp_path / "b",
        meta={**meta, "workdir": "runs/stage1"},
        ceiling=ceiling,
    )
    write_outputs({"rollout": run(18.0)}, tmp_path / "c", meta={**meta, "clips": 4, "workdir": "runs/x"})
    out = tmp_path / "all"
    assert cli(["eval", "--merge", f"{tmp_path / 'a'},{tmp_path / 'b'}", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "| rollout (mila3) | 2-5 | 20.000 |" in printed and "| streaming (stage1) | 6-8 | 18.000 |" in printed
    assert "| recorded frames | 2-5 | - | - | 0.600 | - | - |" in printed
    merged = json.loads((out / "eval.json").read_text())
    assert list(merged["strategies"]) == [
        "rollout (mila3)",
        "rollout (stage1)",
        "streaming (stage1)",
        "repeat frame 1",
    ]  # the clips' baseline, once
    assert (out / "quality_vs_horizon.png").stat().st_size > 1000
    for dirs, message in (
        (f"{tmp_path / 'a'},{tmp_path / 'c'}", "--merge: expected the same clips in every eval.json"),
        (f"{tmp_path / 'a'}", "--merge: expected at least 2 output folders"),
        (f"{tmp_path / 'a'},{tmp_path / 'none'}", "--merge: expected eval.json of jaxdrive eval"),
    ):
        assert cli(["eval", "--merge", dirs, "--out", str(tmp_path / "no")]) == 2, dirs
        assert message in capsys.readouterr().err, message


def test_eval_of_a_warp_guided_model_warps_along_the_recorded_poses(tiny_warp_dit, tmp_path, capsys):
    """Without --routes a warp-guided run is sampled along each clip's recorded poses (it was refused:
    "needs the poses to warp along"); its untrained correction gives the warp, not the held frame."""
    from jaxdrive.cli import main as cli

    out = tmp_path / "eval"
    argv = ["eval", "--workdir", str(tiny_warp_dit), "--strategies", "rollout", "--clips", "2", "--frames", "13"]
    assert cli([*argv, "--steps", "1", "--out", str(out)]) == 0, capsys.readouterr().err
    report = json.loads((out / "eval.json").read_text())
    rollout, repeat = (report["strategies"][n]["buckets"]["2-12"]["psnr"] for n in ("rollout", "repeat frame 1"))
    assert np.isfinite(rollout) and abs(rollout - repeat) > 0.05, (rollout, repeat)


@pytest.mark.optimized_xla  # its time is running the sampler and the scores, not compiling
@pytest.mark.slow(seconds=33)
def test_eval_sweeps_guidance_scales_into_one_table_that_merges(tiny_dit, tmp_path, capsys, monkeypatch):
    """``--cfg 1,2`` scores the strategy at each scale (rows ``rollout@cfgS``), with the route
    guided on its own (``--cfg-route``); every row records its guidance, and ``--merge`` takes it.
    (The 1-step fixture's condition pathways are still at their zero init, so the scales cannot
    change its samples: what reaches the sampler is read where the windows build its guidance.)"""
    import shutil

    import jaxdrive.generate.windows as windows
    from jaxdrive.cli import main as cli

    seen, real = [], windows.sampler_guidance

    def spy(cond, names, batch, scale, controls=()):
        seen.append((scale, tuple(controls), tuple(sorted(names))))
        return real(cond, names, batch, scale, controls)

    monkeypatch.setattr(windows, "sampler_guidance", spy)
    out = tmp_path / "sweep"
    assert (
        cli(
            [
                "eval",
                "--workdir",
                str(tiny_dit),
                "--strategies",
                "rollout",
                "--clips",
                "2",
                "--frames",
                "9",
                "--steps",
                "1",
                "--cfg",
                "1,2",
                "--cfg-route",
                "3",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "| rollout@cfg1 | 2-3 |" in printed and "| rollout@cfg2 | 2-3 |" in printed
    report = json.loads((out / "eval.json").read_text())
    rows = report["strategies"]
    assert list(rows) == ["rollout@cfg1", "rollout@cfg2", "repeat frame 1"]
    assert rows["rollout@cfg1"]["guidance"] == {"cfg": 1.0, "cfg_route": 3.0}
    assert rows["rollout@cfg2"]["guidance"] == {"cfg": 2.0, "cfg_route": 3.0}
    assert (report["cfg"], report["cfg_route"], report["cfg_boxes"]) == ([1.0, 2.0], 3.0, None)
    names = ("boxes", "camera", "text", "waypoints")  # the tiny run's conditions with a null
    assert {(1.0, (("route", 3.0),), names), (2.0, (("route", 3.0),), names)} <= set(seen)
    assert all(np.isfinite(b["psnr"]) for r in rows.values() for b in r["buckets"].values())
    shutil.copytree(out, tmp_path / "again")
    assert cli(["eval", "--merge", f"{out},{tmp_path / 'again'}", "--out", str(tmp_path / "merged")]) == 0
    merged = json.loads((tmp_path / "merged" / "eval.json").read_text())["strategies"]
    assert list(merged) == ["rollout@cfg1 (run)", "rollout@cfg2 (run)", "repeat frame 1"]  # rows named by run
    assert merged["rollout@cfg2 (run)"]["guidance"] == {"cfg": 2.0, "cfg_route": 3.0}
