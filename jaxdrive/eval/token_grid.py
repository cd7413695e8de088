"""How much a generated clip shows the DiT's token grid: the contrast of the steps between
neighbouring pixels on a grid's lines against the steps elsewhere.

    python -m jaxdrive.eval.token_grid --workdir RUN [--frames 33] [--clips 2]

A clip's frames ``[..., F, H, W, 3]`` become one figure a frame: the mean absolute step of the
grey level across the lines of a grid of ``period`` pixels (columns and rows ``offset + k *
period`` to the next), over the mean step across all other lines. A natural image gives about 1;
an image drawn in blocks of ``period`` pixels, whose values jump at the blocks' edges, gives more
(JPEG's blocking-artefact measures compare steps at the 8-pixel block boundaries to those inside
the blocks in the same way: Wang, Bovik and Evans, "Blind measurement of blocking artifacts in
images", ICIP 2000). The grid a run can draw is its token's footprint in pixels, ``patch x
vae_spatial`` (8 for configs/tiny.py's 2 x 2 patches of 4-pixel space-to-depth latents); the
codec's own blocks (``vae_spatial``) at the offsets between the tokens' edges tell the codec's
grid from the DiT's. The command line samples a run's validation clips by the rollout and prints
both against the recorded frames, per horizon bucket.
"""

from __future__ import annotations

import numpy as np

from jaxdrive.validate import check_positive_int


def grid_contrast(video, period: int, offset: int | None = None) -> np.ndarray:
    """Per-frame grid contrast ``[F]`` of ``video [..., F, H, W, C]`` (any range): the mean
    absolute grey-level step between pixel ``offset + k * period`` and the next (columns and
    rows), over the mean step between all other neighbours. ``offset`` defaults to
    ``period - 1`` (the edges of blocks that start at 0). 1: no grid; a block image: more."""
    v = np.asarray(video, np.float64)
    if v.ndim < 4:
        raise ValueError(f"video: expected shape [..., F, H, W, C] (4 or more axes), got {list(v.shape)}")
    check_positive_int("period", period, minimum=2)
    offset = period - 1 if offset is None else offset
    if not 0 <= offset < period:
        raise ValueError(f"offset: expected a pixel step inside the period, 0 to {period - 1}, got {offset}")
    if min(v.shape[-3], v.shape[-2]) < period + 1:
        raise ValueError(
            f"video: expected frames of more than period = {period} pixels a side, got {list(v.shape[-3:-1])}"
        )
    grey = v.mean(-1)
    frames = grey.reshape((-1,) + grey.shape[-3:])  # [N, F, H, W]
    dx = np.abs(np.diff(frames, axis=-1))  # the step from column j to j + 1
    dy = np.abs(np.diff(frames, axis=-2))
    on_x = np.zeros(dx.shape[-1], bool)
    on_x[offset::period] = True
    on_y = np.zeros(dy.shape[-2], bool)
    on_y[offset::period] = True
    on = dx[..., on_x].mean(axis=(0, 2, 3)) + dy[..., on_y, :].mean(axis=(0, 2, 3))
    off = dx[..., ~on_x].mean(axis=(0, 2, 3)) + dy[..., ~on_y, :].mean(axis=(0, 2, 3))
    return on / np.maximum(off, 1e-12)


def main(argv=None) -> int:
    import argparse

    from jaxdrive.world_model import WorldModel

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workdir", required=True, help="a DiT run")
    ap.add_argument("--frames", type=int, default=33, help="pixel frames per clip")
    ap.add_argument("--clips", type=int, default=2, help="validation clips")
    args = ap.parse_args(argv)
    check_positive_int("--frames", args.frames)
    check_positive_int("--clips", args.clips)
    model = WorldModel.from_run(args.workdir)
    m = model.spec.model
    token = m.patch[-1] * m.vae_spatial
    g = model.generate(frames=args.frames, strategy="rollout", clips=args.clips)
    given = int(g.report["quality"]["cond_frames"])  # the pixel frames given
    edges = np.linspace(given, args.frames, 4).round().astype(int)
    grids = [("token", token, None)]
    if m.vae_spatial > 1 and token > m.vae_spatial:
        grids.append(("codec only", token, m.vae_spatial - 1))  # the codec's edges inside a token
    print(f"grid contrast (1: none), {args.clips} clips, grids of {token} pixels (tokens) and {m.vae_spatial} (codec):")
    print("| grid | frames | generated | recorded |\n|---|---|---|---|")
    for name, period, offset in grids:
        gen, rec = grid_contrast(g.video, period, offset), grid_contrast(g.recorded, period, offset)
        for lo, hi in zip(edges[:-1], edges[1:]):
            print(f"| {name} | {lo}-{hi - 1} | {gen[lo:hi].mean():.3f} | {rec[lo:hi].mean():.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
