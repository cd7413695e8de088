"""MiLA: the ~700M STDiT-2 preset (spatial attention over all views, cameras + waypoints, fps,
text, clean condition frames) with TPD (eq. 13-14) and JDC anchors (sec. 3.3) in training, on
CogVideoX VAE latents. Stage 1 trains only the new modules, the last block and the output layer
(appendix B): ``--set optim.trainable=...`` with the regexes of those parameters.

Set ``data.path`` (a dataset from ``jaxdrive data nuscenes``), ``latents.vae_path`` and
``data.text_embeddings`` (``jaxdrive data text-embed`` with a local T5) for your data.
"""

from jaxdrive.config import Config, DataConfig, FlowConfig, LatentConfig, MeshConfig, OptimConfig, TrainConfig
from jaxdrive.models.dit_presets import preset


def get_config() -> Config:
    return Config(
        model=preset("mila", in_channels=16, vae_spatial=8, vae_temporal=4, remat="dots", scan_layers=True),
        data=DataConfig(path="data/nuscenes", frames=33, height=256, width=448, views=6, batch_size=32, threads=8),
        latents=LatentConfig(source="vae", vae_path="runs/cogvideox_vae"),
        flow=FlowConfig(shift=0.0, cond_frames=3, tpd=True, jdc_anchor_rate=0.5),
        optim=OptimConfig(lr=1e-4, warmup_steps=1000, ema_decay=0.9999, weight_decay=0.0),
        train=TrainConfig(steps=100_000, log_every=50, checkpoint_every=1000, sample_every=5000,
                          compute_dtype="bfloat16"),
        mesh=MeshConfig(data=-1, fsdp=1, seq=1),
    )
