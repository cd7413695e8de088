"""MagicDrive-V2 (Gao et al. 2025), progressive training: ``--config configs/magicdrive_v2.py:size=S,stage=N``.

``size=paper`` (default): STDiT-3 XL/2 with MVDiT cross-view attention and all its controls (text,
cameras, ego trajectory, 3D boxes, the BEV map ControlNet) on CogVideoX VAE latents of 6-view
nuScenes clips. ``size=tiny``: the same code path on the tiny model (``configs/tiny.py``) and
synthetic data, minutes on a CPU of 8 devices (``JAXDRIVE_CPU_DEVICES=8``: its mesh is
``data=2, seq=4`` in every stage); what the tests run. It takes MagicDrive-V2's own control
scheme, not tiny.py's: cross-view attention between neighbouring views (MVDiT), the ego
trajectory, the 3D boxes and the BEV map (a ControlNet of one block, 16 channels wide) beside the
cameras, instead of MiLA's waypoints; tiny.py's training aids (the caption encoder, clean given
frames, the residual to the last given frame) stay.

Stages (sec. 4.5, appendix B table I; each starts from the previous one with
``--set train.init_from=RUN_OF_STAGE_N-1``):

1. images at 224 x 400; the model is spatial-only (``model.temporal="off"``); 80k steps.
2. images and 9 / 17 / 33 / 65-frame videos at 224 x 400, images and 9 / 17 / 33 frames at
   424 x 800; the temporal blocks are added, zero-initialised (``"zero_init"``), so the stage-1
   model's outputs are unchanged when it is loaded; 40k steps, lr warm-up 3000 steps.
3. images, 17 and 241 frames ("full") at 224 x 400; images, 17 / 33 / 65 / 129 at 424 x 800;
   images, 9 / 17 / 33 at 848 x 1600; sequence parallel 4 (``mesh.seq=4``); 30k steps.

Every bucket is ``data.buckets`` ``HxWxF:batch:prob``. Its batch balances the step time, as the
paper balances it against the slowest video format at batch 1 (appendix B, E): here each
bucket's batch per data-parallel group is the slowest bucket's token count over its own (capped
at ``MAX_GROUP_BATCH``), a starting point to refine with ``jaxdrive bench buckets``; its
probability is its batch, so that every bucket gets about the same number of batches an epoch
(the paper repeats the scarce long clips to the same end; here every bucket's repeat is
``auto``, :class:`jaxdrive.data.batch_plan.BatchPlan`, so the tiny stages fill every bucket from a
dataset of three scenes). Sampling: rectified flow, 30 steps,
classifier-free guidance 2 (``sample.cfg``, below).

Where it deliberately differs: 424 x 800 is 416 x 800 (the latent grid must divide into 2 x 2
patches: 424 / 8 = 53 latent rows); batch sizes assume the paper's 32 GPUs (8 data-parallel
groups in stage 3) and scale with your mesh; the paper's learning rate and CFG scale did not
survive in our copy of its text ("the classifier-free-guidance (CFG) scale at ."; appendix E):
lr 8e-5 (Open-Sora 1.2's, on which it builds) and guidance 2.0, the ``cfg_scale=2.0`` of the
authors' released test configs (MagicDriveDiT, ``configs/magicdrive/test/17-16x848x1600_..._cfg2.0.py``,
"base value 1, 0 is uncond": our convention) and MagicDrive's own scale (Gao et al. 2024), not
Open-Sora's 7.0 for text-to-video prompts; the nulls it guides against are learned by dropping
each condition 15% of the time (appendix E; ``data.drop_prob``).
Set ``data.path``, ``latents.vae_path`` and ``data.text_embeddings`` at paper size.
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

MAX_GROUP_BATCH = {"paper": 8, "tiny": 2}
# (height, width): frames, per stage (table I); 0 stands for the stage's longest ("full") clip
PAPER = {
    1: {(224, 400): (1,)},
    2: {(224, 400): (1, 9, 17, 33, 65), (416, 800): (1, 9, 17, 33)},
    3: {(224, 400): (1, 17, 241), (416, 800): (1, 17, 33, 65, 129), (848, 1600): (1, 9, 17, 33)},
}
TINY = {  # the same table at tiny resolutions, frames up to 33
    1: {(16, 32): (1,)},
    2: {(16, 32): (1, 9, 17, 33), (32, 32): (1, 9, 17)},
    3: {(16, 32): (1, 17, 33), (32, 32): (1, 17, 33), (32, 56): (1, 9, 17)},
}
STEPS = {"paper": {1: 80_000, 2: 40_000, 3: 30_000}, "tiny": {1: 60, 2: 60, 3: 40}}
GUIDANCE = 2.0  # the authors' released test configs' cfg_scale (module docstring)


def balanced_buckets(
    table: dict, *, spatial: int, temporal: int, patch: int, groups: int, max_group_batch: int
) -> tuple[str, ...]:
    """``data.buckets`` for ``{(H, W): frames}``: each bucket's batch per group is the largest
    bucket's token count over its own, at least 1 and at most ``max_group_batch`` (a lone bucket
    takes the most), times ``groups``; its probability is that batch (equal batch counts per epoch)."""

    def tokens(h, w, f):
        return (1 + (f - 1) // temporal) * (h // (spatial * patch)) * (w // (spatial * patch))

    shapes = [(h, w, f) for (h, w), frames in table.items() for f in frames]
    most = max(tokens(*s) for s in shapes)
    out = []
    for h, w, f in shapes:
        # one bucket (stage 1's images) has nothing to balance against: the largest batch
        per_group = max_group_batch if len(shapes) == 1 else min(max(1, most // tokens(h, w, f)), max_group_batch)
        out.append(f"{h}x{w}x{f}:{per_group * groups}:{per_group}")
    return tuple(out)


def _largest(table: dict) -> tuple[int, int, int]:
    """The (H, W, F) a stage samples at: its highest resolution at that resolution's longest clip."""
    (h, w), frames = max(table.items(), key=lambda kv: kv[0][0] * kv[0][1])
    return h, w, max(frames)


