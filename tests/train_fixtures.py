"""Shared helpers of the training tests: small synthetic clip datasets on disk."""

from __future__ import annotations

# configs/tiny.py without the parts that only add compile time to a test of the run's machinery
# (signals, resume, checkpoints, processes, the compilation cache, buckets, a command's path):
# U-ViT's final convolutions and the caption encoder. The tiny step with depth 1 on data 2 x seq 4:
# 4.7 s of compiling and 14 CPU-s for a 6-step run, against 2.5 s and 8 CPU-s without them. The
# DiT's tests cover both parts.
MACHINERY = ["model.final_conv=0", "model.controls.text=none"]


def write_synthetic(out, *, first: int = 0, train: int = 3, frames: int = 9, views: int = 6):
    """``train`` synthetic scenes from seed ``first`` (``views`` views of 32 x 56) and one
    validation scene, written as a TFDS dataset at ``out``; returns ``out``."""
    from jaxdrive.data.synthetic import generate_clip
    from jaxdrive.data.tfds_io import write_dataset

    clips = lambda seed, n: (generate_clip(seed + i, views=views, frames=frames, height=32, width=56) for i in range(n))
    write_dataset(out, {"train": clips(first, train), "validation": clips(100, 1)}, name="jaxdrive_synthetic")
    return out


def write_same_clips(out, *, seed: int, frames: int, copies: int, shard_bytes: int | None = None):
    """``copies`` copies of one synthetic clip (6 views of 32 x 56) as the train split at ``out``:
    whichever clips a pipeline picks, in whatever order, it feeds the same samples (``shard_bytes``
    1: one clip per shard). Returns ``out``."""
    from jaxdrive.data.synthetic import generate_clip
    from jaxdrive.data.tfds_io import write_dataset

    write_dataset(
        out,
        {"train": (generate_clip(seed, views=6, frames=frames, height=32, width=56) for _ in range(copies))},
        name="jaxdrive_synthetic",
        **({} if shard_bytes is None else {"shard_bytes": shard_bytes}),
    )
    return out


def save_run(config, workdir, devices=None):
    """A run directory for ``config`` (its config.json and one checkpoint of the initial state on
    ``devices``, no training): e.g. the frozen fine model of a distillation. Returns the state saved."""
    import json
    from pathlib import Path

    from jaxdrive.config import to_dict
    from jaxdrive.train.checkpoint import Checkpoints
    from jaxdrive.train.run import CONFIG_FILE, Run

    state = Run(config, devices=devices).init_state()[0]
    ckpts = Checkpoints(workdir, asynchronous=False)
    ckpts.save(0, state, {}, {"step": 0})
    ckpts.close()
    (Path(workdir) / CONFIG_FILE).write_text(json.dumps(to_dict(config)))
    return state


def train_with_a_stop(config, workdir, *, stop_at: int):
    """Train in ``workdir``, SIGTERM after step ``stop_at``, then run the same command again;
    returns ``(interrupted summary, resumed summary)``."""
    import os
    import signal

    from jaxdrive.train.run import train

    def stop(step, metrics):
        if step == stop_at:
            os.kill(os.getpid(), signal.SIGTERM)

    part = train(config, workdir, progress=False, on_step=stop)
    return part, train(config, workdir, progress=False)


def assert_same_state(a, b):
    """Every leaf of two train states (params, Adam moments, EMA, rng) bit for bit."""
    import jax
    import numpy as np

    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def tiny_run(workdir, data, *sets):
    """A 6-view one-layer tiny DiT (``configs/tiny.py``, boxes on, 5-frame windows) trained 1 step on
    ``data`` in ``workdir``, on the 8 test devices (data 2 x seq 4); returns ``workdir``."""
    from pathlib import Path

    from jaxdrive.cli import main as cli

    args = [
        "train",
        "--config",
        str(Path(__file__).resolve().parents[1] / "configs" / "tiny.py"),
        "--workdir",
        str(workdir),
        "--steps",
        "1",
        "--no-progress",
    ]
    for s in (
        f"data.path={data}",
        "model.controls.boxes=true",
        "model.depth=1",  # its users test sampling, eval and routes, not the depth
        "model.final_conv=0",  # nor U-ViT's final convolutions: every sampler compiles them
        "data.frames=5",
        "data.views=6",
        "data.batch_size=2",
        "mesh.data=2",
        "mesh.seq=4",
        *sets,
    ):
        args += ["--set", s]
    assert cli(args) == 0
    return workdir
