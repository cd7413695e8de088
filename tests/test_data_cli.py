"""`jaxdrive data synth / nuscenes / info` end to end, into the grain pipeline."""

import json

import numpy as np
import pytest

from jaxdrive.cli import main
from jaxdrive.data.pipeline import make_pipeline
from jaxdrive.data.tfds_io import open_source


def test_synth_info_and_pipeline(tmp_path, capsys):
    out = tmp_path / "synth"
    assert (
        main(
            [
                "data",
                "synth",
                "--out",
                str(out),
                "--scenes",
                "3",
                "--frames",
                "9",
                "--views",
                "6",
                "--height",
                "32",
                "--width",
                "56",
            ]
        )
        == 0
    )
    assert "wrote 2 train and 1 validation clips" in capsys.readouterr().out
    assert main(["data", "info", str(out)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["splits"]["train"]["num_examples"] == 2
    assert info["splits"]["validation"]["num_examples"] == 1
    assert info["metadata"]["source"] == "synthetic"

    source = open_source(out, "train")
    clip = source[0]
    assert clip["video"].shape == (6, 9, 32, 56, 3)
    ds = make_pipeline(source, {(16, 28, 5): 2}, stride=2, shard_index=0, shard_count=1, seed=3)
    batch = next(iter(ds))
    assert batch["video"].shape == (2, 6, 5, 16, 28, 3)
    assert batch["video"].dtype == np.float32 and -1.0 <= batch["video"].min() <= batch["video"].max() <= 1.0
    np.testing.assert_allclose(batch["fps"], 6.0)
    # the same seed gives the same synthetic dataset
    again = tmp_path / "again"
    main(["data", "synth", "--out", str(again), "--scenes", "3", "--frames", "9", "--height", "32", "--width", "56"])
    np.testing.assert_array_equal(open_source(again, "train")[1]["video"], source[1]["video"])


def test_nuscenes_conversion(tmp_path, capsys):
    from nuscenes_fixture import write_fixture

    root = write_fixture(str(tmp_path / "nus"))
    out = tmp_path / "nus_tfds"
    assert main(["data", "nuscenes", "--dataroot", str(root), "--out", str(out), "--frames", "5"]) == 0
    assert "1 train / 1 validation scenes" in capsys.readouterr().out
    clip = open_source(out, "train")[0]
    assert clip["video"].shape[:2] == (6, 5)
    assert isinstance(clip["scene"], str) and clip["timestamps"].shape == (5,)


@pytest.mark.parametrize(
    "argv, match",
    [
        (["data", "info", "/nonexistent/dataset"], "path: expected a TFDS dataset directory"),
        (["data", "nuscenes", "--dataroot", "/nonexistent", "--out", "/tmp/x"], "/nonexistent"),
    ],
)
def test_bad_input_is_one_line_naming_the_argument(argv, match, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert match in err and "Traceback" not in err


def test_height_without_width_is_rejected():
    with pytest.raises(SystemExit, match="--height/--width: expected both or neither"):
        main(["data", "nuscenes", "--dataroot", "x", "--out", "y", "--height", "32"])


def test_info_messages_reach_stderr_unless_quiet(tmp_path, capsys):
    small = ["--scenes", "2", "--frames", "5", "--height", "16", "--width", "28"]
    assert main(["data", "synth", "--out", str(tmp_path / "a"), *small]) == 0
    assert "INFO jaxdrive.data.tfds_io: wrote dataset" in capsys.readouterr().err
    assert main(["--quiet", "data", "synth", "--out", str(tmp_path / "b"), *small]) == 0
    out = capsys.readouterr()
    assert "wrote 1 train and 1 validation clips" in out.out and "wrote dataset" not in out.err
    # the level and handler are the CLI's only while it runs
    import logging

    assert logging.getLogger("jaxdrive").level == logging.NOTSET and not logging.getLogger("jaxdrive").handlers


def test_nuscenes_faults_are_named_or_skipped(tmp_path, capsys):
    import os

    from jaxdrive.data import nuscenes

    from nuscenes_fixture import write_fixture

    root = write_fixture(str(tmp_path / "nus"))
    first = next(nuscenes.read_clips(root, frames=4))["meta"]["sample_data_tokens"][3][0]  # CAM_BACK
    image = tmp_path / "nus" / nuscenes.load_tables(root)["sample_data"][first]["filename"]
    image.write_bytes(b"not a jpeg")
    argv = ["data", "nuscenes", "--dataroot", root, "--frames", "4"]
    assert main([*argv, "--out", str(tmp_path / "a")]) == 2
    assert f"{image}: expected a readable image" in capsys.readouterr().err
    assert not (tmp_path / "a").exists()
    assert main([*argv, "--out", str(tmp_path / "b"), "--skip-bad-records"]) == 0
    out = capsys.readouterr()
    assert "1 clips left out for unreadable images (1 files, named in the log)" in out.out
    assert [str(image) in line for line in out.err.splitlines()].count(True) == 1  # one line names it
    assert len(open_source(tmp_path / "b", "train")) + len(open_source(tmp_path / "b", "validation")) == 5
    # a missing table: no dataset without it, so nothing to skip
    table = os.path.join(root, "v1.0-mini", "sample_annotation.json")
    os.remove(table)
    assert main([*argv, "--out", str(tmp_path / "c"), "--skip-bad-records"]) == 2
    assert f"{table}: expected the nuScenes table 'sample_annotation', got no such file" in capsys.readouterr().err
    assert not (tmp_path / "c").exists()
