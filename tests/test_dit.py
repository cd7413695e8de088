"""The diffusion transformer on one device: shapes with every control, per-frame noise levels,
zero-initialised branches, classifier-free-guidance nulls, scan/remat, presets and bad input."""

import dataclasses
import functools
import json

import flax.linen as nn
import flax.traverse_util
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdrive.models.dit import DiT, param_count
from jaxdrive.models.dit.blocks import CrossView
from jaxdrive.models.dit.config import CONDITIONS
from jaxdrive.models.dit.controls import frame_mode, group_frames
from jaxdrive.models.dit.inputs import example_inputs
from jaxdrive.models.dit.presets import PRESETS, preset
from jaxdrive.models.params import host_init

from dit_fixtures import BRANCH_ZERO, boxed_params, conditions, forward_fn, max_rel, params_for, perturb, split_inputs

# 6 views x (1 + 4k) frames with k = 1: 5 pixel frames of conditions, 2 latent frames
MV = preset("tiny-mv", depth=1)  # every control; one layer keeps compiling short
MV_SHAPES = (("batch", 2), ("views", 6), ("frames", 2), ("height", 4), ("width", 4))
LEARNED_NULLS = ("text", "fps", "camera", "waypoints", "trajectory", "boxes")


def _mv_inputs(seed=0):
    return split_inputs(example_inputs(MV, seed=seed, **dict(MV_SHAPES)))


def _mv_forward(*args):
    return forward_fn(MV, return_features=True)(*args)[0]


def _no_drop(b=2):
    return {k: np.zeros(b, bool) for k in CONDITIONS}


def _check_shapes_with_every_control():
    params = params_for(MV, MV_SHAPES)
    lat, sig, text, kw = _mv_inputs()
    assert kw["boxes"].shape[1] == 5 and kw["bev_map"].shape[1] == 5 and lat.shape[:3] == (2, 6, 2)
    out, feats = forward_fn(MV, return_features=True)(params, lat, sig, text, dict(kw, drop=_no_drop()))
    assert out.shape == lat.shape and out.dtype == jnp.float32
    assert np.isfinite(np.asarray(out)).all() and float(jnp.std(out)) > 0
    assert set(feats) == {0} and feats[0].shape == (2, 2, 4, 6, MV.width)


def _check_zero_initialised_branches_leave_the_output_unchanged():
    params = params_for(MV, MV_SHAPES)  # branch projections stay at zero
    lat, sig, text, kw = _mv_inputs()
    fwd = _mv_forward
    full = fwd(params, lat, sig, text, dict(kw, drop=_no_drop()))
    _, _, _, other = _mv_inputs(seed=5)  # different map, warp, past features, cond
    for name in ("bev_map", "warp", "features"):
        changed = fwd(params, lat, sig, text, dict(kw, drop=_no_drop(), **{name: other[name]}))
        np.testing.assert_array_equal(changed, full, err_msg=name)
    off = {k: v for k, v in kw.items() if k not in ("bev_map", "warp", "features", "features_mask")}
    np.testing.assert_allclose(fwd(params, lat, sig, text, dict(off, drop=_no_drop())), full, atol=1e-6)
    # the test can fail: once a branch's zero projection is trained, its input matters
    for part in ("map_in", "warp_proj", "linear_out"):
        trained = perturb(params, skip=tuple(n for n in BRANCH_ZERO if n not in (part, "out")))
        base = fwd(trained, lat, sig, text, dict(kw, drop=_no_drop()))
        key = {"map_in": "bev_map", "warp_proj": "warp", "linear_out": "features"}[part]
        moved = fwd(trained, lat, sig, text, dict(kw, drop=_no_drop(), **{key: other[key]}))
        assert max_rel(moved, base) > 1e-4, part


def test_cross_view_attention_starts_as_a_no_op():
    x = jax.random.normal(jax.random.PRNGKey(0), (1, 2, 4, 6, MV.width))
    mod = CrossView(MV)
    variables = nn.unbox(host_init(mod, x))
    apply = jax.jit(mod.apply)
    np.testing.assert_array_equal(apply(variables, x), 0.0)
    trained = perturb(variables)
    assert float(jnp.abs(apply(trained, x)).max()) > 1e-3


def _check_dropped_conditions_equal_the_null_path():
    params = params_for(MV, MV_SHAPES)
    params = perturb(params, skip=())  # branches trained too: drops must still hold
    lat, sig, text, kw = _mv_inputs()
    _, _, text2, other = _mv_inputs(seed=7)
    fwd = _mv_forward
    half = np.array([True, False])
    drop = {k: half for k in CONDITIONS}
    dropped = fwd(params, lat, sig, text, dict(kw, drop=drop))
    kept = fwd(params, lat, sig, text, dict(kw, drop=_no_drop()))
    np.testing.assert_allclose(dropped[1], kept[1], atol=1e-6)  # undropped sample unchanged
    # a dropped sample does not see its conditions: other values, same output
    swapped = {
        **kw,
        **{
            k: other[k]
            for k in (
                "fps",
                "intrinsics",
                "cam_to_ego",
                "waypoints",
                "ego_to_world",
                "boxes",
                "box_classes",
                "box_valid",
                "bev_map",
                "warp",
            )
        },
    }
    again = fwd(params, lat, sig, text2, dict(swapped, drop=drop))
    np.testing.assert_allclose(again[0], dropped[0], atol=1e-6)
    assert max_rel(again[1], dropped[1]) > 1e-4
    # the learned nulls: leaving a condition out is dropping it; a dropped map is the zero map
    only = {k: half if k in LEARNED_NULLS else np.zeros(2, bool) for k in CONDITIONS}
    part = fwd(params, lat, sig, text, dict(kw, drop=only))
    gone = (
        "text_mask",
        "fps",
        "intrinsics",
        "cam_to_ego",
        "waypoints",
        "ego_to_world",
        "boxes",
        "box_classes",
        "box_valid",
    )
    absent = {k: v for k, v in kw.items() if k not in gone}
    nulls = fwd(params, lat, sig, None, dict(absent, drop=_no_drop()))
    np.testing.assert_allclose(nulls[0], part[0], atol=1e-5)
    zero_map = fwd(params, lat, sig, text, dict(kw, bev_map=np.zeros_like(kw["bev_map"]), drop=_no_drop()))
    map_drop = fwd(
        params, lat, sig, text, dict(kw, drop={k: (half if k == "map" else np.zeros(2, bool)) for k in CONDITIONS})
    )
    np.testing.assert_allclose(map_drop[0], zero_map[0], atol=1e-6)
    assert max_rel(map_drop[1], zero_map[1]) > 1e-4


