"""Small: one GPU. A 4-layer, 256-wide factorized DiT on CogVideoX VAE latents (16 channels, 8x
spatial, 4x temporal) of 6-view, 17-frame, 256 x 448 clips, with cameras, waypoints, boxes and
the caption encoder; bf16 compute, fp32 master weights.

Needs a VAE: ``jaxdrive convert vae CogVideoX-2b/vae runs/vae`` (or a fine-tuned one), then
``--set latents.vae_path=runs/vae``.
"""

from jaxdrive.config import Config, DataConfig, FlowConfig, LatentConfig, OptimConfig, TrainConfig
from jaxdrive.models.dit.presets import preset


def get_config() -> Config:
    model = preset(
        "small",
        in_channels=16,
        vae_spatial=8,
        vae_temporal=4,
        text_dim=256,
        text_len=32,
        controls=dict(text="caption", fps=True, camera=True, waypoints=True, boxes=True, cond_frames="replace"),
    )
    return Config(
        model=model,
        data=DataConfig(path="data/synth", frames=17, height=256, width=448, views=6, batch_size=4, threads=4),
        latents=LatentConfig(source="vae", vae_path="runs/vae", vae_mode="chunked"),
        flow=FlowConfig(shift=0.0, cond_frames=1),
        optim=OptimConfig(lr=2e-4, warmup_steps=500, ema_decay=0.999),
        train=TrainConfig(
            steps=50_000, log_every=50, checkpoint_every=1000, sample_every=5000, compute_dtype="bfloat16"
        ),
    )
