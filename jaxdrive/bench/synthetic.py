"""Rendering speed of the synthetic driving world (numpy, one core): clips/s and s/clip.

    python -m jaxdrive.bench.synthetic [--clips 5] [--sizes 6x33x64x112 1x33x128x224]

Each size is VIEWSxFRAMESxHEIGHTxWIDTH; clips use seeds 0..clips-1 (a mix of looks and traffic),
after one warm-up clip.
"""

from __future__ import annotations

import argparse
import time

from jaxdrive.bench.report import emit, table
from jaxdrive.data.synthetic import generate_clip

NAME = "synthetic"
DEFAULT_SIZES = ("6x33x64x112", "1x33x128x224", "6x33x128x224")


def _parse(size: str):
    try:
        views, frames, height, width = (int(p) for p in size.lower().split("x"))
    except ValueError:
        raise ValueError(f"--sizes: expected VIEWSxFRAMESxHEIGHTxWIDTH, got {size!r}") from None
    return views, frames, height, width


def run(sizes, clips):
    rows = []
    for size in sizes:
        views, frames, height, width = _parse(size)
        kwargs = dict(views=views, frames=frames, height=height, width=width)
        generate_clip(10_000, **kwargs)  # warm-up
        times = []
        for seed in range(clips):
            start = time.perf_counter()
            generate_clip(seed, **kwargs)
            times.append(time.perf_counter() - start)
        mean = sum(times) / len(times)
        row = dict(
            views=views,
            frames=frames,
            height=height,
            width=width,
            clips=clips,
            s_per_clip=round(mean, 4),
            best_s=round(min(times), 4),
            clips_per_s=round(1.0 / mean, 3),
        )
        rows.append(row)
        ctx = dict(views=views, frames=frames, height=height, width=width, clips=clips)
        emit(NAME, "seconds_per_clip", row["s_per_clip"], "s", **ctx)
        emit(NAME, "clips_per_second", row["clips_per_s"], "clips/s", **ctx)
    print(table(rows, ["views", "frames", "height", "width", "clips", "s_per_clip", "best_s", "clips_per_s"]))
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(prog="jaxdrive bench synthetic", description=__doc__.split("\n\n")[0])
    parser.add_argument("--clips", type=int, default=5, help="clips rendered per size")
    parser.add_argument(
        "--sizes", nargs="+", default=list(DEFAULT_SIZES), help="VIEWSxFRAMESxHEIGHTxWIDTH, e.g. 6x33x64x112"
    )
    args = parser.parse_args(argv)
    if args.clips < 1:
        parser.error(f"--clips: expected an integer >= 1, got {args.clips}")
    for size in args.sizes:
        try:
            _parse(size)
        except ValueError as err:
            parser.error(str(err))
    return run(args.sizes, args.clips)


if __name__ == "__main__":
    main()
