"""Controllability against exact ground truth: a segmentation evaluator and its mIoU.

MagicDrive-V2 (sec. 5.1 "Evaluation Metrics", tables 2-3) judges how well generations follow
their boxes and maps by running perception models on them (BEVFormer's mAP and BEV mIoU on videos;
BEVFusion's mAP and CVT's road mIoU on images). jaxdrive's synthetic world
knows every pixel's object (``instance_ids``, the track id of the box that drew it), so it can do
better: a small U-Net (:class:`Segmenter`, ~470k parameters at width 32) is trained on recorded
synthetic frames to give each pixel its class (:data:`CLASSES`: background, then
``jaxdrive.classes.OBJECT_CLASSES``); its mIoU on held-out recorded frames against their exact class masks
is the ceiling, and its mIoU on generated frames against the class masks of the boxes they were
conditioned on says how well generation follows the boxes. A generation whose boxes were
shuffled between clips (``jaxdrive eval --shuffle-boxes``) scores against the masks of the boxes
it got; one that ignores its boxes then scores clearly lower.

- :func:`class_masks` (:func:`class_masks_of` a sample): instance ids + the boxes of each frame
  -> per-pixel class ids (:mod:`jaxdrive.data.class_masks`);
- :class:`Segmenter`, :func:`init_params`, :func:`predict` (jitted, batch-sharded);
  :func:`confusion` (counts, summed over any number of frames) and :func:`summary` (per-class
  IoU, the mIoU over the object classes, pixel accuracy) (:mod:`jaxdrive.models.segmenter`);
- :func:`load_segmenter`: a trained run (:mod:`jaxdrive.train.segmenter_run`).

The masks, the network and the scores live below the segmenter's training, which scores its
validation split with them too, and are re-exported here.
"""

from __future__ import annotations

import jax
import numpy as np

from jaxdrive.data.class_masks import class_masks, class_masks_of  # noqa: F401
from jaxdrive.models.segmenter import (  # noqa: F401
    CLASSES,
    NUM_CLASSES,
    Segmenter,
    SegmenterConfig,
    confusion,
    init_params,
    predict,
    summary,
)


class TrainedSegmenter:
    """A trained segmenter: ``classes(frames)`` as :func:`predict`; ``size`` is the frame size
    (height, width) it was trained at."""

    def __init__(self, config, params, size):
        self.config, self.params, self.size = config, jax.device_get(params), tuple(size)

    def classes(self, frames, *, batch_size: int = 256, mesh=None) -> np.ndarray:
        return predict(self.config.segmenter, self.params, frames, batch_size=batch_size, mesh=mesh)


def load_segmenter(workdir, *, option: str = "workdir") -> TrainedSegmenter:
    """The newest checkpoint of a segmenter run (``jaxdrive train --config configs/segmenter.py``);
    errors name ``option`` (how the caller calls ``workdir``)."""
    from jaxdrive.config import SegmenterRunConfig
    from jaxdrive.train.aux_run import load_trained

    init = lambda c: init_params(c.segmenter, jax.random.key(0), (c.data.height, c.data.width))
    config, params = load_trained(workdir, SegmenterRunConfig, "segmenter", init, option=option, what="segmenter")
    return TrainedSegmenter(config, params, (config.data.height, config.data.width))
