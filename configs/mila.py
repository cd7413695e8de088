"""MiLA (Wang et al. 2025), every training stage: ``--config configs/mila.py:size=S,stage=N``.

``size=paper`` (default): the ~700M STDiT-2 preset (spatial attention over all views, eq. 3;
cameras + waypoints, Fourier + MLP, eq. 1-2; fps; text; clean condition frames) on 6 views at
256 x 448. ``size=tiny``: the same code path on the tiny model and synthetic data
(``configs/tiny.py``), minutes on a CPU; what the tests run.

Stages (appendix B):

1. next frames at ONE rate per clip, drawn from {1, 2, 12} fps (``data.rate_strides``); only the
   new modules (multi-view spatial attention, the condition embeddings), the last block and the
   output layer train (``optim.trainable``).
2. the condition frames fixed at 12 fps and the generated ones at a drawn rate
   (``data.rate_head``), every frame's time embedded (``controls.frame_time``); all parameters.
3. as 2, plus MiLA's tail anchor: with probability 0.75 the window's last frame is a JDC noisy
   anchor (eq. 8-12, made by ``flow.jdc_training_anchors`` exactly as the sampler makes it) that
   the loss counts (eq. 15); TPD levels (eq. 13-14) throughout. This model runs
   ``jaxdrive sample --strategy coarse-to-refine`` (anchors every 12 frames: one per second).

Where it follows the paper: the window (4 given + 12 generated frames), the rate sets, the 75%
anchor rate, TPD, the stage-1 trainable set, and the guidance: ``sample.cfg = 3.0`` at both sizes,
"a fixed classifier-free guidance scale of 3.0" (appendix B, Inference), against the nulls that
training learns by dropping each condition 15% of the time (appendix B, Training; ``data.drop_prob``).
With ``--set model.controls.boxes=true`` (boxes are not MiLA's, but the same code path takes
them) stage 1 trains the box encoder and its null too: the stage-1 set names the condition
embeddings by one pattern, which matches ``boxes_embed`` / ``boxes_null`` when they exist.
Where it differs, deliberately: latents are the CogVideoX VAE in frame-wise mode (MiLA's STDiT-2
uses a per-frame image VAE; a causal 3D VAE cannot compress frames of mixed rates, and coarse
anchors are single frames); JDC's g(t) is ``slope * sigma`` with slope 0.5 and alpha1 = 0.1 (the
paper gives neither constant); memory settings the paper does not give: full rematerialisation
and the frame-wise encode one frame of every clip per step (``latents.vae_frame_batch``), so a
step of 4 clips a device fits 80 GiB at fsdp 8 (docs/results/memory.md). Each stage starts from
the previous one with ``--set train.init_from=RUN_OF_STAGE_N-1``.

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
    SampleConfig,
    TrainConfig,
    check_arg,
    load_config,
    parse_arg,
)
from jaxdrive.models.dit.presets import preset

# stage 1's trainable set, regexes over "a/b/kernel" parameter paths: MiLA's new modules (the
# Fourier + MLP condition embeddings; its multi-view spatial attention is the spatial attention
# itself here, attending over all views, so it trains with the last block), the last block and
# the output layer. The embeddings are one pattern (a pattern must match some parameter): the box
# encoder and its null join it when boxes are on, also when --set turns them on after get_config
STAGE1_TRAINABLE = (
    r"^(camera_embed|waypoints_embed|boxes_embed)/|^boxes_null$",
    "fps_embedder",
    "layers_{last}/",
    "final",
    "proj_out",
)
GUIDANCE = 3.0  # appendix B, Inference: "a fixed classifier-free guidance scale of 3.0"


def _paper(stage: int) -> Config:
    # full rematerialisation and the frame-wise encode one frame of every clip at a time: with
    # remat "dots" (380 GiB as "dots_no_batch") or the whole encode (161 GiB) 4 clips a device at
    # fsdp 8 fit no 80 GiB device; as set, 62 GiB (jaxdrive plan, docs/results/memory.md)
    # scanned layers (a 28-layer unrolled step took over 12 minutes to compile, scanned 90 s), the
    # last one a run of its own: stage 1 trains it by name (layers_27)
    model = preset(
        "mila",
        in_channels=16,
        vae_spatial=8,
        vae_temporal=1,
        remat="full",
        scan_layers=True,
        controls=dict(camera=True, waypoints=True, cond_frames="replace", fps=True, frame_time=stage >= 2),
    )
    model = model.replace(scan_breaks=(model.depth - 1,))
    return Config(
        model=model,
        data=DataConfig(path="data/nuscenes", frames=16, height=256, width=448, views=6, batch_size=32, threads=8),
        latents=LatentConfig(source="vae", vae_path="runs/cogvideox_vae", vae_mode="frame_wise", vae_frame_batch=1),
        flow=FlowConfig(shift=0.0, cond_frames=4, cond_frames_random=False, tpd=True),
        optim=OptimConfig(lr=1e-4, warmup_steps=1000, ema_decay=0.9999, weight_decay=0.0),
        train=TrainConfig(
            steps={1: 2_000, 2: 20_000, 3: 8_000}[stage],
            log_every=50,
            checkpoint_every=1000,
            sample_every=5000,
            compute_dtype="bfloat16",
        ),
        mesh=MeshConfig(data=-1, fsdp=1, seq=1),
    )


def _tiny(stage: int) -> Config:
    base = load_config(Path(__file__).with_name("tiny.py"))
    model = base.model.replace(controls=dataclasses.replace(base.model.controls, frame_time=stage >= 2))
    return dataclasses.replace(
        base,
        model=model,
        data=dataclasses.replace(base.data, frames=8),  # 2 given + 6 generated frames
        flow=dataclasses.replace(base.flow, tpd=True),
        train=dataclasses.replace(base.train, steps={1: 100, 2: 300, 3: 200}[stage], checkpoint_every=100),
    )


def get_config(arg=None) -> Config:
    a = parse_arg(arg, size="paper", stage=3)
    check_arg("size", a.size, ("paper", "tiny"))
    check_arg("stage", a.stage, (1, 2, 3))
    config = _paper(a.stage) if a.size == "paper" else _tiny(a.stage)
    d, f = config.data, config.flow
    given = f.cond_frames
    fast = config.data.stride  # the source rate (12 fps): stride 1
    # {12, 2, 1} fps from a 12 fps source; the tiny clips are short, so {12, 2} fps
    strides = (1, 6, 12) if a.size == "paper" else (1, 6)
    data = dataclasses.replace(d, rate_strides=strides, rate_head=0 if a.stage == 1 else given * fast)
    flow = f
    if a.stage == 3:
        flow = dataclasses.replace(f, jdc_anchor_rate=0.75)  # MiLA's tail anchor, 75% of clips
    optim = config.optim
    if a.stage == 1:  # "{last}": the run's last layer (jaxdrive.train.optim.trainable_labels)
        optim = dataclasses.replace(optim, trainable=STAGE1_TRAINABLE)
    return dataclasses.replace(config, data=data, flow=flow, optim=optim, sample=SampleConfig(cfg=GUIDANCE))
