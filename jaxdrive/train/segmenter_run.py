"""Training the segmentation evaluator: ``jaxdrive train --config configs/segmenter.py:size=tiny``.

Every ``data.stride``-th frame of every view of every clip of the split, resized to ``data.height
x data.width`` as the DiT's pipeline resizes them, is held in host memory (uint8) with its exact
class mask (:func:`jaxdrive.data.class_masks.class_masks` of the resized instance ids). A step draws
``data.batch_size`` frames from ``(data.shuffle_seed, step)`` alone (a resumed run sees the same
data) and degrades them as generations are degraded, so that the evaluator scores objects, not
sharpness: a random mix with a blurred copy, Gaussian noise, and a horizontal flip. The loss is
the pixel cross-entropy with class weights ``1 / sqrt(frequency)`` (objects are a few percent of
the pixels). Same run directory layout as a DiT run; at the end the validation split, when there
is one, gives the ceiling mIoU into ``segmenter.json``.
"""

from __future__ import annotations

import logging

import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.config import SegmenterRunConfig
from jaxdrive.data.class_masks import class_masks_of
from jaxdrive.models.segmenter import CLASSES, NUM_CLASSES, Segmenter, confusion, init_params, predict, summary
from jaxdrive.validate import check_positive_int

logger = logging.getLogger(__name__)
INFO_FILE = "segmenter.json"


def check_segmenter_config(config: SegmenterRunConfig) -> None:
    s, d = config.segmenter, config.data
    check_positive_int("segmenter.width", s.width)
    check_positive_int("segmenter.levels", s.levels, minimum=0)
    for name in ("height", "width"):
        size = getattr(d, name)
        if isinstance(size, bool) or not isinstance(size, int) or size < 2**s.levels or size % 2**s.levels:
            raise ValueError(
                f"data.{name}: expected a positive multiple of 2 ** segmenter.levels = {2**s.levels}, got {size!r}"
            )
    for name in ("views", "stride", "batch_size"):
        check_positive_int(f"data.{name}", getattr(d, name))
    check_positive_int("train.steps", config.train.steps)


def load_frames(path, split: str, *, size: tuple[int, int], views: int, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """``(frames uint8 [N, H, W, 3], masks uint8 [N, H, W])``: every ``stride``-th frame of the
    first ``views`` views of every clip of ``split``, resized to ``size``, and their class ids."""
    from jaxdrive.data.tfds_io import open_source
    from jaxdrive.data.transforms import sample_clip
    from jaxdrive.media import to_uint8

    source = open_source(path, split)
    frames, masks = [], []
    for i in range(len(source)):
        clip = source[i]
        have = int(np.shape(clip["ego_to_world"])[0])
        s = sample_clip(
            clip,
            size=size,
            frames=1 + (have - 1) // stride,
            stride=stride,
            views=list(range(views)),
            instances=True,
            where=f"{split} clip {i}",
        )
        frames.append(to_uint8(s["video"]).reshape(-1, *size, 3))
        masks.append(class_masks_of(s).astype(np.uint8).reshape(-1, *size))
    return np.concatenate(frames), np.concatenate(masks)


def class_weights(masks: np.ndarray) -> np.ndarray:
    """``1 / sqrt(frequency)`` per class, scaled to a pixel-weighted mean of 1 (absent classes 0)."""
    freq = np.bincount(masks.ravel(), minlength=NUM_CLASSES).astype(np.float64)
    freq /= freq.sum()
    w = np.where(freq > 0, 1.0 / np.sqrt(np.maximum(freq, 1e-12)), 0.0)
    return (w / (w * freq).sum()).astype(np.float32)


def degrade(frames: np.ndarray, masks: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """uint8 frames -> float32 in [-1, 1], each mixed with a 3x3-blurred copy by a random share,
    Gaussian noise of a random level (up to 0.1) added, half of them flipped with their masks."""
    x = frames.astype(np.float32) / 127.5 - 1.0
    pad = np.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)), mode="edge")
    blur = sum(pad[:, i : i + x.shape[1], j : j + x.shape[2]] for i in range(3) for j in range(3)) / 9.0
    n = len(x)
    mix = rng.uniform(0.0, 1.0, (n, 1, 1, 1)).astype(np.float32)
    x = (
        (1 - mix) * x
        + mix * blur
        + rng.uniform(0.0, 0.1, (n, 1, 1, 1)).astype(np.float32) * rng.standard_normal(x.shape).astype(np.float32)
    )
    flip = rng.random(n) < 0.5
    x[flip] = x[flip, :, ::-1]
    masks = masks.copy()  # the caller's array stays as it was
    masks[flip] = masks[flip, :, ::-1]
    return np.clip(x, -1.0, 1.0), masks


