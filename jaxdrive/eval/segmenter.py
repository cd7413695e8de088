"""Controllability against exact ground truth: a segmentation evaluator and its mIoU.

MagicDrive-V2 (sec. 5.1 "Evaluation Metrics", tables 2-3) judges how well generations follow
their boxes and maps by running perception models on them (BEVFormer's mAP and BEV mIoU on videos;
BEVFusion's mAP and CVT's road mIoU on images). jaxdrive's synthetic world
knows every pixel's object (``instance_ids``, the track id of the box that drew it), so it can do
better: a small U-Net (:class:`Segmenter`, ~470k parameters at width 32) is trained on recorded
synthetic frames to give each pixel its class (:data:`CLASSES`: background, then
``schema.OBJECT_CLASSES``); its mIoU on held-out recorded frames against their exact class masks
is the ceiling, and its mIoU on generated frames against the class masks of the boxes they were
conditioned on says how well generation follows the boxes. A generation whose boxes were
shuffled between clips (``jaxdrive eval --shuffle-boxes``) scores against the masks of the boxes
it got; one that ignores its boxes then scores clearly lower.

- :func:`class_masks` (:func:`class_masks_of` a sample): instance ids + the boxes of each frame
  -> per-pixel class ids;
- :class:`Segmenter`, :func:`init_params`, :func:`predict` (jitted, batch-sharded);
- :func:`confusion` (counts, summed over any number of frames) and :func:`summary` (per-class
  IoU, the mIoU over the object classes, pixel accuracy);
- :func:`load_segmenter`: a trained run (:mod:`jaxdrive.train.segmenter_run`).
"""

from __future__ import annotations

import functools

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from jaxdrive.config import SegmenterConfig
from jaxdrive.data.schema import OBJECT_CLASSES

CLASSES = ("background",) + OBJECT_CLASSES
NUM_CLASSES = len(CLASSES)


def class_masks(instance_ids, box_ids, box_classes, box_valid) -> np.ndarray:
    """Per-pixel class ids ``int32 [..., V, F, H, W]`` (0 background, ``1 + class`` of the box
    whose track id drew the pixel) from ``instance_ids [..., V, F, H, W]`` (-1 where no object)
    and each frame's boxes ``box_ids``, ``box_classes``, ``box_valid`` ``[..., F, N]``. Pixels of
    ids no valid box of their frame carries stay background."""
    inst = np.asarray(instance_ids)
    ids, classes, valid = (np.asarray(x) for x in (box_ids, box_classes, box_valid))
    if inst.ndim < 4 or ids.shape != classes.shape or ids.shape != valid.shape or \
            ids.shape[:-1] != inst.shape[:-4] + (inst.shape[-3],):
        raise ValueError(f"instance_ids: expected [..., V, F, H, W] with boxes [..., F, N] of the same frames, got "
                         f"instance_ids {list(inst.shape)}, box_ids {list(ids.shape)}, box_classes "
                         f"{list(classes.shape)}, box_valid {list(valid.shape)}")
    lead, (V, F, H, W) = inst.shape[:-4], inst.shape[-4:]
    inst = inst.reshape(-1, V, F, H * W)
    ids, classes, valid = (x.reshape(-1, F, x.shape[-1]) for x in (ids, classes, valid))
    out = np.zeros(inst.shape, np.int32)
    for b in range(inst.shape[0]):
        for f in range(F):
            keep = valid[b, f] & (ids[b, f] >= 0)
            if not keep.any():
                continue
            order = np.argsort(ids[b, f][keep])
            table_ids, table_cls = ids[b, f][keep][order], classes[b, f][keep][order]
            px = inst[b, :, f]
            at = np.clip(np.searchsorted(table_ids, px), 0, len(table_ids) - 1)
            hit = (px >= 0) & (table_ids[at] == px)
            out[b, :, f] = np.where(hit, table_cls[at] + 1, 0)
    return out.reshape(*lead, V, F, H, W)


def class_masks_of(sample) -> np.ndarray:
    """:func:`class_masks` of a sample of :func:`jaxdrive.data.pipeline.sample_clip` taken with
    ``instances=True``: ``[V, F, H, W]``."""
    return class_masks(sample["instance_ids"], sample["box_ids"], sample["box_classes"], sample["box_valid"])


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
            width = c.width * 2 ** level
            x = _ConvBlock(width, stride=1 if level == 0 else 2)(x)
            x = _ConvBlock(width)(x)
            skips.append(x)
        for level in reversed(range(c.levels)):
            skip = skips[level]
            x = jax.image.resize(x, (x.shape[0], *skip.shape[1:3], x.shape[-1]), "bilinear")
            x = _ConvBlock(c.width * 2 ** level)(jnp.concatenate([x, skip], -1))
            x = _ConvBlock(c.width * 2 ** level)(x)
        logits = nn.Conv(NUM_CLASSES, (1, 1))(x)
        return logits.reshape(*lead, *logits.shape[1:])


def init_params(config: SegmenterConfig, key, size: tuple[int, int] = (32, 56)):
    return Segmenter(config).init(key, jnp.zeros((1, *size, 3), jnp.float32))["params"]


@functools.partial(jax.jit, static_argnums=0)
def _classes(config: SegmenterConfig, params, frames):
    return jnp.argmax(Segmenter(config).apply({"params": params}, frames), -1).astype(jnp.int32)


def predict(config: SegmenterConfig, params, frames, *, batch_size: int = 256, mesh=None) -> np.ndarray:
    """Class ids ``int32 [..., H, W]`` of frames ``[..., H, W, 3]`` in [-1, 1], ``batch_size``
    frames per jitted call, each batch split over the ``mesh``'s batch axes when one is given
    (:func:`jaxdrive.eval.features.extract`)."""
    from jaxdrive.eval.features import extract
    frames = np.asarray(frames, np.float32)
    lead, hw = frames.shape[:-3], frames.shape[-3:-1]
    flat = frames.reshape(-1, *frames.shape[-3:])
    if not len(flat):
        return np.zeros((*lead, *hw), np.int32)
    params = jax.device_get(params)          # host arrays: replicated onto whatever mesh the call runs on
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
    return {"miou": float(objects.mean()) if objects.size else None,
            "per_class": {name: (None if np.isnan(v) else round(float(v), 4)) for name, v in zip(CLASSES, iou)},
            "pixel_accuracy": float(inter.sum() / max(counts.sum(), 1))}


class TrainedSegmenter:
    """A trained segmenter: ``classes(frames)`` as :func:`predict`; ``size`` is the frame size
    (height, width) it was trained at."""

    def __init__(self, config, params, size):
        self.config, self.params, self.size = config, jax.device_get(params), tuple(size)

    def classes(self, frames, *, batch_size: int = 256, mesh=None) -> np.ndarray:
        return predict(self.config.segmenter, self.params, frames, batch_size=batch_size, mesh=mesh)


def load_segmenter(workdir, *, option: str = "--segmenter") -> TrainedSegmenter:
    """The newest checkpoint of a segmenter run (``jaxdrive train --config configs/segmenter.py``)."""
    from jaxdrive.config import SegmenterRunConfig
    from jaxdrive.train.aux_run import load_trained
    init = lambda c: init_params(c.segmenter, jax.random.key(0), (c.data.height, c.data.width))
    config, params = load_trained(workdir, SegmenterRunConfig, "segmenter", init, option=option, what="segmenter")
    return TrainedSegmenter(config, params, (config.data.height, config.data.width))
