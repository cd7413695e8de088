import re
import sys

import numpy as np
import pytest

from jaxdrive.data import schema, tfds_io


def random_clip(seed, V=2, F=5, H=6, W=10, N=3, Hm=4, Wm=4, instance_ids=True, scene=True):
    rng = np.random.default_rng(seed)
    clip = {
        "video": rng.integers(0, 256, (V, F, H, W, 3), dtype=np.uint8),
        "intrinsics": rng.normal(size=(V, 3, 3)).astype(np.float32),
        "cam_to_ego": rng.normal(size=(V, 4, 4)).astype(np.float32),
        "ego_to_world": rng.normal(size=(F, 4, 4)),
        "boxes": rng.normal(size=(F, N, 7)).astype(np.float32),
        "box_classes": rng.integers(0, 10, (F, N), dtype=np.int32),
        "box_ids": rng.integers(0, 99, (F, N), dtype=np.int32),
        "box_valid": rng.random((F, N)) < 0.5,
        "bev_map": rng.integers(0, 2, (F, Hm, Wm, 8), dtype=np.uint8),
        "waypoints": rng.normal(size=(F, 2)).astype(np.float32),
        "fps": float(rng.choice([2.0, 12.0])),
        "caption": f"caption of clip {seed} ü",
    }
    if instance_ids:
        clip["instance_ids"] = rng.integers(-1, 5, (V, F, H, W), dtype=np.int32)
    if scene:
        clip["scene"] = f"scene-{seed:04d}"
    schema.check_clip(clip)
    return clip


def assert_clip_equal(got, want):
    assert set(got) == set(want)
    for k, v in want.items():
        if isinstance(v, np.ndarray):
            assert got[k].dtype == v.dtype, k
            np.testing.assert_array_equal(got[k], v, err_msg=k)
        else:
            assert got[k] == v and type(got[k]) is type(v), k


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    out = tmp_path_factory.mktemp("ds") / "clips"
    train = [random_clip(i, F=3 + i, V=1 + i % 3) for i in range(5)]
    val = [random_clip(100 + i, H=8) for i in range(2)]
    path = tfds_io.write_dataset(
        out, {"train": iter(train), "validation": val}, metadata={"source": "synthetic", "seed": 0}
    )
    return path, train, val


def test_round_trip_both_splits(written):
    path, train, val = written
    for split, clips in (("train", train), ("validation", val)):
        src = tfds_io.open_source(path, split)
        assert len(src) == len(clips)
        np.testing.assert_array_equal(src.frame_counts, [c["ego_to_world"].shape[0] for c in clips])
        for i, clip in enumerate(clips):
            got = src[i]
            schema.check_clip(got)
            assert_clip_equal(got, clip)
    # the parent directory (one dataset below it) also opens
    assert len(tfds_io.open_source(path.parent, "validation")) == 2
    assert "tensorflow" not in sys.modules


def test_source_pickles(written):
    import pickle

    path, train, _ = written
    src = pickle.loads(pickle.dumps(tfds_io.open_source(path, "train")))
    assert_clip_equal(src[3], train[3])


def test_info(written):
    path, train, val = written
    info = tfds_io.dataset_info(path)
    assert info["splits"]["train"]["num_examples"] == 5
    assert info["splits"]["validation"]["num_examples"] == 2
    assert (info["splits"]["train"]["min_frames"], info["splits"]["train"]["max_frames"]) == (3, 7)
    assert info["features"]["video"] == {"kind": "tensor", "shape": [None, None, None, None, 3], "dtype": "uint8"}
    assert info["features"]["ego_to_world"]["dtype"] == "float64"
    assert info["features"]["scene"] == {"kind": "text"}
    assert info["metadata"] == {"source": "synthetic", "seed": 0}
    assert info["file_format"] == "array_record"


def test_zlib_missing_optional_and_many_shards(tmp_path):
    clips = [random_clip(i, instance_ids=False, scene=False) for i in range(5)]
    path = tfds_io.write_dataset(tmp_path / "z", {"train": clips}, compression="zlib", shard_bytes=1)
    assert len(list(path.glob("*.array_record-*-of-00005"))) == 5
    src = tfds_io.open_source(path, "train")
    for i in range(5):
        assert_clip_equal(src[i], clips[i])


