"""The future-controls predictor (STAGE [2506.13138v1] sec. D, MILE's role): ``--config configs/predictor.py:size=S``.

Trained on the controls of the same datasets as the DiTs (``jaxdrive train --config
configs/predictor.py:size=tiny --set data.path=...``); ``jaxdrive sample --predictor RUN`` rolls it
forward when a clip's recorded controls end, or from the given frames with ``--controls
predicted`` (:mod:`jaxdrive.models.predictor`).

``size=tiny``: 2 layers of width 64, 8 past steps of 1/6 s (stride 2 at 12 Hz), trained on
8-step rollouts: a minute or two on a CPU, and the test suite's size. ``size=small``: 4 layers of
width 128, 16 past steps, 16-step rollouts; the same code path.
"""

from jaxdrive.config import (
    DataConfig,
    OptimConfig,
    PredictorConfig,
    PredictorRunConfig,
    TrainConfig,
    check_arg,
    parse_arg,
)


def get_config(arg=None) -> PredictorRunConfig:
    a = parse_arg(arg, size="tiny")
    check_arg("size", a.size, ("tiny", "small"))
    if a.size == "tiny":
        predictor = PredictorConfig(history=8, horizon=8, stride=2, width=64, depth=2, heads=4, map_patch=16)
        train = TrainConfig(steps=1500, log_every=50, checkpoint_every=500, keep_checkpoints=2)
        batch = 32
    else:
        predictor = PredictorConfig(history=16, horizon=16, stride=2, width=128, depth=4, heads=4, map_patch=8)
        train = TrainConfig(steps=20000, log_every=100, checkpoint_every=2000, keep_checkpoints=3)
        batch = 64
    return PredictorRunConfig(
        predictor=predictor,
        data=DataConfig(path="data/synth", batch_size=batch),
        optim=OptimConfig(lr=1e-3, warmup_steps=100, schedule="cosine", ema_decay=0.99, clip_norm=1.0),
        train=train,
    )
