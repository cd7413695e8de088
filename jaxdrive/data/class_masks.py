"""Exact per-pixel object classes of a recorded clip: the ground truth the segmentation evaluator
(:mod:`jaxdrive.eval.segmenter`) is trained on and scored against.

A clip with ``instance_ids`` (the synthetic world's: the track id of the box that drew each
pixel, -1 where no object did) and its boxes gives every pixel its class: 0 for background,
``1 + class`` (:data:`jaxdrive.classes.OBJECT_CLASSES`) for an object; the segmenter's classes
(:data:`jaxdrive.models.segmenter.CLASSES`) in that order.
"""

from __future__ import annotations

import numpy as np


def class_masks(instance_ids, box_ids, box_classes, box_valid) -> np.ndarray:
    """Per-pixel class ids ``int32 [..., V, F, H, W]`` (0 background, ``1 + class`` of the box
    whose track id drew the pixel) from ``instance_ids [..., V, F, H, W]`` (-1 where no object)
    and each frame's boxes ``box_ids``, ``box_classes``, ``box_valid`` ``[..., F, N]``. Pixels of
    ids no valid box of their frame carries stay background."""
    inst = np.asarray(instance_ids)
    ids, classes, valid = (np.asarray(x) for x in (box_ids, box_classes, box_valid))
    if (
        inst.ndim < 4
        or ids.shape != classes.shape
        or ids.shape != valid.shape
        or ids.shape[:-1] != inst.shape[:-4] + (inst.shape[-3],)
    ):
        raise ValueError(
            f"instance_ids: expected [..., V, F, H, W] with boxes [..., F, N] of the same frames, got "
            f"instance_ids {list(inst.shape)}, box_ids {list(ids.shape)}, box_classes "
            f"{list(classes.shape)}, box_valid {list(valid.shape)}"
        )
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
