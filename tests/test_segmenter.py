"""Controllability: exact class masks from the synthetic world's instance ids, the IoU counts, the
segmentation evaluator's training, and ``jaxdrive eval --segmenter`` with the shuffled-boxes control."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from jaxdrive.data.resize import resize_crop_labels, resize_plan
from jaxdrive.eval.segmenter import CLASSES, class_masks, confusion, summary

CONFIG = str(Path(__file__).resolve().parents[1] / "configs" / "segmenter.py")  # segmenter_run: conftest


def test_class_masks_give_each_pixel_the_class_of_the_box_that_drew_it():
    inst = np.array([[[[7, 7, -1], [3, 9, 3]]]])  # [V=1, F=1, H=2, W=3]
    ids = np.array([[3, 7, 9]])  # [F=1, N=3]
    classes = np.array([[8, 0, 2]])  # pedestrian, car, construction_vehicle
    valid = np.array([[True, True, False]])  # track 9's box is not valid this frame
    out = class_masks(inst, ids, classes, valid)
    np.testing.assert_array_equal(out, [[[[1, 1, 0], [9, 0, 9]]]])
    assert CLASSES[1] == "car" and CLASSES[9] == "pedestrian"
    with pytest.raises(ValueError, match=r"instance_ids: expected \[..., V, F, H, W\] with boxes \[..., F, N\]"):
        class_masks(inst, ids[:, :2], classes, valid)


def test_labels_are_resized_to_the_nearest_pixel_as_the_frames_are():
    labels = np.arange(4 * 6).reshape(4, 6)
    same = resize_plan((4, 6), (4, 6))
    np.testing.assert_array_equal(resize_crop_labels(labels, same), labels)
    half = resize_plan((4, 6), (2, 3))  # every second pixel, from the centres
    np.testing.assert_array_equal(resize_crop_labels(labels, half), labels[1::2, 1::2])
    crop = resize_plan((4, 6), (4, 4))  # cover (no resize), centre crop of width 4
    np.testing.assert_array_equal(resize_crop_labels(labels[None], crop)[0], labels[:, 1:5])


def test_iou_counts_and_miou_worked_numbers():
    truth = np.array([[0, 0, 1, 1], [0, 2, 2, 0]])
    pred = np.array([[0, 1, 1, 1], [0, 2, 0, 0]])
    counts = confusion(pred, truth, num_classes=3)
    np.testing.assert_array_equal(counts, [[3, 1, 0], [0, 2, 0], [1, 0, 1]])
    # class 1: inter 2, union 3; class 2: inter 1, union 2; background: inter 3, union 5
    s = summary(np.pad(counts, ((0, len(CLASSES) - 3), (0, len(CLASSES) - 3))))
    assert s["per_class"]["car"] == pytest.approx(2 / 3, abs=1e-4)
    assert s["per_class"]["truck"] == pytest.approx(1 / 2, abs=1e-4)
    assert s["per_class"]["background"] == pytest.approx(3 / 5, abs=1e-4)
    assert s["per_class"]["bus"] is None  # in neither: left out of the mean
    assert s["miou"] == pytest.approx((2 / 3 + 1 / 2) / 2) and s["pixel_accuracy"] == pytest.approx(6 / 8)
    # A class only predicted counts as IoU 0: predicting objects that are not there costs.
    assert summary(confusion(np.array([3]), np.array([0])))["miou"] == 0.0
    # counts of parts add up to the counts of the whole
    np.testing.assert_array_equal(
        confusion(pred[:1], truth[:1]) + confusion(pred[1:], truth[1:]), confusion(pred, truth)
    )
    with pytest.raises(ValueError, match=r"pred: expected the shape of truth \[2, 4\], got \[4\]"):
        confusion(pred[0], truth)


@pytest.mark.slow(seconds=4)
def test_segmenter_learns_the_classes_and_its_score_needs_the_right_boxes(segmenter_run, clips21):
    from jaxdrive.eval.segmenter import load_segmenter
    from jaxdrive.train.segmenter_run import load_frames

    info = json.loads((segmenter_run / "segmenter.json").read_text())
    assert info["size"] == [32, 56] and info["classes"] == list(CLASSES)
    assert 0 <= info["validation"]["miou"] <= 1  # the test run sees 2 scenes: it fits them, no more
    seg = load_segmenter(segmenter_run)
    frames, masks = load_frames(clips21, "train", size=(32, 56), views=6, stride=2)
    pred = seg.classes(frames.astype(np.float32) / 127.5 - 1.0)
    own = summary(confusion(pred, masks))["miou"]
    other = summary(confusion(pred, np.roll(masks, len(masks) // 2, axis=0)))["miou"]  # another scene's masks
    assert own > 0.3 and other < 0.5 * own, (own, other)
    with pytest.raises(ValueError, match="^workdir: expected a segmenter run directory"):
        load_segmenter(clips21)


def test_segmenter_config_refuses_frame_sizes_its_levels_cannot_halve(clips21, tmp_path, capsys):
    from jaxdrive.cli import main as cli

    assert (
        cli(
            [
                "train",
                "--config",
                f"{CONFIG}:size=test",
                "--workdir",
                str(tmp_path / "r"),
                "--set",
                f"data.path={clips21}",
                "--set",
                "data.height=30",
                "--no-progress",
            ]
        )
        == 2
    )
    assert "data.height: expected a positive multiple of 2 ** segmenter.levels = 4, got 30" in capsys.readouterr().err


@pytest.mark.optimized_xla  # its time is running the sampler and the segmenter, not compiling
@pytest.mark.slow(seconds=20)
def test_eval_measures_controllability_and_the_shuffled_boxes_control_scores_lower(
    tiny_dit, segmenter_run, tmp_path, capsys
):
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
                "--split",
                "train",
                "--steps",
                "1",
                "--segmenter",
                str(segmenter_run),
                "--shuffle-boxes",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "| strategy | frames | PSNR | SSIM | mIoU |" in printed and "| recorded frames | 2-5 |" in printed
    report = json.loads((out / "eval.json").read_text())
    assert report["shuffle_boxes"] is True
    ceiling = report["recorded_controllability"]
    generated = report["strategies"]["rollout"]["buckets"]
    for span, row in generated.items():
        # the recorded frames against their own boxes beat generations against boxes they do not show
        assert ceiling[span]["miou"] > 0.3 and row["miou"] < ceiling[span]["miou"] - 0.15, (span, row, ceiling)
        assert set(row["miou_per_class"]) <= set(CLASSES[1:])
    for args, message in (
        (["--shuffle-boxes"], "--shuffle-boxes: expected with --segmenter"),
        (
            ["--segmenter", str(segmenter_run), "--shuffle-boxes", "--clips", "1"],
            "--clips: expected at least 2 with --shuffle-boxes",
        ),
        (["--segmenter", str(tiny_dit)], "--segmenter: expected a segmenter run directory"),
    ):
        argv = [
            "eval",
            "--workdir",
            str(tiny_dit),
            "--frames",
            "13",
            "--split",
            "train",
            "--steps",
            "1",
            "--out",
            str(tmp_path / "no"),
            *args,
        ]
        if "--clips" not in args:
            argv += ["--clips", "2"]
        assert cli(argv) == 2, args
        assert message in capsys.readouterr().err, message