@pytest.mark.slow(seconds=20)
def test_mvdit_with_every_control_on_six_views():
    """One test for the checks that share the compiled all-controls model (compiling dominates;
    separate tests would compile it once per test worker): the output and feature shapes for
    6 views x (1 + 4k) frames, the zero-initialised branches (map ControlNet, warp injection,
    HTFT) leaving the output unchanged, and dropped conditions equal to the null path."""
    _check_shapes_with_every_control()
    _check_zero_initialised_branches_leave_the_output_unchanged()
    _check_dropped_conditions_equal_the_null_path()


TINY = preset("tiny", controls=dict(cond_frames="replace"))
TINY_SHAPES = (("batch", 2), ("views", 2), ("frames", 4), ("height", 4), ("width", 4))


@functools.cache
def _apply_with_intermediates(cfg):
    dit = DiT(cfg)
    return jax.jit(
        lambda p, lat, sig, text, kw: dit.apply(
            {"params": p}, lat, sig, conditions(text, kw), mutable=["intermediates"]
        )
    )


def _intermediates(cfg, params, lat, sig, text, kw):
    out, state = _apply_with_intermediates(cfg)(params, lat, sig, text, kw)
    inter = state["intermediates"]
    return out, inter["tokens"][0], inter["modulation"][0]


@pytest.mark.slow(seconds=7)
@pytest.mark.parametrize("cfg", [TINY, preset("tiny-full")], ids=["factorized", "full"])
def test_one_frames_sigma_changes_only_that_frames_modulation(cfg):
    """One frame's sigma changes that frame's modulation and nothing upstream of it in any frame's
    inputs; a [B] sigma is every frame at that level; (factorized, sharing its compiled model)
    condition frames are modulated at sigma 0."""
    shapes = TINY_SHAPES
    params = params_for(cfg, shapes)
    lat, sig, text, kw = split_inputs(example_inputs(cfg, **dict(shapes)))
    if "cond_mask" in kw:  # no condition frame here (same inputs, one compile)
        kw["cond_mask"] = np.zeros_like(kw["cond_mask"])
    sig = np.asarray([[0.9, 0.7, 0.5, 0.3], [0.2, 0.4, 0.6, 0.8]], np.float32)
    out, tokens, mod = _intermediates(cfg, params, lat, sig, text, kw)
    sig2 = sig.copy()
    sig2[:, 2] = [0.05, 0.95]
    out2, tokens2, mod2 = _intermediates(cfg, params, lat, sig2, text, kw)
    assert mod.shape[:2] == (2, 4)
    np.testing.assert_array_equal(tokens2, tokens)  # the inputs of every frame
    others = [0, 1, 3]
    np.testing.assert_array_equal(np.asarray(mod2)[:, others], np.asarray(mod)[:, others])
    assert max_rel(np.asarray(mod2)[:, 2], np.asarray(mod)[:, 2]) > 1e-3
    assert max_rel(np.asarray(out2)[:, :, 2], np.asarray(out)[:, :, 2]) > 1e-4
    # a [B] sigma is the same levels on every frame
    flat, _, mflat = _intermediates(cfg, params, lat, np.asarray([0.3, 0.6], np.float32), text, kw)
    same, _, msame = _intermediates(cfg, params, lat, np.repeat([[0.3], [0.6]], 4, 1).astype(np.float32), text, kw)
    np.testing.assert_allclose(flat, same, atol=1e-6)
    np.testing.assert_allclose(mflat, msame, atol=1e-6)
    if cfg.controls.cond_frames:
        _check_condition_frames_carry_sigma_zero()


def _check_condition_frames_carry_sigma_zero():
    params = params_for(TINY, TINY_SHAPES)
    lat, sig, text, kw = split_inputs(example_inputs(TINY, **dict(TINY_SHAPES)))
    kw["cond_mask"] = np.array([[True, False, False, False], [True, True, False, False]])
    _, tokens, mod = _intermediates(TINY, params, lat, sig, text, kw)
    zero = sig.copy()
    zero[kw["cond_mask"]] = 0.0
    kw2 = dict(kw, cond_mask=np.zeros_like(kw["cond_mask"]))
    lat2 = np.where(kw["cond_mask"][:, None, :, None, None, None], kw["cond_latents"], lat)
    _, tokens2, mod2 = _intermediates(TINY, params, lat2, zero, text, kw2)
    np.testing.assert_allclose(mod, mod2, atol=1e-6)
    np.testing.assert_allclose(tokens, tokens2, atol=1e-6)


@pytest.mark.slow(seconds=9)
def test_full_layout_with_controls_and_concat_condition_frames():
    cfg = preset(
        "tiny-full",
        controls=dict(
            camera=True,
            boxes=True,
            trajectory=True,
            cond_frames="concat",
            warp=True,
            map=True,
            map_blocks=1,
            map_hidden=8,
        ),
    )
    shapes = (("batch", 2), ("views", 3), ("frames", 2), ("height", 4), ("width", 4))
    params = params_for(cfg, shapes)
    lat, sig, text, kw = split_inputs(example_inputs(cfg, **dict(shapes)))
    fwd = forward_fn(cfg)
    out = fwd(params, lat, sig, text, kw)
    assert out.shape == lat.shape and np.isfinite(np.asarray(out)).all()
    # zero-initialised concat embedding: the condition latents do not matter at init
    other = dict(kw, cond_latents=kw["cond_latents"] + 1.0, warp=kw["warp"] * 2, bev_map=1 - kw["bev_map"])
    np.testing.assert_array_equal(fwd(params, lat, sig, text, other), out)


