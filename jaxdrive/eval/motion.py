"""ADE / FDE of the future-controls predictor against the constant-velocity baseline.

    python -m jaxdrive.eval.motion --workdir PREDICTOR_RUN [--data PATH] [--split validation]

For every clip, windows start at every step; from each the predictor is rolled forward
open loop (its own predictions fed back, the map re-cut from the clip's stitched scene map at each
predicted pose, :mod:`jaxdrive.data.scene_map`) and so is the constant-velocity step
(:func:`jaxdrive.models.predictor.constant_velocity`). At each horizon h (seconds): ADE, the mean
position error over the steps up to h, and FDE, the error at h, in metres, for the ego and for
every agent present at the window's start and seen at the step scored.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.data.scene_map import DEFAULT_RANGE, SceneMap
from jaxdrive.models.predictor import constant_velocity_rollout, rollout_program

HORIZONS = (1.0, 2.0, 4.0)


def motion_errors(params, config, clips, *, horizons=HORIZONS, bev_range=DEFAULT_RANGE):
    """ADE / FDE (module docstring) of ``params`` over ``clips`` (control fields and ``fps``, as
    :func:`jaxdrive.train.predictor_run.load_controls` gives): ``{"horizons": {h: {"ego": {"ade",
    "fde", "cv_ade", "cv_fde"}, "agents": {...}}}, "windows", "agent_tracks"}``, horizons the
    clips are too short for left out; None when none fits."""
    from jaxdrive.train.predictor_run import to_traffic, window_traffic
    t, s = config.history, config.stride
    fps = clips[0]["fps"]
    shortest = min(len(c["ego_to_world"]) for c in clips)
    steps = {h: int(round(h * fps / s)) for h in horizons}
    steps = {h: k for h, k in steps.items() if k >= 1 and (t - 1 + k) * s < shortest}
    if not steps:
        return None
    total = max(steps.values())
    predicted, constant = rollout_program(config), jax.jit(constant_velocity_rollout, static_argnums=(1,))
    sums = {(who, kind, h): 0.0 for who in ("ego", "agents") for kind in ("ade", "fde", "cv_ade", "cv_fde")
            for h in steps}
    counts = {(who, h): 0 for who in ("ego", "agents") for h in steps}
    windows = tracks = 0
    for clip in clips:
        offsets = s * np.arange(t + total)
        starts = range(0, len(clip["ego_to_world"]) - int(offsets[-1]), s)
        ws = [window_traffic(clip, st + offsets, t) for st in starts]
        batch = {k: np.stack([w[k] for w in ws]) for k in ws[0]}
        traffic = to_traffic(batch, t)
        scene = SceneMap.from_clip(clip["bev_map"], clip["ego_to_world"], bev_range).device()
        bev = jnp.asarray(batch["bev"][:, t - 1], jnp.float32)
        runs = {"": predicted(params, traffic, total, bev, scene, None), "cv_": constant(traffic, total)}
        true_ego, true_agents = batch["ego"][:, t:], batch["agents"][:, t:]
        seen = batch["seen"][:, t:] & batch["seen"][:, t - 1:t]
        windows += len(ws)
        tracks += int(batch["seen"][:, t - 1].sum())
        for prefix, (ego, agents) in runs.items():
            e_ego = np.linalg.norm(np.asarray(ego)[..., :2] - true_ego[..., :2], axis=-1)            # [B, S]
            e_ag = np.linalg.norm(np.asarray(agents)[..., :2] - true_agents[..., :2], axis=-1)        # [B, S, N]
            for h, k in steps.items():
                sums["ego", prefix + "ade", h] += e_ego[:, :k].mean(1).sum()
                sums["ego", prefix + "fde", h] += e_ego[:, k - 1].sum()
                # agents: ADE over the steps each was seen, FDE where seen at h
                m = seen[:, :k]
                per = (e_ag[:, :k] * m).sum(1) / np.maximum(m.sum(1), 1)                              # [B, N]
                scored = seen[:, k - 1]
                sums["agents", prefix + "ade", h] += per[scored].sum()
                sums["agents", prefix + "fde", h] += e_ag[:, k - 1][scored].sum()
                if not prefix:
                    counts["ego", h] += len(ws)
                    counts["agents", h] += int(scored.sum())
    out = {"horizons": {}, "windows": windows, "agent_tracks": tracks, "step_seconds": s / fps}
    for h in steps:
        out["horizons"][f"{h:g}s"] = {who: {kind: round(sums[who, kind, h] / max(counts[who, h], 1), 3)
                                            for kind in ("ade", "fde", "cv_ade", "cv_fde")}
                                      for who in ("ego", "agents")}
    return out


def format_table(scores: dict) -> str:
    """The scores as a small table (metres; lower is better)."""
    lines = [f"ADE / FDE in metres over {scores['windows']} windows ({scores['agent_tracks']} agent tracks); "
             f"predictor vs constant velocity",
             f"  {'horizon':8s} {'who':7s} {'ADE':>7s} {'cv ADE':>7s} {'FDE':>7s} {'cv FDE':>7s}"]
    for h, row in scores["horizons"].items():
        for who, r in row.items():
            lines.append(f"  {h:8s} {who:7s} {r['ade']:7.3f} {r['cv_ade']:7.3f} {r['fde']:7.3f} {r['cv_fde']:7.3f}")
    return "\n".join(lines)


def main(argv=None) -> int:
    import argparse
    import json
    from pathlib import Path

    from jaxdrive.data.scene_map import bev_range_of
    from jaxdrive.data.tfds_io import dataset_info
    from jaxdrive.train.predictor_run import load_controls, load_predictor
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workdir", required=True, help="a predictor run (configs/predictor.py)")
    ap.add_argument("--data", help="dataset (default: the run's data.path)")
    ap.add_argument("--split", default="validation")
    ap.add_argument("--out", help="write the scores as JSON here")
    args = ap.parse_args(argv)
    config, params, _ = load_predictor(args.workdir)
    path = args.data or config.data.path
    clips = load_controls(path, args.split, max_agents=config.predictor.max_agents)
    scores = motion_errors(params, config.predictor, clips,
                           bev_range=bev_range_of(dataset_info(path)["metadata"]))
    if scores is None:
        raise SystemExit(f"--data: the {args.split!r} clips of {path} are too short for a 1 s horizon")
    print(format_table(scores))
    if args.out:
        Path(args.out).write_text(json.dumps(scores, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