def test_failure_leaves_nothing(tmp_path):
    def clips():
        yield random_clip(0)
        yield random_clip(1)
        raise RuntimeError("renderer crashed")

    out = tmp_path / "clips"
    with pytest.raises(RuntimeError, match="renderer crashed"):
        tfds_io.write_dataset(out, {"train": clips()})
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []  # no temporary directory left behind either

    bad = random_clip(1)
    bad["video"] = bad["video"].astype(np.float32)
    with pytest.raises(ValueError, match=r"clips.*split 'train' clip 1: field 'video': expected dtype uint8"):
        tfds_io.write_dataset(out, {"train": [random_clip(0), bad]})
    assert list(tmp_path.iterdir()) == []


class _SecondOfTwo:
    """Process 1 of a two-process write, as :class:`jaxdrive.parallel.Processes` looks to it
    (the gathers answer for both)."""

    index, count = 1, 2

    def gather(self, value: int) -> list[int]:
        return [value, value]


@pytest.mark.parametrize("failure", [RuntimeError("renderer crashed"), "bad dtype"])
def test_a_failed_process_of_several_names_the_temporary_dataset_and_its_removal(tmp_path, failure):
    """Process 1 of 2 fails while writing its shards: it stops at once (the others may still write
    into the shared temporary directory, so it cannot remove it) and its error names that
    directory and the command that removes it."""

    def clips():
        yield random_clip(0)
        if isinstance(failure, Exception):
            raise failure
        bad = random_clip(1)
        bad["video"] = bad["video"].astype(np.float32)
        yield bad

    out = tmp_path / "clips"
    kind = RuntimeError if isinstance(failure, Exception) else ValueError
    with pytest.raises(kind) as info:
        tfds_io.write_dataset(out, {"train": clips()}, processes=_SecondOfTwo())
    left = [p for p in tmp_path.iterdir()]
    assert not out.exists() and len(left) == 1 and left[0].name.startswith(".clips.tmp-"), left
    text = str(info.value) + "".join(getattr(info.value, "__notes__", []))
    assert f"the partial dataset stays in {left[0]}: remove it with rm -rf '{left[0]}'" in text, text


def test_overwrite_and_existing(tmp_path):
    out = tfds_io.write_dataset(tmp_path / "c", {"train": [random_clip(0)]})
    with pytest.raises(ValueError, match="already exists"):
        tfds_io.write_dataset(out, {"train": [random_clip(1)]})
    tfds_io.write_dataset(out, {"train": [random_clip(1), random_clip(2)]}, overwrite=True)
    assert len(tfds_io.open_source(out, "train")) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c"]


def test_errors_name_the_path(tmp_path):
    with pytest.raises(ValueError, match=f"{tmp_path / 'nope'}.*does not exist"):
        tfds_io.open_source(tmp_path / "nope", "train")
    out = tfds_io.write_dataset(tmp_path / "c", {"train": [random_clip(0)]})
    with pytest.raises(ValueError, match=r"split: expected one of \['train'\]"):
        tfds_io.open_source(out, "test")
    (out / "dataset_info.json").write_text("{ truncated")
    with pytest.raises(ValueError, match=str(out)):
        tfds_io.open_source(out, "train")


@pytest.mark.parametrize("how", ["overwrite", "truncate"])
def test_a_damaged_shard_names_its_file_and_keeps_the_other_records(tmp_path, how):
    from jaxdrive.data.faults import BadRecordError

    from shard_faults import damaged_dataset

    path, clips, bad, shard = damaged_dataset(tmp_path / "clips", how)
    src = tfds_io.open_source(path, "train")
    for i, clip in enumerate(clips):
        if i in bad:
            position = i - 3
            where = rf"^{re.escape(str(shard))}: record {position} \(clip {i} of split 'train'"
            with pytest.raises(BadRecordError, match=where) as e:
                src[i]
            assert isinstance(e.value, ValueError) and e.value.path == str(shard)
        else:  # nothing else lost: the other shards and, when only overwritten, the shard's intact record
            assert_clip_equal(src[i], clip)