@pytest.mark.slow(seconds=8)
def test_stdit2_layers_patch_spanning_two_frames_and_the_caption_encoder():
    from jaxdrive.data.text import tokenize_captions

    cfg = preset(
        "tiny",
        block="stdit2",
        patch=(2, 2, 2),
        text_len=12,
        controls=dict(waypoints=True, camera=True, text="caption", caption_vocab=64, caption_layers=1),
    )
    shapes = (("batch", 2), ("views", 2), ("frames", 4), ("height", 4), ("width", 4))
    params = params_for(cfg, shapes)
    lat, sig, _, kw = split_inputs(example_inputs(cfg, **dict(shapes)))
    caps = [
        "This is a driving scene video captured by camera in CAM_FRONT of a car at gridville-centre "
        "during summer daytime.",
        "This is a driving scene video captured by camera in CAM_FRONT of a car "
        "at gridville-centre during winter night.",
    ]
    ids, mask = tokenize_captions(caps, vocab=64, max_len=12)
    fwd = forward_fn(cfg)
    a = fwd(params, lat, sig, ids, dict(kw, text_mask=mask))
    assert a.shape == lat.shape and float(jnp.std(a)) > 0
    b = fwd(params, lat, sig, ids[::-1], dict(kw, text_mask=mask[::-1]))
    assert max_rel(a, b) > 1e-4  # the caption reaches the output


SCAN_SHAPES = (("batch", 1), ("views", 2), ("frames", 2), ("height", 4), ("width", 4))


def _unrolled_and_scanned(base, scanned):
    """Parameters of ``base`` (unrolled) and the same with layers 0 and 1 stacked as the scanned
    run ``layers_0_2``, checked against the tree ``scanned`` initialises."""
    params = params_for(base, SCAN_SHAPES)
    stacked = dict(params)
    layers = [stacked.pop(f"layers_{i}") for i in (0, 1)]
    stacked["layers_0_2"] = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *layers)
    assert jax.tree_util.tree_structure(stacked) == jax.tree_util.tree_structure(
        nn.unbox(boxed_params(scanned, SCAN_SHAPES))
    )
    return params, stacked


@pytest.mark.slow(seconds=12)
@pytest.mark.parametrize("dtype", ["float32", "bfloat16"])
def test_scan_and_remat_match_the_python_loop(dtype):
    # bfloat16: the float32 parameters promote a layer's output, so the scan carry changed type
    # (nn.scan refused it) until the residual stream was kept float32 in both paths
    base = preset("tiny", depth=2, dtype=dtype)
    scanned = dataclasses.replace(base, scan_layers=True, remat="dots")
    params, stacked = _unrolled_and_scanned(base, scanned)
    lat, sig, text, kw = split_inputs(example_inputs(base, **dict(SCAN_SHAPES)))

    def loss(cfg):
        dit = DiT(cfg)
        return jax.jit(
            jax.value_and_grad(
                lambda p, x: jnp.sum(dit.forward(p, x, sig, conditions(text, kw)) * jnp.sin(x)), argnums=1
            )
        )

    (v1, g1), (v2, g2) = loss(base)(params, lat), loss(scanned)(stacked, lat)
    tol = 1e-5 if dtype == "float32" else 2e-2
    np.testing.assert_allclose(v2, v1, rtol=tol)
    assert max_rel(g2, g1) < tol


@pytest.mark.slow(seconds=11)
def test_a_scan_break_gives_a_layer_its_own_name_and_changes_nothing_else():
    """MiLA's paper config scans its layers but trains the last one by name in stage 1."""
    from jaxdrive.models.dit.config import layer_runs

    base = preset("tiny", depth=3)
    broken = dataclasses.replace(base, scan_layers=True, scan_breaks=(2,))
    assert layer_runs(broken) == [(0, 2), (2, 3)] and layer_runs(base) == [(0, 3)]
    params, stacked = _unrolled_and_scanned(base, broken)  # layers_0_2 scanned, layers_2 alone
    lat, sig, text, kw = split_inputs(example_inputs(base, **dict(SCAN_SHAPES)))
    a = forward_fn(base)(params, lat, sig, text, kw)  # jitted: eagerly each op would compile alone
    b = forward_fn(broken)(stacked, lat, sig, text, kw)
    np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-6)
    for bad in [(0,), (3,)]:
        with pytest.raises(ValueError, match=rf"scan_breaks: expected layer indices in \(0, 3\), got {bad[0]}"):
            dataclasses.replace(base, scan_breaks=bad).replace()


def test_frame_alignment_with_the_vae():
    assert frame_mode("boxes", 5, 2, 4) == "pixel" and frame_mode("boxes", 2, 2, 4) == "latent"
    with pytest.raises(ValueError, match=r"boxes: expected 2 \(latent\) or 5 \(pixel\) frames .* got 4"):
        frame_mode("boxes", 4, 2, 4)
    x = jnp.arange(9)[None]  # 9 = 1 + 4 * 2 pixel frames -> 3 latent
    np.testing.assert_array_equal(group_frames(x, 4)[0], [[0, 0, 0, 0], [1, 2, 3, 4], [5, 6, 7, 8]])


def _init_error(cfg, **changes):
    ex = example_inputs(cfg, **dict(MV_SHAPES))
    sigma = changes.pop("sigma", ex["sigma"])
    DiT(cfg).init(jax.random.PRNGKey(0), ex["latents"], sigma, ex["cond"].replace(**changes))


