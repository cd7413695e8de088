"""The segmentation evaluator of ``jaxdrive eval --segmenter``: ``--config configs/segmenter.py:size=S``.

A small U-Net (:mod:`jaxdrive.eval.segmenter`) trained on the recorded frames of a synthetic
dataset to give every pixel its object class, from the exact per-pixel instance ids the synthetic
world records (nuScenes has none). Train it on the DiT's dataset at the DiT's frame size
(``--set data.path=... data.height=... data.width=...``): it scores frames of that size.

``size=tiny``: width 32, 2 levels (~470k parameters), 32 x 56 frames of 6 views, every second
frame; 1500 steps of 32 frames. ``size=test``: width 16, 300 steps of 16 frames, what the test
suite trains in about a minute on 2 cores (it fits its two training scenes, mIoU 0.42-0.46 on their
frames; the same code path).
"""

from jaxdrive.config import (
    DataConfig,
    OptimConfig,
    SegmenterConfig,
    SegmenterRunConfig,
    TrainConfig,
    check_arg,
    parse_arg,
)


def get_config(arg=None) -> SegmenterRunConfig:
    a = parse_arg(arg, size="tiny")
    check_arg("size", a.size, ("tiny", "test"))
    if a.size == "tiny":
        segmenter = SegmenterConfig(width=32, levels=2)
        train = TrainConfig(steps=1500, log_every=50, checkpoint_every=500, keep_checkpoints=2)
    else:
        segmenter = SegmenterConfig(width=16, levels=2)
        train = TrainConfig(steps=300, log_every=50, checkpoint_every=0, keep_checkpoints=1)
    # test: 60% of the frames of 250 steps of 32 (4800, not 8000) for the same fit of the training
    # scenes (mIoU 0.42-0.46 on their frames, against 0.43-0.49; the tests need more than 0.3)
    batch = 32 if a.size == "tiny" else 16
    return SegmenterRunConfig(
        segmenter=segmenter,
        data=DataConfig(path="data/synth", height=32, width=56, views=6, stride=2, batch_size=batch),
        optim=OptimConfig(lr=2e-3, warmup_steps=50, schedule="cosine", ema_decay=0.99, clip_norm=1.0),
        train=train,
    )
