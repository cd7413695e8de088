"""Training the future-controls predictor: ``jaxdrive train --config configs/predictor.py:size=tiny``.

Windows of ``history + horizon`` steps (one step every ``predictor.stride`` source frames) are cut
from every clip of the dataset's split, held in memory as controls only (no video). The loss
rolls the predictor ``horizon`` steps forward on its own predictions (each step's map the recorded
BEV map of that step's true pose) and averages the position error in metres, plus 2 m per radian
of heading error, of the ego and of every agent seen at the target step. Same run directory
layout as a DiT run (``config.json``, ``checkpoints/``, ``metrics.jsonl``), atomic checkpoints and
exact resume (a step's windows are drawn from ``(train.seed, step)``); at the end the validation
split, when there is one, is scored (:func:`motion_errors`: ADE / FDE against the constant-velocity
baseline, also ``python -m jaxdrive.eval.motion``) into ``motion.json``.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.config import PredictorRunConfig
from jaxdrive.data.scene_map import DEFAULT_RANGE, SceneMap, bev_range_of
from jaxdrive.data.traffic import CONTROL_FIELDS, load_controls, window_traffic  # noqa: F401  (their old home)
from jaxdrive.generate.future import FuturePredictor
from jaxdrive.geometry import wrap
from jaxdrive.models.predictor import (
    Predictor,
    constant_velocity_rollout,
    init_params,
    rollout,
    rollout_program,
    to_traffic,
)
from jaxdrive.validate import check_positive_int

logger = logging.getLogger(__name__)

YAW_METRES = 2.0  # metres of loss per radian of heading error
INFO_FILE = "predictor.json"


def check_predictor_config(config: PredictorRunConfig) -> None:
    p = config.predictor
    for name in ("history", "horizon", "stride", "width", "depth", "heads", "map_patch", "max_agents"):
        check_positive_int(f"predictor.{name}", getattr(p, name), minimum=2 if name == "history" else 1)
    if p.width % p.heads:
        raise ValueError(f"predictor.width: expected a multiple of predictor.heads = {p.heads}, got {p.width}")
    check_positive_int("data.batch_size", config.data.batch_size)
    check_positive_int("train.steps", config.train.steps)


class Windows:
    """Every window of ``history + horizon`` steps at ``stride`` in ``clips``; :meth:`batch` draws
    ``size`` of them for a step, from ``(seed, step)`` alone."""

    def __init__(self, clips: list[dict], history: int, horizon: int, stride: int, *, where: str):
        self.clips, self.history = clips, history
        self.offsets = stride * np.arange(history + horizon)
        self.index = [
            (c, s) for c, clip in enumerate(clips) for s in range(len(clip["ego_to_world"]) - int(self.offsets[-1]))
        ]
        if not self.index:
            longest = max((len(c["ego_to_world"]) for c in clips), default=0)
            raise ValueError(
                f"data.path: expected clips of at least {self.offsets[-1] + 1} frames ({where}: "
                f"history {history} + horizon {horizon} steps at stride {stride}), got at most {longest}"
            )

    def batch(self, size: int, seed: int, step: int) -> dict:
        rng = np.random.default_rng([seed, step])
        picks = rng.integers(len(self.index), size=size)
        ws = [window_traffic(self.clips[c], s + self.offsets, self.history) for c, s in (self.index[i] for i in picks)]
        return {k: np.stack([w[k] for w in ws]) for k in ws[0]}


def rollout_loss(model: Predictor, params, batch: dict, history: int):
    """The mean error of a ``horizon``-step rollout (module docstring) and its parts."""
    traffic = to_traffic(batch, history)
    bev = jnp.asarray(batch["bev"][:, history - 1 : -1], jnp.float32)  # each step's current map
    steps = bev.shape[1]
    ego, agents, _ = rollout(model, params, traffic, steps, bev=bev)
    true_ego = jnp.asarray(batch["ego"][:, history:], jnp.float32)
    true_agents = jnp.asarray(batch["agents"][:, history:], jnp.float32)
    seen = jnp.asarray(batch["seen"][:, history:]) & traffic.seen[:, -1:, :]

    def error(pred, true):
        d = jnp.sqrt(jnp.sum((pred[..., :2] - true[..., :2]) ** 2, -1) + 1e-6)
        return d + YAW_METRES * jnp.abs(wrap(pred[..., 2] - true[..., 2]))

    e_ego = error(ego, true_ego).mean()
    e_agents = jnp.sum(error(agents, true_agents) * seen) / jnp.maximum(seen.sum(), 1)
    return e_ego + e_agents, {"ego_error": e_ego, "agent_error": e_agents}


def train_predictor(config: PredictorRunConfig, workdir, *, progress: bool = True, on_step=None) -> dict:
    """Train (or resume) the predictor in ``workdir``; returns ``{"step", "status", "loss", "params"}``
    (and ``"motion"``, the validation scores, when the dataset has a validation split). ``status``
    as a DiT run's: ``"done"``, ``"interrupted"`` (SIGTERM / SIGINT, checkpoint saved) or
    ``"diverged"`` (``train.max_bad_steps`` non-finite losses in a row). ``on_step(step, metrics)``
    is called after every step (tests)."""
    from jaxdrive.train.aux_run import fit

    check_predictor_config(config)
    p, d, t = config.predictor, config.data, config.train
    clips = load_controls(d.path, d.split, max_agents=p.max_agents)
    windows = Windows(clips, p.history, p.horizon, p.stride, where=f"split {d.split!r}")
    model = Predictor(p)
    params = init_params(p, jax.random.key(t.seed), bev_size=clips[0]["bev_map"].shape[1:3])
    fps = clips[0]["fps"]  # what generation needs to run it: its map grid and its step in seconds
    info = {"bev_size": list(clips[0]["bev_map"].shape[1:3]), "fps": fps, "step_seconds": p.stride / fps}
    out = fit(
        config,
        workdir,
        params,
        lambda q, batch: rollout_loss(model, q, batch, p.history),
        lambda step: windows.batch(d.batch_size, d.shuffle_seed, step),
        files={INFO_FILE: info},
        progress=progress,
        on_step=on_step,
    )
    status, params = out["status"], out["params"]
    if status == "done":
        motion = _validate(config, params, workdir)
        if motion is not None:
            out["motion"] = motion
    return out


def _validate(config, params, workdir):
    """ADE / FDE on the validation split at the horizons its clips allow, into ``motion.json``."""
    from jaxdrive.data.tfds_io import open_source

    try:
        open_source(config.data.path, "validation")
    except ValueError:
        return None
    clips = load_controls(config.data.path, "validation", max_agents=config.predictor.max_agents)
    from jaxdrive.data.tfds_io import dataset_info

    scores = motion_errors(
        params, config.predictor, clips, bev_range=bev_range_of(dataset_info(config.data.path)["metadata"])
    )
    if scores is None:
        logger.warning("validation clips too short for a 1 s horizon: no ADE / FDE")
        return None
    if jax.process_index() == 0:
        (Path(workdir) / "motion.json").write_text(json.dumps(scores, indent=1))
    logger.info("%s", format_table(scores))
    return scores


HORIZONS = (1.0, 2.0, 4.0)


def motion_errors(params, config, clips, *, horizons=HORIZONS, bev_range=DEFAULT_RANGE):
    """ADE / FDE of ``params`` over ``clips`` (control fields and ``fps``, as
    :func:`jaxdrive.data.traffic.load_controls` gives): for every clip, windows start at every
    step; from each the predictor is rolled forward open loop (its own predictions fed back, the
    map re-cut from the clip's stitched scene map at each predicted pose,
    :mod:`jaxdrive.data.scene_map`) and so is the constant-velocity step
    (:func:`jaxdrive.models.predictor.constant_velocity`). At each horizon h (seconds): ADE, the
    mean position error over the steps up to h, and FDE, the error at h, in metres, for the ego
    and for every agent present at the window's start and seen at the step scored.
    ``{"horizons": {h: {"ego": {"ade", "fde", "cv_ade", "cv_fde"}, "agents": {...}}}, "windows",
    "agent_tracks"}``, horizons the clips are too short for left out; None when none fits."""
    t, s = config.history, config.stride
    fps = clips[0]["fps"]
    shortest = min(len(c["ego_to_world"]) for c in clips)
    steps = {h: int(round(h * fps / s)) for h in horizons}
    steps = {h: k for h, k in steps.items() if k >= 1 and (t - 1 + k) * s < shortest}
    if not steps:
        return None
    total = max(steps.values())
    predicted, constant = rollout_program(config), jax.jit(constant_velocity_rollout, static_argnums=(1,))
    sums = {
        (who, kind, h): 0.0 for who in ("ego", "agents") for kind in ("ade", "fde", "cv_ade", "cv_fde") for h in steps
    }
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
        seen = batch["seen"][:, t:] & batch["seen"][:, t - 1 : t]
        windows += len(ws)
        tracks += int(batch["seen"][:, t - 1].sum())
        for prefix, (ego, agents) in runs.items():
            e_ego = np.linalg.norm(np.asarray(ego)[..., :2] - true_ego[..., :2], axis=-1)  # [B, S]
            e_ag = np.linalg.norm(np.asarray(agents)[..., :2] - true_agents[..., :2], axis=-1)  # [B, S, N]
            for h, k in steps.items():
                sums["ego", prefix + "ade", h] += e_ego[:, :k].mean(1).sum()
                sums["ego", prefix + "fde", h] += e_ego[:, k - 1].sum()
                # agents: ADE over the steps each was seen, FDE where seen at h
                m = seen[:, :k]
                per = (e_ag[:, :k] * m).sum(1) / np.maximum(m.sum(1), 1)  # [B, N]
                scored = seen[:, k - 1]
                sums["agents", prefix + "ade", h] += per[scored].sum()
                sums["agents", prefix + "fde", h] += e_ag[:, k - 1][scored].sum()
                if not prefix:
                    counts["ego", h] += len(ws)
                    counts["agents", h] += int(scored.sum())
    out = {"horizons": {}, "windows": windows, "agent_tracks": tracks, "step_seconds": s / fps}
    for h in steps:
        out["horizons"][f"{h:g}s"] = {
            who: {
                kind: round(sums[who, kind, h] / max(counts[who, h], 1), 3)
                for kind in ("ade", "fde", "cv_ade", "cv_fde")
            }
            for who in ("ego", "agents")
        }
    return out


def format_table(scores: dict) -> str:
    """The scores as a small table (metres; lower is better)."""
    lines = [
        f"ADE / FDE in metres over {scores['windows']} windows ({scores['agent_tracks']} agent tracks); "
        f"predictor vs constant velocity",
        f"  {'horizon':8s} {'who':7s} {'ADE':>7s} {'cv ADE':>7s} {'FDE':>7s} {'cv FDE':>7s}",
    ]
    for h, row in scores["horizons"].items():
        for who, r in row.items():
            lines.append(f"  {h:8s} {who:7s} {r['ade']:7.3f} {r['cv_ade']:7.3f} {r['fde']:7.3f} {r['cv_fde']:7.3f}")
    return "\n".join(lines)


def load_predictor(workdir, *, option: str = "workdir"):
    """``(config, params, info)`` of a predictor run: its newest checkpoint's parameters (EMA when
    kept) and ``info`` (``bev_size``, the ``fps`` of its data and ``step_seconds``). Errors name
    ``option`` (how the caller calls ``workdir``)."""
    from jaxdrive.train.aux_run import load_trained

    path = Path(workdir) / INFO_FILE
    info = json.loads(path.read_text()) if path.is_file() else None

    def init(c):
        if info is None:
            raise ValueError(f"{option}: expected {path} (written by the predictor's training), found none")
        return init_params(c.predictor, jax.random.key(0), bev_size=tuple(info["bev_size"]))

    config, params = load_trained(workdir, PredictorRunConfig, "predictor", init, option=option, what="predictor")
    return config, params, info


def load_future_predictor(workdir, *, option: str = "workdir"):
    """A predictor run as :class:`jaxdrive.generate.future.FuturePredictor` (what ``jaxdrive sample
    --predictor RUN`` rolls forward): its config, newest parameters and the seconds of its step.
    Errors name ``option``."""
    config, params, info = load_predictor(workdir, option=option)
    return FuturePredictor(config.predictor, params, float(info["step_seconds"]))