@pytest.mark.parametrize(
    "changes,pattern",
    [
        (
            dict(intrinsics=np.zeros((2, 5, 3, 3), np.float32)),
            r"intrinsics: expected shape \[2, 6, 3, 3\], got \[2, 5, 3, 3\]",
        ),
        (dict(cam_to_ego=np.zeros((2, 4, 4, 4), np.float32)), r"cam_to_ego: expected shape \[2, 6, 4, 4\]"),
        (dict(boxes=np.zeros((2, 4, 2, 7), np.float32)), r"boxes: expected 2 \(latent\) or 5 \(pixel\) frames"),
        (dict(bev_map=np.zeros((2, 3, 16, 16, 8), np.float32)), r"bev_map: expected 2 \(latent\) or 5 \(pixel\)"),
        (dict(bev_map=np.zeros((2, 5, 16, 16, 3), np.float32)), r"bev_map: expected shape \[2, \*, \*, \*, 8\]"),
        (dict(waypoints=np.zeros((2, 3, 2), np.float32)), r"waypoints: expected 2 \(latent\) or 5 \(pixel\)"),
        (
            dict(sigma=np.zeros((2, 3), np.float32)),
            r"sigma: expected shape \[B\] = \[2\] or \[B, F'\] = \[2, 2\], got \[2, 3\]",
        ),
        (dict(sigma=np.zeros((3,), np.float32)), r"sigma: expected shape \[2\], got \[3\]"),
        (dict(sigma=np.full((2,), 1.5, np.float32)), r"sigma: expected values in \[0.0, 1.0\], got"),
        (dict(drop={"weather": np.zeros(2, bool)}), r"drop: expected condition names .* got 'weather'"),
        (
            dict(features={3: np.zeros((2, 1, 4, 6, 64), np.float32)}),
            r"features: expected a mapping with the layers \[0\]",
        ),
    ],
)
def test_bad_input_names_the_argument(changes, pattern):
    with pytest.raises(ValueError, match=pattern):
        _init_error(MV, **changes)


def test_cross_attention_takes_its_own_kernel_when_set(monkeypatch):
    # DiTConfig.cross_attn_impl moves the text / control cross-attention alone (a TPU lever:
    # splash there, the 8-frame temporal attention left on XLA); unset it follows local_attn_impl
    from jaxdrive.models.dit import blocks

    seen = []
    real = blocks.attention

    def spy(q, k, v, *, impl, **kw):
        seen.append((q.shape[1] == k.shape[1], impl))  # self-attention: as many keys as queries
        return real(q, k, v, impl="xla", **kw)

    monkeypatch.setattr(blocks, "attention", spy)
    shapes = (("batch", 1), ("frames", 2), ("height", 8), ("width", 8))  # 32 video tokens, 8 text
    for cross, want in ((None, "blockwise"), ("cudnn", "cudnn")):
        cfg = preset("tiny", depth=1, local_attn_impl="blockwise", cross_attn_impl=cross)
        ex = example_inputs(cfg, **dict(shapes))
        seen.clear()
        DiT(cfg).init(jax.random.PRNGKey(0), ex["latents"], jnp.full((1,), 0.5), ex["cond"])
        assert {impl for is_self, impl in seen if not is_self} == {want}, (cross, seen)
        # the spatial and temporal self-attentions keep theirs
        assert {impl for is_self, impl in seen if is_self} == {"auto", "blockwise"}, (cross, seen)


def test_bad_config_and_presets():
    with pytest.raises(ValueError, match=r"cross_attn_impl: expected one of \[.*'splash'\], got 'ring'"):
        preset("tiny", cross_attn_impl="ring")
    with pytest.raises(ValueError, match=r"name: expected one of \[.*'cogvideox-2b'.*\], got 'cogvideox-9b'"):
        preset("cogvideox-9b")
    with pytest.raises(ValueError, match="boxes: this DiT takes no boxes"):
        cfg = preset("tiny")
        ex = example_inputs(cfg)
        ex["cond"] = ex["cond"].replace(boxes=np.zeros((1, 1, 2, 7), np.float32))
        DiT(cfg).init(jax.random.PRNGKey(0), **ex)
    with pytest.raises(ValueError, match=r"layout: expected one of \['factorized', 'full'\], got 'mixed'"):
        preset("tiny", layout="mixed")


def test_heads_must_divide_the_tensor_axis():
    from jaxdrive.parallel import make_mesh

    cfg = preset("tiny", heads=3, head_dim=16)
    with jax.set_mesh(make_mesh(data=4, tensor=2)):
        with pytest.raises(ValueError, match=r"heads: expected a multiple of the mesh axis 'tensor' \(size 2\), got 3"):
            jax.eval_shape(lambda: DiT(cfg).init(jax.random.PRNGKey(0), **example_inputs(cfg, batch=4)))


def test_presets_exist_and_tiny_counts_are_exact():
    assert {"stdit3-xl/2", "mila", "magicdrive-v2", "cogvideox-2b", "tiny", "small"} <= set(PRESETS)
    cfg = preset("tiny")
    n = sum(
        int(np.prod(x.shape))
        for x in jax.tree_util.tree_leaves(
            jax.eval_shape(
                lambda: jax.tree_util.tree_map(
                    lambda b: b.value, boxed_params(cfg, TINY_SHAPES), is_leaf=lambda b: hasattr(b, "value")
                )
            )
        )
    )
    assert param_count(cfg) == n


