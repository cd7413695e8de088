"""Training the future-controls predictor: ``jaxdrive train --config configs/predictor.py:size=tiny``.

Windows of ``history + horizon`` steps (one step every ``predictor.stride`` source frames) are cut
from every clip of the dataset's split, held in memory as controls only (no video). The loss
rolls the predictor ``horizon`` steps forward on its own predictions (each step's map the recorded
BEV map of that step's true pose) and averages the position error in metres, plus 2 m per radian
of heading error, of the ego and of every agent seen at the target step. Same run directory
layout as a DiT run (``config.json``, ``checkpoints/``, ``metrics.jsonl``), atomic checkpoints and
exact resume (a step's windows are drawn from ``(train.seed, step)``); at the end the validation
split, when there is one, is scored (:mod:`jaxdrive.eval.motion`) into ``motion.json``.
"""

from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.config import PredictorRunConfig
from jaxdrive.data.traffic import clip_tracks
from jaxdrive.models.predictor import Predictor, Traffic, init_params, rollout, wrap
from jaxdrive.validate import check_positive_int

CONTROL_FIELDS = ("ego_to_world", "boxes", "box_classes", "box_ids", "box_valid", "bev_map")
YAW_METRES = 2.0            # metres of loss per radian of heading error
INFO_FILE = "predictor.json"


def check_predictor_config(config: PredictorRunConfig) -> None:
    p = config.predictor
    for name in ("history", "horizon", "stride", "width", "depth", "heads", "map_patch", "max_agents"):
        check_positive_int(f"predictor.{name}", getattr(p, name), minimum=2 if name == "history" else 1)
    if p.width % p.heads:
        raise ValueError(f"predictor.width: expected a multiple of predictor.heads = {p.heads}, got {p.width}")
    check_positive_int("data.batch_size", config.data.batch_size)
    check_positive_int("train.steps", config.train.steps)


def load_controls(path, split: str, *, max_agents: int) -> list[dict]:
    """The control fields of every clip of ``split`` (box slots padded or cut to ``max_agents``)."""
    from jaxdrive.data.pipeline import _pad_boxes
    from jaxdrive.data.tfds_io import open_source
    source = open_source(path, split)
    clips = []
    for i in range(len(source)):
        rec = source[i]
        clip = {k: np.asarray(rec[k]) for k in CONTROL_FIELDS}
        _pad_boxes(clip, max_agents, f"{split} clip {i}")
        clip["fps"] = float(rec["fps"])
        clips.append(clip)
    return clips


def window_traffic(clip: dict, frames: np.ndarray, history: int) -> dict:
    """Numpy traffic of ``clip`` at source ``frames`` (the tracks of the last history frame):
    ``Traffic`` fields of the first ``history`` steps and the targets of the rest."""
    sub = {k: clip[k][frames] for k in ("ego_to_world", "boxes", "box_classes", "box_ids", "box_valid")}
    tr = clip_tracks(sub, ref=history - 1)
    return {"ego": tr["ego"], "agents": tr["agents"], "seen": tr["seen"], "size": tr["size"], "z": tr["z"],
            "classes": np.maximum(tr["classes"], 0), "ids": tr["ids"], "bev": clip["bev_map"][frames]}


def to_traffic(w: dict, history: int) -> Traffic:
    """The history part of stacked windows (leading batch axis) as a device :class:`Traffic`."""
    f32 = lambda x: jnp.asarray(x, jnp.float32)
    return Traffic(ego=f32(w["ego"][:, :history]), agents=f32(w["agents"][:, :history]),
                   seen=jnp.asarray(w["seen"][:, :history]), size=f32(w["size"]), z=f32(w["z"]),
                   classes=jnp.asarray(w["classes"], jnp.int32), ids=jnp.asarray(w["ids"], jnp.int32))


