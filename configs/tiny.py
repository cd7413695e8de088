"""Tiny: the demo and the tests, minutes on a laptop CPU.

A 2-layer, 64-wide factorized DiT (MiLA-style: spatial attention over all views, eq. 3; cameras
and waypoints added to the tokens, eq. 1-2; the built-in caption encoder; clean condition
frames) on frame-wise space-to-depth latents of 32 x 56 synthetic clips, 6 views x 9 frames.

Why it learns on a CPU in minutes (``jaxdrive demo``):

- a token is 2 x 2 latents of 48 channels, 192 numbers, three times the width: the model predicts
  the clean latents (``prediction="data"``, Li & He 2025), which a narrow network can, where the
  velocity means passing the token's 192 numbers of noise through 64 (the samples were noise);
- every frame also sees the newest given frame at its own position, and the model predicts the
  change from it (``reference_frame="residual"``, as GenCast predicts the residual to the current
  state): freshly initialised it repeats the last given frame with all its detail, and the few
  hundred steps a CPU affords go into learning the motion, not into learning to copy;
- U-ViT's final 3x3 convolutions (``final_conv=32``): a 64-wide model's per-token output drew
  the token grid into the frames as 8 x 8-pixel blocks; the convolutions see across token seams
  (the demo's first window 17.42 -> 18.10 dB PSNR, at the repeat baseline, the blocks gone) at
  about 1.5x the step time;
- every training window has its two given frames (``cond_frames_random=False``): the demo only
  continues clips, and each step then trains exactly that.

Guidance: ``sample.cfg`` stays 1.0 (none), what the demo has always sampled with; the conditions
are still dropped 15% of the time (``data.drop_prob``), so ``--cfg`` / ``--cfg-route`` have nulls
to guide against.
"""

from jaxdrive.config import Config, DataConfig, FlowConfig, LatentConfig, OptimConfig, TrainConfig
from jaxdrive.models.dit.presets import preset


def get_config() -> Config:
    latents = LatentConfig(source="space_to_depth", factor=4)
    model = preset(
        "tiny",
        in_channels=3 * latents.factor**2,
        vae_spatial=latents.factor,
        vae_temporal=1,
        text_dim=64,
        text_len=16,
        patch=(1, 2, 2),
        prediction="data",
        final_conv=32,
        controls=dict(
            text="caption",
            caption_vocab=512,
            caption_layers=1,
            fps=True,
            camera=True,
            waypoints=True,
            cond_frames="replace",
            reference_frame="residual",
        ),
    )
    return Config(
        model=model,
        data=DataConfig(path="data/synth", frames=9, height=32, width=56, views=6, batch_size=2),
        latents=latents,
        flow=FlowConfig(shift=1.0, cond_frames=2, cond_frames_random=False),
        optim=OptimConfig(lr=1e-3, warmup_steps=20, schedule="cosine", ema_decay=0.99, clip_norm=1.0),
        train=TrainConfig(steps=800, log_every=10, checkpoint_every=200, keep_checkpoints=2, sample_steps=20),
    )
