"""Input pipeline throughput: TFDS ArrayRecord clips -> grain -> bucketed training batches.

    python -m jaxdrive.bench.pipeline [--clips 32] [--views 6] [--frames 33] [--size 224 400]
                                      [--out 17 128 224] [--batch 2] [--threads 0 4] [--data DIR]

Writes N random clips (uint8 video of ``--views`` x ``--frames`` x ``--size``) to a temporary TFDS
dataset (or reads ``--data DIR``), then times batches of ``--out`` (F, H, W) frames for each thread
count, side by side in one run: batches/s, clips/s and output frames/s (views x frames per clip).
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time

import numpy as np

from jaxdrive.bench.report import emit, table
from jaxdrive.data import pipeline, schema, tfds_io

NAME = "pipeline"


def _random_clip(rng, views, frames, height, width, boxes=16, bev=64):
    e2w = np.tile(np.eye(4), (frames, 1, 1))
    e2w[:, 0, 3] = np.arange(frames)
    return {
        "video": rng.integers(0, 256, (views, frames, height, width, 3), dtype=np.uint8),
        "intrinsics": np.tile(
            np.array([[width, 0, width / 2], [0, width, height / 2], [0, 0, 1]], np.float32), (views, 1, 1)
        ),
        "cam_to_ego": np.tile(np.eye(4, dtype=np.float32), (views, 1, 1)),
        "ego_to_world": e2w,
        "boxes": rng.normal(size=(frames, boxes, 7)).astype(np.float32),
        "box_classes": rng.integers(0, 10, (frames, boxes), dtype=np.int32),
        "box_ids": rng.integers(0, 100, (frames, boxes), dtype=np.int32),
        "box_valid": rng.random((frames, boxes)) < 0.5,
        "bev_map": rng.integers(0, 2, (frames, bev, bev, 8), dtype=np.uint8),
        "waypoints": np.stack([np.arange(frames), np.zeros(frames)], 1).astype(np.float32),
        "fps": 12.0,
        "caption": schema.caption(sensor="CAM_FRONT", location="synthetic", season="summer", daytime="day"),
    }


def run(data, *, out, batch, threads, batches, stride, seed=0):
    source = tfds_io.open_source(data, "train")
    F, H, W = out
    rows = []
    for n in threads:
        ds = pipeline.make_pipeline(
            source,
            {(H, W, F): batch},
            stride=stride,
            seed=seed,
            shard_index=0,
            shard_count=1,
            num_threads=n,
            prefetch=max(2 * n, 1),
        )
        it = iter(ds)
        first = next(it)  # warm-up (opens files, fills the prefetch buffer)
        views = first["video"].shape[1]
        t0 = time.perf_counter()
        for _ in range(batches):
            next(it)
        dt = time.perf_counter() - t0
        row = dict(
            threads=n,
            batch=batch,
            out=f"{views}x{F}x{H}x{W}",
            batches_per_s=round(batches / dt, 2),
            clips_per_s=round(batches * batch / dt, 2),
            frames_per_s=round(batches * batch * views * F / dt, 1),
        )
        rows.append(row)
        ctx = dict(threads=n, batch=batch, views=views, frames=F, height=H, width=W, stride=stride)
        emit(NAME, "batches_per_s", row["batches_per_s"], "1/s", **ctx)
        emit(NAME, "clips_per_s", row["clips_per_s"], "1/s", **ctx)
        emit(NAME, "frames_per_s", row["frames_per_s"], "1/s", **ctx)
    print(table(rows, ["threads", "batch", "out", "batches_per_s", "clips_per_s", "frames_per_s"]))
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(prog="jaxdrive bench pipeline", description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", help="an existing TFDS clip dataset (default: write random clips)")
    parser.add_argument("--clips", type=int, default=32)
    parser.add_argument("--views", type=int, default=6)
    parser.add_argument("--frames", type=int, default=33, help="frames per source clip")
    parser.add_argument("--size", type=int, nargs=2, default=[224, 400], metavar=("H", "W"))
    parser.add_argument("--out", type=int, nargs=3, default=[17, 128, 224], metavar=("F", "H", "W"))
    parser.add_argument("--stride", type=int, default=1)
    parser.add_argument("--batch", type=int, default=2)
    parser.add_argument("--batches", type=int, default=20, help="timed batches per thread count")
    parser.add_argument("--threads", type=int, nargs="+", default=[0, 4])
    parser.add_argument("--compression", choices=("bytes", "zlib"), default="bytes")
    args = parser.parse_args(argv)
    for name in ("jaxdrive.data.pipeline", "jaxdrive.data.batch_plan"):  # the plan's per-epoch lines
        logging.getLogger(name).setLevel(logging.WARNING)
    kw = dict(out=tuple(args.out), batch=args.batch, threads=args.threads, batches=args.batches, stride=args.stride)
    if args.data:
        return run(args.data, **kw)
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        clips = (_random_clip(rng, args.views, args.frames, *args.size) for _ in range(args.clips))
        t0 = time.perf_counter()
        path = tfds_io.write_dataset(f"{tmp}/clips", {"train": clips}, compression=args.compression)
        write_s = time.perf_counter() - t0
        emit(
            NAME,
            "write_clips_per_s",
            round(args.clips / write_s, 2),
            "1/s",
            clips=args.clips,
            views=args.views,
            frames=args.frames,
            height=args.size[0],
            width=args.size[1],
            compression=args.compression,
        )
        return run(path, **kw)


if __name__ == "__main__":
    main()