def _paper(stage: int) -> Config:
    temporal = {1: "off", 2: "zero_init", 3: "on"}[stage]
    table = PAPER[stage]
    h, w, f = _largest(table)
    groups = 8 if stage == 3 else 32
    buckets = balanced_buckets(
        table, spatial=8, temporal=4, patch=2, groups=groups, max_group_batch=MAX_GROUP_BATCH["paper"]
    )
    return Config(
        # full rematerialisation and the 3D VAE encoding one clip's view of every device at a time:
        # its stage-3 bucket 848 x 1600 x 9, 3 clips a device, encoded at once held 420 GiB
        model=preset("magicdrive-v2", vae_spatial=8, vae_temporal=4, remat="full", scan_layers=True, temporal=temporal),
        data=DataConfig(
            path="data/nuscenes", frames=f, height=h, width=w, views=6, batch_size=groups, threads=8, buckets=buckets
        ),
        latents=LatentConfig(source="vae", vae_path="runs/cogvideox_vae", vae_clip_batch=1),
        flow=FlowConfig(shift=0.0, cond_frames=1),
        optim=OptimConfig(lr=8e-5, warmup_steps=0 if stage == 1 else 3000, schedule="constant", ema_decay=0.9999),
        train=TrainConfig(
            steps=STEPS["paper"][stage], log_every=50, checkpoint_every=1000, compute_dtype="bfloat16", sample_steps=30
        ),
        mesh=MeshConfig(data=-1, fsdp=1, seq=4 if stage == 3 else 1),
        sample=SampleConfig(cfg=GUIDANCE),
    )


def _tiny(stage: int) -> Config:
    base = load_config(Path(__file__).with_name("tiny.py"))
    table = TINY[stage]
    h, w, f = _largest(table)
    m = base.model
    buckets = balanced_buckets(
        table,
        spatial=base.latents.factor,
        temporal=1,
        patch=m.patch[1],
        groups=2,
        max_group_batch=MAX_GROUP_BATCH["tiny"],
    )
    controls = dataclasses.replace(
        m.controls, waypoints=False, trajectory=True, boxes=True, map=True, map_blocks=1, map_hidden=16
    )
    model = m.replace(temporal={1: "off", 2: "zero_init", 3: "on"}[stage], multiview="cross_view", controls=controls)
    return dataclasses.replace(
        base,
        model=model,
        data=dataclasses.replace(base.data, frames=f, height=h, width=w, batch_size=2, buckets=buckets),
        train=dataclasses.replace(base.train, steps=STEPS["tiny"][stage], checkpoint_every=20),
        mesh=MeshConfig(data=2, seq=4),
        sample=SampleConfig(cfg=GUIDANCE),
    )


def get_config(arg=None) -> Config:
    a = parse_arg(arg, size="paper", stage=3)
    check_arg("size", a.size, ("paper", "tiny"))
    check_arg("stage", a.stage, (1, 2, 3))
    return _paper(a.stage) if a.size == "paper" else _tiny(a.stage)
