"""Tiny: the demo and the tests, a few minutes on a laptop CPU.

A 2-layer, 64-wide factorized DiT (MiLA-style: spatial attention over all views, eq. 3; cameras
and waypoints added to the tokens, eq. 1-2; the built-in caption encoder; clean condition
frames) on frame-wise space-to-depth latents of 32 x 56 synthetic clips, 6 views x 9 frames.
"""

from jaxdrive.config import Config, DataConfig, FlowConfig, LatentConfig, OptimConfig, TrainConfig
from jaxdrive.models.dit_presets import preset


def get_config() -> Config:
    latents = LatentConfig(source="space_to_depth", factor=4)
    model = preset("tiny", in_channels=3 * latents.factor ** 2, vae_spatial=latents.factor, vae_temporal=1,
                   text_dim=64, text_len=16, patch=(1, 2, 2),
                   controls=dict(text="caption", caption_vocab=512, caption_layers=1, fps=True, camera=True,
                                 waypoints=True, cond_frames="replace"))
    return Config(
        model=model,
        data=DataConfig(path="data/synth", frames=9, height=32, width=56, views=6, batch_size=2),
        latents=latents,
        flow=FlowConfig(shift=1.0, cond_frames=2),
        optim=OptimConfig(lr=1e-3, warmup_steps=20, schedule="cosine", ema_decay=0.99, clip_norm=1.0),
        train=TrainConfig(steps=300, log_every=10, checkpoint_every=100, keep_checkpoints=2, sample_steps=20),
    )
