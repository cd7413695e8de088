"""MagicDrive-V2: STDiT-3 XL/2 with MVDiT cross-view attention and all its controls (text,
cameras, ego trajectory, 3D boxes, the BEV map ControlNet) on CogVideoX VAE latents of 6-view
clips; the sequence sharded over ``seq`` (the paper needs 8-way sequence parallelism for its
longest clips). Set ``data.path``, ``latents.vae_path`` and ``data.text_embeddings``.
"""

from jaxdrive.config import Config, DataConfig, FlowConfig, LatentConfig, MeshConfig, OptimConfig, TrainConfig
from jaxdrive.models.dit_presets import preset


def get_config() -> Config:
    return Config(
        model=preset("magicdrive-v2", vae_spatial=8, vae_temporal=4, remat="dots", scan_layers=True),
        data=DataConfig(path="data/nuscenes", frames=33, height=424, width=800, views=6, batch_size=8, threads=8),
        latents=LatentConfig(source="vae", vae_path="runs/cogvideox_vae"),
        flow=FlowConfig(shift=0.0, cond_frames=1),
        optim=OptimConfig(lr=8e-5, warmup_steps=1000, ema_decay=0.9999),
        train=TrainConfig(steps=100_000, log_every=50, checkpoint_every=1000, compute_dtype="bfloat16"),
        mesh=MeshConfig(data=-1, fsdp=1, seq=8),
    )
