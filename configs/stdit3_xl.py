"""Open-Sora 1.2's STDiT-3 XL/2 (1.2B) on CogVideoX VAE latents of 6-view clips, FSDP-sharded:
the size of the papers' factorized backbones, for a TPU pod or a GPU cluster.
Set ``data.path``, ``latents.vae_path`` and ``data.text_embeddings``.
"""

from jaxdrive.config import Config, DataConfig, FlowConfig, LatentConfig, MeshConfig, OptimConfig, TrainConfig
from jaxdrive.models.dit.presets import preset


def get_config() -> Config:
    return Config(
        model=preset("stdit3-xl/2", in_channels=16, vae_spatial=8, vae_temporal=4, remat="dots", scan_layers=True),
        data=DataConfig(path="data/nuscenes", frames=33, height=256, width=448, views=6, batch_size=64, threads=8),
        latents=LatentConfig(source="vae", vae_path="runs/cogvideox_vae"),
        flow=FlowConfig(shift=0.0, cond_frames=1),
        optim=OptimConfig(lr=1e-4, warmup_steps=1000, ema_decay=0.9999),
        train=TrainConfig(steps=200_000, log_every=50, checkpoint_every=1000, compute_dtype="bfloat16"),
        mesh=MeshConfig(data=-1, fsdp=8, seq=1),
    )
