"""LongDWM's coarse DiT: CogVideoX-2B's full 3D attention over [text; video] on CogVideoX VAE
latents, with the structure-preservation loss (sec. 3.3). Start from imported weights
(``jaxdrive.convert.load_diffusers_transformer``). Set ``data.path``, ``latents.vae_path`` and
``data.text_embeddings`` (T5, 226 tokens).

Fine-to-coarse distillation (sec. 3.3, eq. 7-8) trains this coarse model against a trained fine
run: ``--set flow.distill_teacher=runs/longdwm_fine --set flow.distill_segment_len=13 --set
data.frames=145 --set latents.vae_mode=frame_wise --set model.vae_temporal=1`` (LongDWM encodes
the coarse model's frames one by one, so segment ends are latent frames).
"""

from jaxdrive.config import Config, DataConfig, FlowConfig, LatentConfig, MeshConfig, OptimConfig, TrainConfig
from jaxdrive.models.dit_presets import preset


def get_config() -> Config:
    return Config(
        model=preset("cogvideox-2b", vae_spatial=8, vae_temporal=4, remat="dots", scan_layers=True,
                     controls=dict(cond_frames="replace")),
        data=DataConfig(path="data/nuscenes", frames=49, height=480, width=720, views=1, batch_size=8, threads=8),
        latents=LatentConfig(source="vae", vae_path="runs/cogvideox_vae"),
        flow=FlowConfig(shift=0.0, cond_frames=1, structure_weight=0.1),
        optim=OptimConfig(lr=2e-5, warmup_steps=500, ema_decay=0.0),
        train=TrainConfig(steps=20_000, log_every=50, checkpoint_every=1000, compute_dtype="bfloat16"),
        mesh=MeshConfig(data=-1, fsdp=8, seq=1),
    )