class Windows:
    """Every window of ``history + horizon`` steps at ``stride`` in ``clips``; :meth:`batch` draws
    ``size`` of them for a step, from ``(seed, step)`` alone."""

    def __init__(self, clips: list[dict], history: int, horizon: int, stride: int, *, where: str):
        self.clips, self.history = clips, history
        self.offsets = stride * np.arange(history + horizon)
        self.index = [(c, s) for c, clip in enumerate(clips)
                      for s in range(len(clip["ego_to_world"]) - int(self.offsets[-1]))]
        if not self.index:
            longest = max((len(c["ego_to_world"]) for c in clips), default=0)
            raise ValueError(f"data.path: expected clips of at least {self.offsets[-1] + 1} frames ({where}: "
                             f"history {history} + horizon {horizon} steps at stride {stride}), got at most {longest}")

    def batch(self, size: int, seed: int, step: int) -> dict:
        rng = np.random.default_rng([seed, step])
        picks = rng.integers(len(self.index), size=size)
        ws = [window_traffic(self.clips[c], s + self.offsets, self.history) for c, s in
              (self.index[i] for i in picks)]
        return {k: np.stack([w[k] for w in ws]) for k in ws[0]}


def rollout_loss(model: Predictor, params, batch: dict, history: int):
    """The mean error of a ``horizon``-step rollout (module docstring) and its parts."""
    traffic = to_traffic(batch, history)
    bev = jnp.asarray(batch["bev"][:, history - 1:-1], jnp.float32)        # each step's current map
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


def train_predictor(config: PredictorRunConfig, workdir, *, log=print, progress: bool = True, on_step=None) -> dict:
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
    fps = clips[0]["fps"]          # what generation needs to run it: its map grid and its step in seconds
    info = {"bev_size": list(clips[0]["bev_map"].shape[1:3]), "fps": fps, "step_seconds": p.stride / fps}
    out = fit(config, workdir, params, lambda q, batch: rollout_loss(model, q, batch, p.history),
              lambda step: windows.batch(d.batch_size, d.shuffle_seed, step), files={INFO_FILE: info}, log=log,
              progress=progress, on_step=on_step)
    status, params = out["status"], out["params"]
    if status == "done":
        motion = _validate(config, params, workdir, log)
        if motion is not None:
            out["motion"] = motion
    return out


def _validate(config, params, workdir, log):
    """ADE / FDE on the validation split at the horizons its clips allow, into ``motion.json``."""
    from jaxdrive.data.tfds_io import open_source
    from jaxdrive.eval.motion import format_table, motion_errors
    try:
        open_source(config.data.path, "validation")
    except ValueError:
        return None
    clips = load_controls(config.data.path, "validation", max_agents=config.predictor.max_agents)
    from jaxdrive.data.scene_map import bev_range_of
    from jaxdrive.data.tfds_io import dataset_info
    scores = motion_errors(params, config.predictor, clips,
                           bev_range=bev_range_of(dataset_info(config.data.path)["metadata"]))
    if scores is None:
        log("validation clips too short for a 1 s horizon: no ADE / FDE")
        return None
    if jax.process_index() == 0:
        (Path(workdir) / "motion.json").write_text(json.dumps(scores, indent=1))
    log(format_table(scores))
    return scores


def load_predictor(workdir):
    """``(config, params, info)`` of a predictor run: its newest checkpoint's parameters (EMA when
    kept) and ``info`` (``bev_size``, the ``fps`` of its data and ``step_seconds``)."""
    from jaxdrive.train.aux_run import load_trained
    path = Path(workdir) / INFO_FILE
    info = json.loads(path.read_text()) if path.is_file() else None

    def init(c):
        if info is None:
            raise ValueError(f"--predictor: expected {path} (written by the predictor's training), found none")
        return init_params(c.predictor, jax.random.key(0), bev_size=tuple(info["bev_size"]))
    config, params = load_trained(workdir, PredictorRunConfig, "predictor", init, option="--predictor",
                                  what="predictor")
    return config, params, info