def pixel_loss(model: Segmenter, params, batch: dict, weights):
    logits = model.apply({"params": params}, jnp.asarray(batch["frames"]))
    labels = jnp.asarray(batch["masks"], jnp.int32)
    logp = jax.nn.log_softmax(logits, -1)
    nll = -jnp.take_along_axis(logp, labels[..., None], -1)[..., 0]
    w = jnp.asarray(weights)[labels]
    loss = jnp.sum(w * nll) / jnp.maximum(jnp.sum(w), 1e-6)
    accuracy = jnp.mean(jnp.argmax(logits, -1) == labels)
    return loss, {"pixel_accuracy": accuracy}


def train_segmenter(config: SegmenterRunConfig, workdir, *, progress: bool = True, on_step=None) -> dict:
    """Train (or resume) the segmenter in ``workdir``; returns ``{"step", "status", "loss",
    "params"}`` (and ``"validation"``, the ceiling scores of :func:`jaxdrive.models.segmenter.summary`,
    when the dataset has a validation split); ``status`` as a DiT run's."""
    from jaxdrive.train.aux_run import fit

    check_segmenter_config(config)
    s, d, t = config.segmenter, config.data, config.train
    size = (d.height, d.width)
    frames, masks = load_frames(d.path, d.split, size=size, views=d.views, stride=d.stride)
    weights = class_weights(masks)
    logger.info(
        "segmenter: %d frames of %d x %d from split %r; object pixels %s",
        len(frames),
        d.height,
        d.width,
        d.split,
        f"{(masks > 0).mean():.1%}",
    )
    model = Segmenter(s)

    def batch(step):
        rng = np.random.default_rng([d.shuffle_seed, step])
        pick = rng.integers(len(frames), size=d.batch_size)
        x, m = degrade(frames[pick], masks[pick], rng)
        return {"frames": x, "masks": m}

    info = {"size": list(size), "classes": list(CLASSES), "class_weights": [round(float(w), 4) for w in weights]}
    out = fit(
        config,
        workdir,
        init_params(s, jax.random.key(t.seed), size),
        lambda q, b: pixel_loss(model, q, b, weights),
        batch,
        files={INFO_FILE: info},
        progress=progress,
        on_step=on_step,
    )
    if out["status"] == "done":
        scores = _validate(config, out["params"], workdir, info)
        if scores is not None:
            out["validation"] = scores
    return out


def _validate(config, params, workdir, info):
    """The ceiling: mIoU on the validation split's recorded frames, into ``segmenter.json``."""
    import json
    from pathlib import Path

    from jaxdrive.data.tfds_io import open_source

    d = config.data
    try:
        open_source(d.path, "validation")
    except ValueError:
        return None
    frames, masks = load_frames(d.path, "validation", size=(d.height, d.width), views=d.views, stride=d.stride)
    pred = predict(config.segmenter, params, frames.astype(np.float32) / 127.5 - 1.0)
    scores = summary(confusion(pred, masks))
    if jax.process_index() == 0:
        (Path(workdir) / INFO_FILE).write_text(
            json.dumps({**info, "validation": scores, "validation_frames": len(frames)}, indent=1)
        )
    per_class = ", ".join(f"{k} {v:.3f}" for k, v in scores["per_class"].items() if v is not None and k != "background")
    logger.info("validation (%d recorded frames): mIoU %.3f (%s)", len(frames), scores["miou"], per_class)
    return scores
