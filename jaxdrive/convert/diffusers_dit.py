"""diffusers ``CogVideoXTransformer3DModel`` folders -> a ``"full"``-layout :class:`DiT` and its params.

    dit, params = load_diffusers_transformer("CogVideoX-2b/transformer")
    out = dit.forward(params, latents, sigma, Conditions(text=text))   # latents [B, 1, F', h, w, C], sigma [B],
                                                                       # text [B, L, D]

The imported model embeds ``sigma * 1000`` as its timestep (CogVideoX's DDPM timesteps are
``t = 1000 sigma`` in jaxdrive's noise-level convention) and returns what the original network
returns (CogVideoX: a v-prediction in its own DDPM parametrisation; sampling it with a CogVideoX
scheduler is the caller's business). The 3D RoPE of CogVideoX 1.0 follows the diffusers pipeline
(positions spread over the training grid ``sample_height / p x sample_width / p``), 1.5 uses
integer positions. The text length must be ``max_text_seq_length`` for 3D sin-cos models, as in
diffusers (their position table covers exactly that many text tokens).

Supported: CogVideoX 1.0 (2B sin-cos, 5B RoPE), 1.5 (patch_size_t, ofs embedding, no patch bias),
image-to-video models (their ``in_channels`` include the image latents the caller concatenates).
Not supported (clear error): learned positional embeddings (CogVideoX-5B-I2V 1.0), other
activations, LayerNorms without affine parameters.
"""

from __future__ import annotations

import einops
import numpy as np

from jaxdrive.convert.safetensors_io import read_config, read_weights
from jaxdrive.models.dit.config import Controls, DiTConfig, check_config, layer_runs
from jaxdrive.models.dit.model import DiT

CLASS_NAME = "CogVideoXTransformer3DModel"