def test_the_parameter_tree_is_traced_once_per_config_and_each_caller_gets_its_own(monkeypatch):
    """A run asks for its DiT's parameter tree several times (its init, its checkpoint target,
    each restore): the model is traced once per config and input shapes. The values drawn, the
    boxes and the shapes are those of a fresh trace; a caller that edits its tree changes no
    other caller's."""
    import jaxdrive.models.dit.model as dit_model
    from jaxdrive.models.params import abstract_params, host_params

    traced = []
    monkeypatch.setattr(dit_model, "abstract_params", lambda *a, **k: traced.append(1) or abstract_params(*a, **k))
    cfg = preset("tiny", depth=1, head_dim=12)  # a config no other test traced in this process
    first = DiT(cfg).abstract_params()
    first.pop(next(iter(first)))
    boxed = DiT(cfg).init_params(7, boxed=True)
    second = DiT(cfg).abstract_params()
    assert len(traced) == 1 and len(second) == len(first) + 1
    DiT(cfg).abstract_params(frames=3)  # other input shapes: traced again
    DiT(dataclasses.replace(cfg, head_dim=8)).abstract_params()  # another config too
    assert len(traced) == 3
    fresh = host_params(*abstract_params(DiT(cfg), **example_inputs(cfg)), 7, boxed=True)
    assert jax.tree_util.tree_structure(boxed) == jax.tree_util.tree_structure(fresh)
    for a, b in zip(jax.tree_util.tree_leaves(boxed), jax.tree_util.tree_leaves(fresh)):
        np.testing.assert_array_equal(a, b)


def test_cogvideox_2b_preset_has_the_diffusers_parameter_count():
    # two of the 30 layers: the same structure, a fraction of the tracing time
    torch = pytest.importorskip("torch")
    diffusers = pytest.importorskip("diffusers")
    with torch.device("meta"):  # its defaults are CogVideoX-2B's (30 layers)
        ref = diffusers.CogVideoXTransformer3DModel(num_layers=2)
    want = sum(p.numel() for p in ref.parameters())
    assert param_count(preset("cogvideox-2b", depth=2)) == want


@pytest.mark.slow(seconds=7)
def test_dit_benchmark_prints_json_figures(capsys):
    from jaxdrive.cli import main

    main(["bench", "dit", "--presets", "tiny", "--seq", "2", "--repeats", "1"])
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    figures = {r["figure"] for r in rows}
    assert {"fwd_bwd_time", "tokens_per_s", "per_device_temp_memory", "compile_time"} <= figures
    assert all(r["bench"] == "dit" for r in rows)
    assert next(r for r in rows if r["figure"] == "per_device_temp_memory")["value"] > 0


def test_a_token_wider_than_the_model_needs_data_prediction():
    # 48 channels x a 2x2 patch = 192 numbers per token against a width of 4 x 16 = 64: velocity
    # prediction cannot pass the token's noise through, so it is refused with both numbers named
    with pytest.raises(
        ValueError,
        match=r"patch x in_channels = 192 numbers .*heads x head_dim = 64.*"
        r"got prediction='velocity'",
    ):
        preset("tiny", in_channels=48)
    assert preset("tiny", in_channels=48, prediction="data").patch_dim == 192
    assert preset("tiny", in_channels=16).prediction == "velocity"  # 64 numbers: fits the width
    with pytest.raises(ValueError, match=r"prediction: expected one of \['velocity', 'data'\], got 'eps'"):
        preset("tiny", prediction="eps")
    with pytest.raises(ValueError, match=r"prediction_min_sigma: expected a level in \(0, 1\], got 0.0"):
        preset("tiny", prediction_min_sigma=0.0)


def test_reference_input_is_the_newest_given_frame_on_every_frame():
    from jaxdrive.models.dit import reference_input

    x = np.zeros((3, 2, 4, 2, 2, 3), np.float32)
    cond = np.arange(x.size, dtype=np.float32).reshape(x.shape)
    mask = np.array([[True, True, False, False], [True, False, False, False], [False] * 4])
    r = np.asarray(reference_input(x, cond, mask))
    assert r.shape == (3, 2, 4, 2, 2, 4)
    for f in range(4):
        np.testing.assert_array_equal(r[0, :, f, ..., :3], cond[0, :, 1])  # the newer of two given frames
        np.testing.assert_array_equal(r[1, :, f, ..., :3], cond[1, :, 0])
    np.testing.assert_array_equal(
        r[..., 3], np.broadcast_to(np.array([1, 1, 0])[:, None, None, None, None], r.shape[:-1])
    )
    np.testing.assert_array_equal(r[2], 0)  # nothing given: zeros
    np.testing.assert_array_equal(reference_input(x, None, None), 0)


def test_reference_frame_control_reaches_every_frame_through_a_zero_initialised_embedding():
    cfg = preset("tiny", controls=dict(cond_frames="replace", reference_frame="input"))
    params = params_for(cfg, TINY_SHAPES)
    lat, sig, text, kw = split_inputs(example_inputs(cfg, **dict(TINY_SHAPES)))
    kw["cond_mask"] = np.array([[True, True, False, False], [True, False, False, False]])
    fwd = forward_fn(cfg)
    out = fwd(params, lat, sig, text, kw)
    assert not np.any(np.asarray(params["reference_embed"]["kernel"]))
    # the newest given frame's latents change every generated frame once the embedding is trained
    trained = dict(params, reference_embed=jax.tree_util.tree_map(lambda a: a + 0.1, params["reference_embed"]))
    moved = np.asarray(kw["cond_latents"]).copy()
    moved[0, :, 1] += 1.0
    a = fwd(trained, lat, sig, text, kw)
    b = fwd(trained, lat, sig, text, dict(kw, cond_latents=moved))
    assert min(max_rel(np.asarray(b)[0, :, f], np.asarray(a)[0, :, f]) for f in (2, 3)) > 1e-3
    np.testing.assert_allclose(np.asarray(b)[1], np.asarray(a)[1], atol=1e-6)  # the other clip is untouched
    assert max_rel(fwd(trained, lat, sig, text, kw), out) > 1e-3
    with pytest.raises(ValueError, match=r"controls.reference_frame: expected condition frames"):
        preset("tiny", controls=dict(reference_frame="input"))
    with pytest.raises(
        ValueError, match=r"controls.reference_frame: expected one of \['input', 'residual', 'warp', None\]"
    ):
        preset("tiny", controls=dict(cond_frames="replace", reference_frame="copy"))
    with pytest.raises(ValueError, match=r"'residual' .* needs prediction='data', got prediction='velocity'"):
        preset("tiny", controls=dict(cond_frames="replace", reference_frame="residual"))
    with pytest.raises(
        ValueError,
        match=r"out_channels: a residual to the given frame needs in_channels = 4 outputs, "
        r"got 8",
    ):
        preset(
            "tiny", prediction="data", out_channels=8, controls=dict(cond_frames="replace", reference_frame="residual")
        )


