"""STAGE (Wang et al. 2025), every training stage: ``--config configs/stage.py:size=S,stage=N``.

STAGE streams a driving video frame by frame: frame T from the anchor frame (the first, for global
consistency), the condition frame (T - 1) and its own controls (3D boxes and the BEV map), with
HTFT fusing the same layers' features of frames T-1, T-5 and T-10 at the same denoising step
from a FIFO of the last 10 frames (sec. 4B). ``jaxdrive sample --strategy streaming`` samples it.

``size=paper`` (default): a STDiT-3 DiT (spatial attention over all views, temporal attention over
the 3-frame window, cross-attention to box tokens, the BEV map ControlNet) on frame-wise CogVideoX
VAE latents of 6 views at 512 x 768, 12 Hz nuScenes. ``size=tiny``: the same code path on the tiny
model and synthetic data (``configs/tiny.py`` plus boxes and the map), minutes on a CPU; what the
tests run.

Stages (sec. 4C):

1. streaming learning: windows ``[anchor, condition, new]`` from recorded clips, HTFT off
   (``stream.taps=()``; the model has no HTFT layers yet).
2. HTFT learning: ``model.htft_layers`` added (zero-initialised output: the stage-1 model's outputs
   unchanged), only their parameters trained (``optim.trainable``), from stage 1
   (``train.init_from``, required). The past features come from a no-gradient pass over the clip.
3. learning through simulating inference: all parameters; the condition frames are the model's
   own streaming rollout of the clip, run once per clip (``stream.self_rollout``).

DCT degradation of a share of the condition frames and noise on them in every stage (STAGE's
augmentation); the foreground-weighted loss W_aux (``flow.foreground_k``). ``size=tiny`` leaves
the degradation out, puts more noise on the condition frames (0.1 instead of 0.02) and trains
stage 1 for 1000 steps, as measured on its 145-frame stream of a validation scene (PSNR of all
generated frames; the scene's repeat-the-last-frame baseline is 19.4 dB, noise about 16 dB):

| stage 1 | streamed as generated | clipped to the latents' range |
|---|---|---|
| 300 steps, STAGE's augmentation (30% DCT-degraded, noise 0.02) | 6.7 dB | |
| 300 steps, no degradation, noise 0.02 | 12.3 dB | 15.6 dB |
| 300 steps, no degradation, noise 0.1 | 14.1 dB | 16.7 dB |
| 300 steps, no degradation, noise 0.3 | 8.4 dB | |
| 1000 steps, no degradation, noise 0.1 | | 17.6 dB |

With 30% of the condition frames low-passed, the tiny model cannot tell a degraded condition
frame from a sharp one and learns to sharpen them all, which, fed back frame after frame,
compounds into saturated stripes; noise teaches it to pull a perturbed condition frame back
(too much, 0.3, and it blurs the scene away). Streamed frames are always clipped to the
latents' range (``jaxdrive.generate.streaming.in_range``).

What maps to what (STAGE uses an SD U-Net; jaxdrive has one DiT): the U-Net's mid-block
features, where HTFT reads and writes, are the outputs of the DiT layers in ``htft_layers``
(the middle layer); "the latent of frame T" is one frame-wise VAE latent frame, so a 3-frame
window is anchor, condition and new; STAGE's noise-prediction loss is the rectified-flow velocity
loss (jaxdrive's one convention). Where the paper is silent (steps, learning rates, the
degradation share, the stage-3 rollout's steps) the values below are choices. Guidance:
``sample.cfg`` stays 1.0 (none): the paper uses no classifier-free guidance. Each stage starts
from the previous one with ``--set train.init_from=RUN_OF_STAGE_N-1``.

Set ``data.path``, ``latents.vae_path`` and ``data.text_embeddings`` for your data (paper size).
"""

import dataclasses
from pathlib import Path

from jaxdrive.config import (
    Config,
    DataConfig,
    FlowConfig,
    LatentConfig,
    MeshConfig,
    OptimConfig,
    StreamConfig,
    TrainConfig,
    check_arg,
    load_config,
    parse_arg,
)
from jaxdrive.models.dit.presets import preset

HTFT_TRAINABLE = ("htft_",)  # stage 2: only the HTFT modules' parameters


def _paper(stage: int) -> Config:
    # scanned layers: the step runs the model in the stage-3 rollout, the feature pass and the
    # gradient window, and 28 + 13 (ControlNet) unrolled layers in each made its compile take
    # over 15 minutes; init_from moves the layers between the runs the HTFT layer splits
    # full rematerialisation and the frame-wise encode one frame of every clip at a time (as MiLA):
    # with them stage 3 plans 31 GiB a device at fsdp 32 (docs/results/memory.md)
    model = preset(
        "stdit3-xl/2",
        in_channels=16,
        vae_spatial=8,
        vae_temporal=1,
        remat="full",
        scan_layers=True,
        controls=dict(camera=True, boxes=True, map=True, map_blocks=13, cond_frames="replace", fps=True),
    )
    return Config(
        model=model,
        data=DataConfig(path="data/nuscenes", frames=12, height=512, width=768, views=6, batch_size=32, threads=8),
        latents=LatentConfig(source="vae", vae_path="runs/cogvideox_vae", vae_mode="frame_wise", vae_frame_batch=1),
        flow=FlowConfig(shift=0.0, cond_frames=1, foreground_k=1.0, foreground_c=0.5),
        optim=OptimConfig(lr=1e-4, warmup_steps=1000, ema_decay=0.9999),
        train=TrainConfig(
            steps={1: 40_000, 2: 20_000, 3: 10_000}[stage],
            log_every=50,
            checkpoint_every=1000,
            compute_dtype="bfloat16",
            sample_steps=30,
        ),
        mesh=MeshConfig(data=-1, fsdp=1, seq=1),
        stream=StreamConfig(enabled=True, rollout_steps=10, degrade_rate=0.3, degrade_keep=0.5, cond_noise=0.02),
    )


def _tiny(stage: int) -> Config:
    base = load_config(Path(__file__).with_name("tiny.py"))
    controls = dataclasses.replace(base.model.controls, boxes=True, map=True, map_blocks=1)
    return dataclasses.replace(
        base,
        model=base.model.replace(controls=controls),
        data=dataclasses.replace(base.data, frames=12),  # frame j's taps -1, -5, -10 all inside the clip
        flow=dataclasses.replace(base.flow, cond_frames=1, foreground_k=1.0),
        train=dataclasses.replace(base.train, steps={1: 1000, 2: 100, 3: 50}[stage], checkpoint_every=100),
        stream=StreamConfig(enabled=True, rollout_steps=4, degrade_rate=0.0, cond_noise=0.1),
    )


def get_config(arg=None) -> Config:
    a = parse_arg(arg, size="paper", stage=3)
    check_arg("size", a.size, ("paper", "tiny"))
    check_arg("stage", a.stage, (1, 2, 3))
    config = _paper(a.stage) if a.size == "paper" else _tiny(a.stage)
    model, stream, optim = config.model, config.stream, config.optim
    if a.stage == 1:
        stream = dataclasses.replace(stream, taps=())
    else:
        model = model.replace(htft_layers=(model.depth // 2 - 1,))
    if a.stage == 2:
        optim = dataclasses.replace(optim, trainable=HTFT_TRAINABLE)
    stream = dataclasses.replace(stream, self_rollout=a.stage == 3)
    return dataclasses.replace(config, model=model, stream=stream, optim=optim)
