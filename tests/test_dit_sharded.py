"""The DiT sharded over (data, fsdp, seq, tensor) meshes of 8 fake CPU devices matches the
single-device model: outputs and gradients (parameters and latents), for the factorized layout
with spatial attention over all views, the MVDiT layout with cross-view attention, the map
ControlNet, box tokens, condition frames and HTFT, the projected layout, and the full layout with scanned,
rematerialised layers. Parameters are sharded by their logical names
(FSDP over ``embed``, tensor parallel over heads and MLP features) and the spatial patches over
``seq``, so every sequence-sharded attention runs as a ring."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdrive.models.dit import DiT
from jaxdrive.models.dit.inputs import example_inputs
from jaxdrive.models.dit.presets import preset
from jaxdrive.parallel import make_mesh, shard_params

from dit_fixtures import boxed_params, conditions, max_rel, params_for, split_inputs, tree_max_rel

CASES = {
    "factorized-joint": (preset("tiny", depth=1), dict(data=2, seq=4), 2),
    # MVDiT with the controls whose tensors meet the sharded patches: cross-view attention, the map
    # ControlNet, box tokens (per-frame-and-view cross-attention), condition frames and HTFT
    "mvdit-controls": (
        preset("tiny-mv", depth=1, controls=dict(trajectory=False, warp=False, waypoints=False, camera=False)),
        dict(fsdp=2, seq=2, tensor=2),
        3,
    ),
    # the projected layout: ray casting, the BEV map's gather and the canvas's convolutions per
    # (frame, view) with the batch over data and the tokens over seq
    "layout": (preset("tiny", depth=1, controls=dict(layout=True)), dict(data=2, seq=2, tensor=2), 2),
    "full-scan-remat": (preset("tiny-full", scan_layers=True, remat="full"), dict(seq=8), 2),
    # the per-frame output head (overlapping output patches, U-ViT's final convolutions over
    # output, input and given frame) with its frames over seq
    "final-conv-frames-over-seq": (
        preset(
            "tiny",
            depth=1,
            prediction="data",
            final_conv=8,
            out_patches="overlap",
            controls=dict(cond_frames="replace", reference_frame="residual"),
        ),
        dict(data=2, seq=2, tensor=2),
        2,
    ),
}


def batch_sharded(tree, mesh):
    """Every array of ``tree`` with a batch axis put over the mesh's batch axes (data, fsdp), as
    the training step gets its batches (inputs given whole would never meet a reshape rule of
    Explicit sharding on a sharded batch axis)."""
    n = mesh.shape["data"] * mesh.shape["fsdp"]
    spec = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec(("data", "fsdp")))
    return jax.tree_util.tree_map(
        lambda a: jax.device_put(a, spec) if np.ndim(a) and np.shape(a)[0] % n == 0 else a, tree
    )


def _loss_fn(cfg):
    dit = DiT(cfg)

    def loss(params, lat, sig, text, kw):
        out = dit.forward(params, lat, sig, conditions(text, kw))
        return jnp.sum(out * jnp.cos(lat)), out

    return jax.jit(jax.value_and_grad(loss, argnums=(0, 1), has_aux=True))


@pytest.mark.slow(seconds=30)
@pytest.mark.parametrize("case", CASES)
def test_sharded_matches_single_device(case):
    cfg, mesh_shape, views = CASES[case]
    shapes = (("batch", 2), ("views", views), ("frames", 2), ("height", 8), ("width", 8))
    params = params_for(cfg, shapes, skip=())  # every branch live, zero inits perturbed
    lat, sig, text, kw = split_inputs(example_inputs(cfg, **dict(shapes)))
    fn = _loss_fn(cfg)
    (_, want), (gp_want, gx_want) = fn(params, lat, sig, text, kw)
    mesh = make_mesh(**mesh_shape)
    boxed = jax.tree_util.tree_map(
        lambda b, v: b.replace_boxed(v),
        boxed_params(cfg, shapes),
        params,
        is_leaf=lambda x: hasattr(x, "replace_boxed"),
    )
    with jax.set_mesh(mesh):
        sharded = shard_params(boxed, mesh)
        (_, got), (gp, gx) = fn(sharded, *batch_sharded((lat, sig, text, kw), mesh))
        if mesh_shape.get("fsdp", 1) > 1 or mesh_shape.get("tensor", 1) > 1:
            specs = {str(x.sharding.spec) for x in jax.tree_util.tree_leaves(sharded)}
            assert any("fsdp" in s for s in specs) and any("tensor" in s for s in specs)
    assert max_rel(got, want) < 1e-5
    assert max_rel(gx, gx_want) < 1e-4
    assert tree_max_rel(gp, gp_want) < 1e-4


@pytest.mark.slow(seconds=9)
def test_full_layout_on_a_one_device_explicit_mesh():
    """The [text; video] join with a seq axis of size 1 (a single-GPU run) matches no mesh."""
    cfg = preset("tiny-full")
    shapes = (("batch", 1), ("views", 1), ("frames", 2), ("height", 8), ("width", 8))
    params = params_for(cfg, shapes, skip=())
    lat, sig, text, kw = split_inputs(example_inputs(cfg, **dict(shapes)))
    want = _loss_fn(cfg)(params, lat, sig, text, kw)[0][1]
    with jax.set_mesh(make_mesh(devices=jax.devices()[:1])):
        got = _loss_fn(cfg)(params, lat, sig, text, kw)[0][1]
    assert max_rel(got, want) < 1e-6


@pytest.mark.slow(seconds=10)
def test_full_layout_whose_frame_tokens_the_seq_axis_does_not_divide():
    """LongDWM's distillation with one segment (2 keyframes of 30 x 45 tokens, 226 text tokens,
    seq=4) stopped at tracing: the clip's 2700 video tokens divide seq, a frame's 1350 do not, so
    the [text; video] join runs unsharded over seq, and it gave the 226 text tokens the video's
    seq-sharded layout. Here: 12 tokens a frame, 24 a clip, 7 text tokens, seq=8."""
    cfg = preset("tiny-full", text_len=7)
    shapes = (("batch", 2), ("views", 1), ("frames", 2), ("height", 8), ("width", 6))
    params = params_for(cfg, shapes, skip=())
    lat, sig, text, kw = split_inputs(example_inputs(cfg, **dict(shapes)))
    fn = _loss_fn(cfg)
    (_, want), (_, gx_want) = fn(params, lat, sig, text, kw)
    mesh = make_mesh(seq=8)
    with jax.set_mesh(mesh):
        (_, got), (_, gx) = fn(params, *batch_sharded((lat, sig, text, kw), mesh))
    assert max_rel(got, want) < 1e-5
    assert max_rel(gx, gx_want) < 1e-4
