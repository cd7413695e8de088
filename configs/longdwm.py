"""LongDWM (Wang et al. 2025), every role: ``--config configs/longdwm.py:size=S,role=R``.

``size=paper`` (default): CogVideoX-2B's transformer (full 3D attention over [text; video],
structure-preservation loss, sec. 3.3) on CogVideoX VAE latents, front camera at 480 x 720; start
from imported weights (``train.init_from`` a diffusers folder). ``size=tiny``: the same code path
on the tiny model and synthetic data (``configs/tiny.py``), minutes on a CPU; what the tests run.

Roles:

- ``coarse`` (CDiT, sec. 3.1): few frames from long clips, one keyframe every ``K - 1 = 12``
  frames (1 fps from 12), the first frame given; frames encoded one by one (frame-wise VAE), as
  LongDWM encodes the coarse model's frames.
- ``fine`` (FDiT, sec. 3.2, eq. 6): ``K = 13`` consecutive frames; the last frame is dropped with
  a fixed ratio (50%: the paper does not give it), so the model learns prediction (``prefix``)
  and interpolation (``ends``: first and last frame given). It fills the segments between the
  coarse keyframes: ``jaxdrive sample --workdir COARSE --fine-workdir FINE --strategy coarse-fine``.
- ``distill`` (sec. 3.3, eq. 7-8): the coarse model trained against a frozen fine run
  (``flow.distill_teacher``: set it to the fine run's directory) on dense clips of 145 frames,
  encoded one frame at a time (``latents.vae_frame_batch=1``): the 145 frames encoded at once
  need 105 GiB of temporaries a chip on a v5p-64 (fsdp=8, seq=4), one at a time 28 GiB (XLA:TPU,
  docs/results/memory.md).

Where it follows the paper: the two models, K = 13, the structure loss, the fine model's two
tasks, the distillation. Where it differs, deliberately: rectified flow (velocity ``noise - x``,
jaxdrive's one convention) where LongDWM fine-tunes CogVideoX's v-prediction; both models on
frame-wise latents (the fine model's segment ends are then exactly the coarse keyframes, where
LongDWM hands keyframes over as decoded frames to a 3D VAE); 1 + 12k-frame horizons.
Guidance: ``sample.cfg`` stays 1.0 (none), as the paper samples without classifier-free guidance
(it names no scale); ``jaxdrive sample --cfg S`` guides against the nulls that the 15% drops
(``data.drop_prob``) train.

Set ``data.path``, ``latents.vae_path`` and ``data.text_embeddings`` (T5, 226 tokens) at paper size.
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
    TrainConfig,
    check_arg,
    load_config,
    parse_arg,
)
from jaxdrive.models.dit.presets import preset

SEGMENT = 13  # K: frames of a fine segment; keyframes every K - 1


def _paper(role: str) -> Config:
    return Config(
        model=preset(
            "cogvideox-2b",
            vae_spatial=8,
            vae_temporal=1,
            remat="dots",
            scan_layers=True,
            controls=dict(cond_frames="replace"),
        ),
        data=DataConfig(path="data/nuscenes", frames=SEGMENT, height=480, width=720, views=1, batch_size=8, threads=8),
        latents=LatentConfig(source="vae", vae_path="runs/cogvideox_vae", vae_mode="frame_wise"),
        flow=FlowConfig(shift=0.0, cond_frames=1, cond_frames_random=False, structure_weight=0.1),
        optim=OptimConfig(lr=2e-5, warmup_steps=500, ema_decay=0.0),
        train=TrainConfig(steps=20_000, log_every=50, checkpoint_every=1000, compute_dtype="bfloat16"),
        mesh=MeshConfig(data=-1, fsdp=8, seq=1),
    )


def _tiny(role: str) -> Config:
    base = load_config(Path(__file__).with_name("tiny.py"))
    return dataclasses.replace(
        base,
        flow=dataclasses.replace(base.flow, cond_frames=1, structure_weight=0.1),
        train=dataclasses.replace(base.train, steps=300, checkpoint_every=100),
    )


def get_config(arg=None) -> Config:
    a = parse_arg(arg, size="paper", role="coarse")
    check_arg("size", a.size, ("paper", "tiny"))
    check_arg("role", a.role, ("coarse", "fine", "distill"))
    config = _paper(a.role) if a.size == "paper" else _tiny(a.role)
    seg = config.data.frames  # K: the fine window
    d, f = config.data, config.flow
    if a.role == "coarse":  # the coarse model's frames are the keyframes: every K - 1 frames
        data = dataclasses.replace(d, stride=seg - 1)
        flow = f
    elif a.role == "fine":  # eq. 6: the last frame given (interpolation) or not (prediction)
        data = d
        flow = dataclasses.replace(f, patterns=("prefix", "ends"), pattern_rates=(0.5, 0.5))
    else:  # eq. 7-8: the coarse frames of a dense clip of n (K - 1) + 1 frames
        data = dataclasses.replace(d, frames=(seg - 1) * (4 if a.size == "tiny" else 12) + 1)
        flow = dataclasses.replace(f, distill_teacher="runs/longdwm_fine", distill_segment_len=seg)
        if a.size == "paper":
            config = dataclasses.replace(config, latents=dataclasses.replace(config.latents, vae_frame_batch=1))
    return dataclasses.replace(config, data=data, flow=flow)