def config_from_diffusers(config: dict, **overrides) -> DiTConfig:
    """The :class:`DiTConfig` of a diffusers CogVideoX transformer config (``overrides`` e.g.
    ``dtype="bfloat16"``, ``scan_layers=True``, ``remat="dots"``)."""
    c = dict(config)
    name = c.get("_class_name", CLASS_NAME)
    if name != CLASS_NAME:
        raise ValueError(f"config: expected _class_name {CLASS_NAME!r}, got {name!r}")
    get = lambda k, d: c.get(k, d)
    if get("use_learned_positional_embeddings", False):
        raise ValueError("config: use_learned_positional_embeddings=True (CogVideoX-5B-I2V 1.0) is not supported")
    for key, want in (
        ("activation_fn", "gelu-approximate"),
        ("timestep_activation_fn", "silu"),
        ("norm_elementwise_affine", True),
    ):
        if get(key, want) != want:
            raise ValueError(f"config: expected {key} = {want!r}, got {get(key, want)!r}")
    p, pt = int(get("patch_size", 2)), get("patch_size_t", None)
    heads, head_dim = int(get("num_attention_heads", 30)), int(get("attention_head_dim", 64))
    rope = bool(get("use_rotary_positional_embeddings", False))
    base = None
    if rope and pt is None:
        base = (int(get("sample_height", 60)) // p, int(get("sample_width", 90)) // p)
    in_ch = int(get("in_channels", 16))
    out_ch = get("out_channels", 16)
    cfg = DiTConfig(
        layout="full",
        depth=int(get("num_layers", 30)),
        heads=heads,
        head_dim=head_dim,
        mlp_ratio=4.0,
        in_channels=in_ch,
        out_channels=in_ch if out_ch is None else int(out_ch),
        patch=(1 if pt is None else int(pt), p, p),
        qk_norm="layer",
        qkv_bias=bool(get("attention_bias", True)),
        norm_eps=float(get("norm_eps", 1e-5)),
        positions="rope" if rope else "sincos",
        rope_base=base,
        spatial_interpolation_scale=float(get("spatial_interpolation_scale", 1.875)),
        temporal_interpolation_scale=float(get("temporal_interpolation_scale", 1.0)),
        time_embed_dim=int(get("time_embed_dim", 512)),
        time_freq_dim=heads * head_dim,
        flip_sin_to_cos=bool(get("flip_sin_to_cos", True)),
        freq_shift=float(get("freq_shift", 0)),
        timestep_scale=1000.0,
        text_dim=int(get("text_embed_dim", 4096)),
        text_len=int(get("max_text_seq_length", 226)),
        ofs_embed_dim=get("ofs_embed_dim", None),
        controls=Controls(text="embeddings", text_null=False),
    )
    return cfg.replace(**overrides) if overrides else check_config(cfg)


def _lin(w, b=None):
    out = {"kernel": np.ascontiguousarray(w.T)}
    if b is not None:
        out["bias"] = b
    return out


def convert_state_dict(sd: dict, cfg: DiTConfig, source: str = "state dict") -> dict:
    """diffusers tensors (name -> array) -> the params tree of ``DiT(cfg)`` (unscanned names).

    Raises ``ValueError`` listing the tensors that are missing and those left unused."""
    used: set = set()
    missing: list = []

    def take(name, default=None):
        if name in sd:
            used.add(name)
            return np.asarray(sd[name], np.float32)
        if default is None:
            missing.append(name)
            return None
        return default

    d, h = cfg.width, cfg.heads
    pt, p, _ = cfg.patch
    cin, cout = cfg.in_channels, cfg.out_dim
    params: dict = {}
    w = take("patch_embed.proj.weight")
    if w is not None:
        if w.ndim == 4:  # Conv2d [D, C, p, p] -> rows ordered (ph, pw, C)
            kernel = einops.rearrange(w, "d c ph pw -> (ph pw c) d")
        else:  # Linear [D, C pt p p] -> rows ordered (pt, ph, pw, C)
            kernel = einops.rearrange(w, "d (c pt ph pw) -> (pt ph pw c) d", c=cin, pt=pt, ph=p, pw=p)
        params["patch_embed"] = {"kernel": kernel, "bias": take("patch_embed.proj.bias", np.zeros(d, np.float32))}
    params["text_proj"] = _lin(take("patch_embed.text_proj.weight"), take("patch_embed.text_proj.bias"))

    def mlp2(prefix):
        return {
            f"linear_{i}": _lin(take(f"{prefix}.linear_{i}.weight"), take(f"{prefix}.linear_{i}.bias")) for i in (1, 2)
        }

    params["t_embedder"] = mlp2("time_embedding")
    if cfg.ofs_embed_dim is not None:
        params["ofs_embedder"] = mlp2("ofs_embedding")

    def heads_in(prefix):
        w, b = take(f"{prefix}.weight"), take(f"{prefix}.bias")
        out = {"kernel": None if w is None else einops.rearrange(w, "(h k) d -> d h k", h=h)}
        if cfg.qkv_bias:
            out["bias"] = None if b is None else einops.rearrange(b, "(h k) -> h k", h=h)
        return out

    for i in range(cfg.depth):
        pre = f"transformer_blocks.{i}"
        layer = {}
        for n in (1, 2):
            layer[f"norm{n}"] = {"scale": take(f"{pre}.norm{n}.norm.weight"), "bias": take(f"{pre}.norm{n}.norm.bias")}
            layer[f"norm{n}_linear"] = _lin(take(f"{pre}.norm{n}.linear.weight"), take(f"{pre}.norm{n}.linear.bias"))
        wo = take(f"{pre}.attn1.to_out.0.weight")
        layer["attn"] = {
            "to_q": heads_in(f"{pre}.attn1.to_q"),
            "to_k": heads_in(f"{pre}.attn1.to_k"),
            "to_v": heads_in(f"{pre}.attn1.to_v"),
            "norm_q": {"scale": take(f"{pre}.attn1.norm_q.weight"), "bias": take(f"{pre}.attn1.norm_q.bias")},
            "norm_k": {"scale": take(f"{pre}.attn1.norm_k.weight"), "bias": take(f"{pre}.attn1.norm_k.bias")},
            "to_out": {
                "kernel": None if wo is None else einops.rearrange(wo, "d (h k) -> h k d", h=h),
                "bias": take(f"{pre}.attn1.to_out.0.bias"),
            },
        }
        layer["ff"] = {
            "fc1": _lin(take(f"{pre}.ff.net.0.proj.weight"), take(f"{pre}.ff.net.0.proj.bias")),
            "fc2": _lin(take(f"{pre}.ff.net.2.weight"), take(f"{pre}.ff.net.2.bias")),
        }
        params[f"layers_{i}"] = {"layer": layer}
    params["norm_final"] = {"scale": take("norm_final.weight"), "bias": take("norm_final.bias")}
    params["norm_out_linear"] = _lin(take("norm_out.linear.weight"), take("norm_out.linear.bias"))
    params["norm_out"] = {"scale": take("norm_out.norm.weight"), "bias": take("norm_out.norm.bias")}
    wp, bp = take("proj_out.weight"), take("proj_out.bias")
    if wp is not None:  # rows ordered (C, [pt,] ph, pw) -> (pt, ph, pw, C)
        sizes = dict(c=cout, pt=pt, ph=p, pw=p)
        wp = einops.rearrange(wp, "(c pt ph pw) d -> d (pt ph pw c)", **sizes)
        bp = einops.rearrange(bp, "(c pt ph pw) -> (pt ph pw c)", **sizes)
        params["proj_out"] = {"kernel": np.ascontiguousarray(wp), "bias": bp}
    unused = sorted(set(sd) - used - {"patch_embed.pos_embedding"})
    if missing or unused:
        raise ValueError(
            f"{source}: expected the tensors of a {CLASS_NAME} with {cfg.depth} layers; "
            f"missing {missing[:20]}{' ...' if len(missing) > 20 else ''}, "
            f"unexpected {unused[:20]}{' ...' if len(unused) > 20 else ''}"
        )
    return params


def _check_tree(params, expected, source):
    from flax.traverse_util import flatten_dict

    got, want = flatten_dict(params), flatten_dict(expected)
    missing = sorted("/".join(k) for k in set(want) - set(got))
    extra = sorted("/".join(k) for k in set(got) - set(want))
    bad = sorted(
        f"{'/'.join(k)}: expected {list(want[k].shape)}, got {list(np.shape(got[k]))}"
        for k in set(got) & set(want)
        if tuple(np.shape(got[k])) != tuple(want[k].shape)
    )
    if missing or extra or bad:
        raise ValueError(
            f"{source}: the tensors do not fit the config: missing {missing}, unexpected {extra}, wrong shapes {bad}"
        )


def load_diffusers_transformer(path, **overrides):
    """``(dit, params)`` from a diffusers ``CogVideoXTransformer3DModel`` folder (``config.json`` +
    ``diffusion_pytorch_model.safetensors`` or its sharded index). ``overrides``: DiTConfig
    fields (e.g. ``dtype``, ``scan_layers``, ``remat``, ``attn_impl``). Params are float32 NumPy
    arrays; place them with :func:`jaxdrive.parallel.shard_params` (the boxed tree comes from
    ``jax.eval_shape(dit.init, ...)``) or ``jax.device_put``."""
    import flax.linen as nn
    import jax

    from jaxdrive.models.dit.inputs import example_inputs

    cfg = config_from_diffusers(read_config(path, CLASS_NAME), **overrides)
    scan = cfg.scan_layers
    tensors = {k: np.asarray(v, np.float32) for k, v in read_weights(path).items()}
    params = convert_state_dict(tensors, cfg.replace(scan_layers=False), source=str(path))
    if scan:
        for start, end in layer_runs(cfg):
            if end - start > 1:
                layers = [params.pop(f"layers_{i}") for i in range(start, end)]
                params[f"layers_{start}_{end}"] = jax.tree_util.tree_map(lambda *a: np.stack(a), *layers)
    dit = DiT(cfg)
    expected = jax.eval_shape(lambda: nn.unbox(dit.init(jax.random.PRNGKey(0), **example_inputs(cfg))["params"]))
    _check_tree(params, expected, str(path))
    return dit, params
