"""ADE / FDE of the future-controls predictor against the constant-velocity baseline.

    python -m jaxdrive.eval.motion --workdir PREDICTOR_RUN [--data PATH] [--split validation]

For every clip, windows start at every step; from each the predictor is rolled forward
open loop (its own predictions fed back, the map re-cut from the clip's stitched scene map at each
predicted pose, :mod:`jaxdrive.data.scene_map`) and so is the constant-velocity step
(:func:`jaxdrive.models.predictor.constant_velocity`). At each horizon h (seconds): ADE, the mean
position error over the steps up to h, and FDE, the error at h, in metres, for the ego and for
every agent present at the window's start and seen at the step scored
(:func:`jaxdrive.train.predictor_run.motion_errors`, which the predictor's training also scores its
validation split with).
"""

from __future__ import annotations

# computed where the predictor's training validates with them; here: the command line
from jaxdrive.train.predictor_run import HORIZONS, format_table, load_predictor, motion_errors  # noqa: F401


def main(argv=None) -> int:
    import argparse
    import json
    from pathlib import Path

    from jaxdrive.data.scene_map import bev_range_of
    from jaxdrive.data.tfds_io import dataset_info
    from jaxdrive.data.traffic import load_controls

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workdir", required=True, help="a predictor run (configs/predictor.py)")
    ap.add_argument("--data", help="dataset (default: the run's data.path)")
    ap.add_argument("--split", default="validation")
    ap.add_argument("--out", help="write the scores as JSON here")
    args = ap.parse_args(argv)
    config, params, _ = load_predictor(args.workdir)
    path = args.data or config.data.path
    clips = load_controls(path, args.split, max_agents=config.predictor.max_agents)
    scores = motion_errors(params, config.predictor, clips, bev_range=bev_range_of(dataset_info(path)["metadata"]))
    if scores is None:
        raise SystemExit(f"--data: the {args.split!r} clips of {path} are too short for a 1 s horizon")
    print(format_table(scores))
    if args.out:
        Path(args.out).write_text(json.dumps(scores, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
