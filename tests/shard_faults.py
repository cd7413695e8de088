"""Damage the ArrayRecord shards of a dataset written by ``jaxdrive.data.tfds_io.write_dataset`` as a
bad disk or a cut copy would: bytes overwritten inside records, or the file cut short."""

from __future__ import annotations

import struct
from pathlib import Path

_BLOCK = 1 << 16  # Riegeli's block size


def shard_files(dataset, split: str = "train") -> list[Path]:
    """The shard files of ``split``, in order."""
    files = sorted(Path(dataset).glob(f"*-{split}.array_record-*"))
    assert files, f"no {split} shards under {dataset}"
    return files


def overwrite_records(shard: Path, records) -> None:
    """Overwrite 64 bytes in the middle of the data of each of ``records`` (positions in the shard).
    Walks Riegeli's chunk headers (40 bytes: hashes, data size at bytes 8-16) from byte 64, one
    chunk per record (``group_size:1``); the records must lie in the first 64 KiB block."""
    data = bytearray(shard.read_bytes())
    start, chunks = 64, []
    for _ in range(max(records) + 1):
        size = struct.unpack("<Q", data[start + 8 : start + 16])[0]
        chunks.append((start, size))
        start += 40 + size
    assert start < _BLOCK, f"{shard}: records beyond the first block"
    for r in records:
        at, size = chunks[r]
        mid = at + 40 + size // 2
        data[mid - 32 : mid + 32] = bytes(range(64))
    shard.write_bytes(bytes(data))


def truncate(shard: Path) -> None:
    """Cut the shard file to half its length (its index, at the end, is lost)."""
    data = shard.read_bytes()
    shard.write_bytes(data[: len(data) // 2])


def damaged_dataset(out, how: str):
    """12 tiny clips (2 views, 5 frames of 6 x 10), 3 per shard, shard 1 damaged: ``how`` =
    ``"overwrite"`` (its records 0 and 1: clips 3 and 4 unreadable, 5 intact) or ``"truncate"``
    (clips 3, 4 and 5). Returns ``(dataset path, clips, unreadable clip indices, damaged shard)``."""
    from test_tfds_io import random_clip

    from jaxdrive.data import tfds_io

    clips = [random_clip(i, V=2, F=5, H=6, W=10) for i in range(12)]
    path = tfds_io.write_dataset(out, {"train": clips}, shard_bytes=16_000)  # 3 records of ~6.8 kB each
    shards = shard_files(path)
    src = tfds_io.open_source(path, "train")
    assert len(shards) == 4 and [src.shard_of(i) for i in (3, 5)] == [(str(shards[1]), 0), (str(shards[1]), 2)]
    if how == "overwrite":
        overwrite_records(shards[1], [0, 1])
        return path, clips, {3, 4}, shards[1]
    truncate(shards[1])
    return path, clips, {3, 4, 5}, shards[1]
