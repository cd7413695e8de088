"""The segmentation evaluator's network, its inference and its scores: a small U-Net that gives
every pixel of a frame its object class (:data:`CLASSES`), the classes of many frames batch-sharded
over a mesh (:func:`predict`), and the confusion counts and IoU of predicted classes against true
ones (:func:`confusion`, :func:`summary`).

Why and how it is used (trained on recorded frames, scored on generated ones):
:mod:`jaxdrive.eval.segmenter`; its training: :mod:`jaxdrive.train.segmenter_run`.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import cast

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.classes import OBJECT_CLASSES
from jaxdrive.parallel.batches import extract

CLASSES = ("background",) + OBJECT_CLASSES
NUM_CLASSES = len(CLASSES)


@dataclasses.dataclass(frozen=True)
class SegmenterConfig:
    """The segmentation evaluator (:class:`Segmenter`, :mod:`jaxdrive.eval.segmenter`): a small
    U-Net that gives every pixel of a frame its object class (:data:`CLASSES`: background or one of
    ``OBJECT_CLASSES``); its run: :class:`jaxdrive.config.SegmenterRunConfig`, which re-exports
    this class."""

    width: int = 32  # channels at full resolution, doubled at every level
    levels: int = 2  # stride-2 downsamplings (frame sides divisible by 2**levels)


class _ConvBlock(nn.Module):
    features: int
    stride: int = 1

    @nn.compact
    def __call__(self, x):
        x = nn.Conv(self.features, (3, 3), strides=self.stride, padding="SAME")(x)
        return nn.silu(nn.GroupNorm(num_groups=min(8, self.features))(x))


class Segmenter(nn.Module):
    """A U-Net: two 3x3 convolutions per level, ``levels`` stride-2 downsamplings doubling the
    width, bilinear upsampling with skip connections; logits ``[..., H, W, NUM_CLASSES]`` from
    frames ``[..., H, W, 3]`` in [-1, 1]."""

    config: SegmenterConfig

    @nn.compact
    def __call__(self, frames):
        c = self.config
        lead = frames.shape[:-3]
        x = frames.reshape(-1, *frames.shape[-3:])
        skips = []
        for level in range(c.levels + 1):
            width = c.width * 2**level
            x = _ConvBlock(width, stride=1 if level == 0 else 2)(x)
            x = _ConvBlock(width)(x)
            skips.append(x)
        for level in reversed(range(c.levels)):
            skip = skips[level]
            x = jax.image.resize(x, (x.shape[0], *skip.shape[1:3], x.shape[-1]), "bilinear")
            x = _ConvBlock(c.width * 2**level)(jnp.concatenate([x, skip], -1))
            x = _ConvBlock(c.width * 2**level)(x)
        logits = nn.Conv(NUM_CLASSES, (1, 1))(x)
        return logits.reshape(*lead, *logits.shape[1:])


def init_params(config: SegmenterConfig, key, size: tuple[int, int] = (32, 56)):
    """Fresh parameters for ``size`` frames, initialised in one jitted program (run eagerly, each
    layer's initialiser and forward op would compile on its own), compiled once per config and
    size."""
    return _init_params(config, key, tuple(size))


@functools.partial(jax.jit, static_argnums=(0, 2))
def _init_params(config: SegmenterConfig, key, size: tuple[int, ...]):
    return Segmenter(config).init(key, jnp.zeros((1, *size, 3), jnp.float32))["params"]


@functools.partial(jax.jit, static_argnums=0)
def _classes(config: SegmenterConfig, params, frames):
    # apply without mutable= returns the output alone (the stub's return also allows the (output, vars) tuple)
    logits = cast(jax.Array, Segmenter(config).apply({"params": params}, frames))
    return jnp.argmax(logits, -1).astype(jnp.int32)


def predict(config: SegmenterConfig, params, frames, *, batch_size: int = 256, mesh=None) -> np.ndarray:
    """Class ids ``int32 [..., H, W]`` of frames ``[..., H, W, 3]`` in [-1, 1], ``batch_size``
    frames per jitted call, each batch split over the ``mesh``'s batch axes when one is given
    (:func:`jaxdrive.parallel.batches.extract`)."""
    frames = np.asarray(frames, np.float32)
    lead, hw = frames.shape[:-3], frames.shape[-3:-1]
    flat = frames.reshape(-1, *frames.shape[-3:])
    if not len(flat):
        return np.zeros((*lead, *hw), np.int32)
    params = jax.device_get(params)  # host arrays: replicated onto whatever mesh the call runs on
    out = extract(lambda p, x: _classes(config, p, x), params, flat, batch_size=batch_size, mesh=mesh)
    return out.reshape(*lead, *hw)


def confusion(pred, truth, num_classes: int = NUM_CLASSES) -> np.ndarray:
    """``int64 [C, C]`` counts of (true class, predicted class) over all pixels of ``pred`` and
    ``truth`` (same shape); sums of these over parts equal the counts of the whole."""
    pred, truth = np.asarray(pred), np.asarray(truth)
    if pred.shape != truth.shape:
        raise ValueError(f"pred: expected the shape of truth {list(truth.shape)}, got {list(pred.shape)}")
    idx = truth.astype(np.int64).ravel() * num_classes + pred.astype(np.int64).ravel()
    return np.bincount(idx, minlength=num_classes * num_classes).reshape(num_classes, num_classes)


def summary(counts: np.ndarray) -> dict:
    """From :func:`confusion` counts: ``per_class`` IoU (``|pred & truth| / |pred | truth|``;
    None where neither has the class), ``miou``: the mean IoU over the object classes either
    side has (background left out: it is most of every frame), None if there are none, and
    ``pixel_accuracy``."""
    counts = np.asarray(counts, np.float64)
    inter = np.diag(counts)
    union = counts.sum(0) + counts.sum(1) - inter
    iou = np.where(union > 0, inter / np.maximum(union, 1), np.nan)
    objects = iou[1:][union[1:] > 0]
    return {
        "miou": float(objects.mean()) if objects.size else None,
        "per_class": {name: (None if np.isnan(v) else round(float(v), 4)) for name, v in zip(CLASSES, iou)},
        "pixel_accuracy": float(inter.sum() / max(counts.sum(), 1)),
    }