def test_residual_reference_frame_starts_by_repeating_the_newest_given_frame():
    """Freshly initialised (zero output projection) a residual model's data estimate is exactly
    the newest given frame on every frame; a clip with no given frame gets zeros."""
    cfg = preset("tiny", prediction="data", controls=dict(cond_frames="replace", reference_frame="residual"))
    params = jax.tree_util.tree_map(jnp.asarray, nn.unbox(boxed_params(cfg, TINY_SHAPES)))
    lat, sig, text, kw = split_inputs(example_inputs(cfg, **dict(TINY_SHAPES)))
    kw["cond_mask"] = np.array([[True, True, False, False], [False] * 4])
    out = np.asarray(forward_fn(cfg)(params, lat, sig, text, kw))
    for f in range(4):
        np.testing.assert_array_equal(out[0, :, f], np.asarray(kw["cond_latents"])[0, :, 1])
    np.testing.assert_array_equal(out[1], 0.0)


@pytest.mark.slow(seconds=8)
def test_final_convolutions_start_as_a_no_op_and_are_3x3_convolutions():
    """U-ViT's final convolutions (``final_conv``): zero-initialised, the model's output is that of
    the same model without them; each is a "same" 3x3 convolution (checked against XLA's)."""
    from jaxdrive.models.dit.model import _conv3x3
    from jaxdrive.models.params import Init

    cfg = preset(
        "tiny", prediction="data", final_conv=8, controls=dict(cond_frames="replace", reference_frame="residual")
    )
    params = jax.tree_util.tree_map(jnp.asarray, nn.unbox(boxed_params(cfg, TINY_SHAPES)))
    assert {"final_conv_1_kernel", "final_conv_2_kernel"} <= set(params)
    assert not np.any(params["final_conv_2_kernel"]) and np.any(params["final_conv_1_kernel"])
    assert params["final_conv_1_kernel"].shape == (3, 3, 2 * cfg.in_channels + cfg.in_channels + 1, 8)
    lat, sig, text, kw = split_inputs(example_inputs(cfg, **dict(TINY_SHAPES)))
    kw["cond_mask"] = np.array([[True, True, False, False], [True, False, False, False]])
    plain = dataclasses.replace(cfg, final_conv=0)
    trained = perturb(params)  # every weight, the convolutions' too
    without = {k: v for k, v in trained.items() if not k.startswith("final_conv")}
    zeroed = dict(
        trained,
        final_conv_2_kernel=jnp.zeros_like(trained["final_conv_2_kernel"]),
        final_conv_2_bias=jnp.zeros_like(trained["final_conv_2_bias"]),
    )
    a = forward_fn(cfg)(zeroed, lat, sig, text, kw)
    np.testing.assert_array_equal(a, forward_fn(plain)(without, lat, sig, text, kw))
    assert max_rel(forward_fn(cfg)(trained, lat, sig, text, kw), a) > 1e-3  # trained, they act

    class Conv(nn.Module):
        @nn.compact
        def __call__(self, x):
            return _conv3x3(self, "c", x, 5, Init("lecun", fan_in_axes=3))

    x = np.random.default_rng(0).normal(size=(2, 3, 6, 7, 4)).astype(np.float32)  # any leading axes
    p = nn.unbox(Conv().init(jax.random.key(0), x))["params"]
    p = dict(p, c_bias=jnp.arange(5.0))
    ref = jax.lax.conv_general_dilated(
        x.reshape(6, 6, 7, 4), p["c_kernel"], (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC")
    ) + jnp.arange(5.0)
    np.testing.assert_allclose(Conv().apply({"params": p}, x), ref.reshape(2, 3, 6, 7, 5), rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match=r"final_conv: expected an integer >= 0, got -1"):
        preset("tiny", final_conv=-1)


def _overlap_tokens(img, patch, junk):
    """The tokens whose overlapping patches (``out_patches="overlap"``) all agree with ``img
    [h, w, C]``: token ``(a, b)`` holds the ``2 ph x 2 pw`` window of ``img`` centred on its
    footprint, with ``junk`` where the window leaves the frame."""
    _, ph, pw = patch
    h, w, c = img.shape
    padded = np.pad(img, ((ph // 2, ph // 2), (pw // 2, pw // 2), (0, 0)))
    frame = np.pad(np.ones((h, w)), ((ph // 2, ph // 2), (pw // 2, pw // 2)))
    padded = np.where(frame[..., None] > 0, padded, junk)
    windows = [
        padded[a * ph : a * ph + 2 * ph, b * pw : b * pw + 2 * pw].reshape(-1)
        for a in range(h // ph)
        for b in range(w // pw)
    ]
    return np.stack(windows)[None, None, :, None]  # [B, F', S, V, 2 ph 2 pw C]


def test_overlapping_output_patches_spread_a_seam_and_give_back_the_image_they_agree_on():
    """``out_patches="overlap"``: a token paints a tent-weighted ``2 ph x 2 pw`` patch centred on
    its footprint. Worked number: two tokens of constant 0 and 1 (``ph=2``) give ``[0, 1/4, 3/4,
    1]`` down the frame, a seam of 1 spread into steps of 1/4, 1/2, 1/4 (``"disjoint"``: ``[0, 0,
    1, 1]``). Tokens that agree on their overlaps give back their image exactly, the frame's edges
    too (what lies outside the frame is never painted); a zero projection paints zeros."""
    from jaxdrive.models.dit.embed import tent_window, unpatchify_overlap

    np.testing.assert_array_equal(tent_window(2), [0.25, 0.75, 0.75, 0.25])
    w4 = tent_window(4)
    np.testing.assert_allclose(w4[:4] + w4[4:], 1.0)  # the two tokens over a position weigh it 1
    two = np.zeros((1, 1, 2, 1, 16), np.float32)
    two[0, 0, 1] = 1.0
    out = np.asarray(unpatchify_overlap(jnp.asarray(two), (1, 2, 2), (2, 1), 1))
    np.testing.assert_array_equal(out[0, 0, 0, :, 0, 0], [0.0, 0.25, 0.75, 1.0])
    rng = np.random.default_rng(0)
    for patch, grid in [((1, 2, 2), (3, 4)), ((1, 4, 2), (2, 3))]:
        img = rng.normal(size=(grid[0] * patch[1], grid[1] * patch[2], 3)).astype(np.float32)
        tokens = _overlap_tokens(img, patch, junk=1e3)
        out = np.asarray(unpatchify_overlap(jnp.asarray(tokens), patch, grid, 3))
        np.testing.assert_allclose(out[0, 0, 0], img, rtol=1e-5, atol=1e-5)
    odd_patch = r"out_patches: .* expected an even patch height and width, got patch=\(1, 1, 1\)"
    with pytest.raises(ValueError, match=odd_patch):
        preset("tiny", patch=(1, 1, 1), out_patches="overlap")
    with pytest.raises(ValueError, match=r"out_patches: expected one of \['disjoint', 'overlap'\], got 'tent'"):
        preset("tiny", out_patches="tent")


@pytest.mark.slow(seconds=6)
def test_an_overlapping_head_starts_at_zero_four_times_as_wide():
    """The DiT with ``out_patches="overlap"``: its output projection is four times as wide (a
    token's ``2 ph x 2 pw`` patch) and starts at zero, so the residual model gives the newest
    given frame bit for bit; trained, it paints."""
    controls = dict(cond_frames="replace", reference_frame="residual")
    cfg = preset("tiny", prediction="data", out_patches="overlap", controls=controls)
    params = jax.tree_util.tree_map(jnp.asarray, nn.unbox(boxed_params(cfg, TINY_SHAPES)))
    kernel = params["proj_out"]["kernel"]
    assert kernel.shape == (cfg.width, 4 * cfg.patch_dim) and not np.any(kernel)
    lat, sig, text, kw = split_inputs(example_inputs(cfg, **dict(TINY_SHAPES)))
    kw["cond_mask"] = np.array([[True, True, False, False], [True, False, False, False]])
    out = np.asarray(forward_fn(cfg)(params, lat, sig, text, kw))
    for f in range(2, 4):
        np.testing.assert_array_equal(out[0, :, f], np.asarray(kw["cond_latents"])[0, :, 1])
    assert max_rel(forward_fn(cfg)(perturb(params), lat, sig, text, kw), out) > 1e-3


# 3 latent frames = 9 pixel frames: four at 12 fps, then 1 fps (MiLA: 12-fps condition frames, coarse 1 fps)
FT_SHAPES = (("batch", 2), ("views", 1), ("frames", 3), ("height", 4), ("width", 4))
FT_ON, FT_OFF = preset("tiny", controls=dict(frame_time=True)), preset("tiny")


def test_latent_frames_take_the_time_of_their_newest_pixel_frame_relative_to_the_first():
    from jaxdrive.models.dit.controls import latent_frame_times

    t = np.array([[10.0, 10.1, 10.2, 10.3, 10.4, 11.4, 12.4, 13.4, 14.4]], np.float32)
    np.testing.assert_allclose(latent_frame_times(t, 3, 4), [[0.0, 0.4, 4.4]], atol=1e-5)  # pixel 0, 4, 8
    np.testing.assert_allclose(latent_frame_times(t[:, ::4], 3, 4), [[0.0, 0.4, 4.4]], atol=1e-5)  # per latent frame
    with pytest.raises(ValueError, match=r"frame_times: expected 3 \(latent\) or 9 \(pixel\) frames .* got 4"):
        latent_frame_times(t[:, :4], 3, 4)


@pytest.mark.slow(seconds=9)
def test_frame_time_control_starts_as_a_no_op_and_reads_relative_times():
    """Zero-initialised: a model with the control equals the same parameters without it. Once its
    last layer is trained the output depends on the frame times, but not on a shift of all of them,
    and a window cut from a longer clip's conditions means what the same window alone means."""
    base = jax.tree_util.tree_map(jnp.asarray, nn.unbox(boxed_params(FT_ON, FT_SHAPES)))
    assert not np.any(base["frame_time_embed"]["FourierMLP_0"]["fc2"]["kernel"])
    params = perturb(base, skip=BRANCH_ZERO + ("frame_time_embed",))
    without = {k: v for k, v in params.items() if k != "frame_time_embed"}
    assert jax.tree_util.tree_structure(without) == jax.tree_util.tree_structure(
        nn.unbox(boxed_params(FT_OFF, FT_SHAPES))
    )
    lat, sig, text, kw = split_inputs(example_inputs(FT_ON, **dict(FT_SHAPES)))
    times = kw["frame_times"]
    assert times.shape == (2, 9)
    on, off = forward_fn(FT_ON), forward_fn(FT_OFF)
    plain = off(without, lat, sig, text, {k: v for k, v in kw.items() if k != "frame_times"})
    np.testing.assert_allclose(on(params, lat, sig, text, kw), plain, atol=1e-6)

    trained = dict(params, frame_time_embed=perturb(params["frame_time_embed"], scale=0.1, seed=3))
    out = on(trained, lat, sig, text, kw)
    uniform = np.tile(np.arange(9, dtype=np.float32) / 12, (2, 1))  # 12 fps throughout
    assert max_rel(on(trained, lat, sig, text, dict(kw, frame_times=uniform)), out) > 1e-3
    assert max_rel(out, plain) > 1e-3
    np.testing.assert_allclose(on(trained, lat, sig, text, dict(kw, frame_times=times + 8.0)), out, atol=1e-5)
    # per latent frame: latent frame j has pixel frame 4j's time
    np.testing.assert_allclose(on(trained, lat, sig, text, dict(kw, frame_times=times[:, ::4])), out, atol=1e-6)
    # a dropped frame time is the model without it; the other clip keeps its times
    drop = {"frame_time": np.array([True, False])}
    dropped = np.asarray(on(trained, lat, sig, text, dict(kw, drop=drop)))
    absent = np.asarray(on(trained, lat, sig, text, {k: v for k, v in kw.items() if k != "frame_times"}))
    np.testing.assert_allclose(dropped[0], absent[0], atol=1e-6)
    np.testing.assert_allclose(dropped[1], np.asarray(out)[1], atol=1e-6)

    # a 2-latent-frame window cut from a 5-latent-frame clip (4 at 12 fps, then 1 fps) by
    # Conditions.per_frame, as a rollout cuts its windows, against the same window alone
    from jaxdrive.generate.windows import controls_at

    steps = np.where(np.arange(17) < 4, 1 / 12, 1.0)
    long = np.tile(np.cumsum(steps) - steps[0], (2, 1)).astype(np.float32)
    clip = conditions(text, dict(kw, frame_times=long))
    cut = controls_at(clip, [2, 3, 4], 4).given()  # latent frames 2..4: pixel 8..16
    assert cut["frame_times"][0, 0] > 5  # not at time 0 in the long clip
    alone = dict(kw, frame_times=np.tile(np.arange(9, dtype=np.float32), (2, 1)))  # the window at 1 fps
    cut.pop("text")
    np.testing.assert_allclose(on(trained, lat, sig, text, cut), on(trained, lat, sig, text, alone), atol=1e-5)


def test_frame_times_from_a_batch_and_bad_frame_times():
    from jaxdrive.models.dit.conditions import Conditions

    batch = {"fps": np.ones(2), "frame_times": np.tile(np.arange(9.0), (2, 1))}
    c = Conditions.from_batch(batch, FT_ON)
    assert c.frame_times.dtype == np.float32 and c.frame_times.shape == (2, 9)
    assert Conditions.from_batch(batch, FT_OFF).frame_times is None
    ex = example_inputs(FT_ON, **dict(FT_SHAPES))
    lat, sig = ex["latents"], ex["sigma"]
    ex["cond"].check(FT_ON, lat, sig)
    for times, pattern in [
        (np.zeros((2, 4), np.float32), r"frame_times: expected 3 \(latent\) or 9 \(pixel\) frames"),
        (np.zeros((2,), np.float32), r"frame_times: expected shape \[2, \*\], got \[2\]"),
        (np.zeros((3, 9), np.float32), r"frame_times: expected shape \[2, \*\], got \[3, 9\]"),
    ]:
        with pytest.raises(ValueError, match=pattern):
            ex["cond"].replace(frame_times=times).check(FT_ON, lat, sig)
    with pytest.raises(ValueError, match=r"frame_times: this DiT takes no frame_time \(controls.frame_time is False\)"):
        ex["cond"].check(FT_OFF, lat, sig)


@pytest.mark.slow(seconds=6)
def test_growing_temporal_blocks_leaves_a_spatial_only_models_outputs_unchanged():
    """MagicDrive-V2's stage 1 -> 2 growth: a spatial-only model (``temporal="off"``) loaded into
    one with zero-initialised temporal blocks (``temporal="zero_init"``) gives exactly its outputs,
    on images and on videos; once trained, the temporal blocks act."""
    spatial = preset("tiny", temporal="off")
    grown = dataclasses.replace(spatial, temporal="zero_init")
    shapes = dict(TINY_SHAPES)
    stage1 = perturb(jax.tree_util.tree_map(jnp.asarray, nn.unbox(boxed_params(spatial, TINY_SHAPES))))
    fresh = jax.tree_util.tree_map(jnp.asarray, nn.unbox(boxed_params(grown, TINY_SHAPES)))
    flat1, flat2 = flax.traverse_util.flatten_dict(stage1, sep="/"), flax.traverse_util.flatten_dict(fresh, sep="/")
    assert set(flat1) < set(flat2) and all("/temporal/" in k for k in set(flat2) - set(flat1))
    assert not any("/temporal/" in k for k in flat1)
    stage2 = flax.traverse_util.unflatten_dict({**flat2, **flat1}, sep="/")  # what train.init_from loads
    for frames in (1, shapes["frames"]):
        inputs = example_inputs(spatial, **dict(shapes, frames=frames))
        lat, sig, text, kw = split_inputs(inputs)
        a = forward_fn(spatial)(stage1, lat, sig, text, kw)
        np.testing.assert_allclose(forward_fn(grown)(stage2, lat, sig, text, kw), a, rtol=1e-6, atol=1e-6)
        # the usual init of the same blocks is not a no-op, and trained grown blocks act
        usual = flax.traverse_util.unflatten_dict(
            {
                **flax.traverse_util.flatten_dict(
                    nn.unbox(boxed_params(dataclasses.replace(spatial, temporal="on"), TINY_SHAPES)), sep="/"
                ),
                **flat1,
            },
            sep="/",
        )
        assert max_rel(forward_fn(dataclasses.replace(spatial, temporal="on"))(usual, lat, sig, text, kw), a) > 1e-3
        if frames > 1:
            assert max_rel(forward_fn(grown)(perturb(stage2), lat, sig, text, kw), a) > 1e-3
    with pytest.raises(ValueError, match=r"temporal: expected 'on' for layout 'factorized' with block 'stdit2'"):
        preset("tiny", block="stdit2", temporal="off")
    with pytest.raises(ValueError, match=r"temporal: expected one of"):
        preset("tiny", temporal="grow")
