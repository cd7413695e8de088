"""Model FLOPs of the DiT train step and model FLOPs utilisation (MFU), for
:mod:`jaxdrive.bench.train`.

One train step (the backward of a matmul is two matmuls of its size, so forward +
backward = 3 x forward; with 2 FLOPs per multiply-add)::

    F_step = 6 * sum_W |W| * T_W  +  3 * sum_attentions 4 * S_q * S_k * D

- ``W``: the weight matrices of the transformer blocks (the ``layers_*`` kernels), each applied to
  ``T_W`` tokens: the video tokens ``B N`` in the factorized layout, text + video ``B (L + N)`` in
  the full layout (CogVideoX's blocks run over ``[text; video]``), the text tokens ``B L`` for the
  keys / values of text cross-attention. ``N = V F' / pt * h / ph * w / pw`` video tokens per clip,
  ``L`` the text length. With every matrix applied to every token this is the usual
  ``6 N_params tokens``. Not counted: biases, norms, the adaLN modulation matrices (they act on one
  timestep embedding per frame) and everything outside the blocks (patch embedding, timestep and
  text embedders, output layer): a few percent at these sizes (``xla_flops_per_step``, XLA's own
  count of the compiled step, is printed alongside).
- attention: ``QK^T`` and ``AV``, ``4 S_q S_k D`` per attention forward (``D = heads x head_dim``),
  per layer and clip: full layout ``4 (L + N)^2 D``; factorized layout, spatial attention over all
  views of a frame ``4 F' (V S)^2 D``, temporal ``4 V S F'^2 D``, text cross-attention ``4 N L D``
  (``S = h / ph * w / pw``). Control-token attentions and cross-view attention are not modelled
  (no FLOPs, hence no MFU, for a cross-view preset).

MFU = ``F_step / step time / peak FLOP/s``: ``--peak-tflops`` (TFLOP/s of the device), else the
dense bf16 peak of known accelerators by ``device_kind`` (TPU v4 / v5e / v5p / v6e, A100, H100,
H200; the presets compute in float32, so against a bf16 peak their MFU is a lower bound). A CPU
has no such figure: MFU is then printed as null with the reason, the achieved TFLOP/s are printed
regardless. Activation recomputation (``remat``) is not counted: this is MFU, not HFU.
"""

from __future__ import annotations

import math

# Dense bf16 peak TFLOP/s per chip / GPU (vendor figures), matched in order against the lower-cased
# device_kind ("TPU v5 lite" is v5e, "TPU v5" v5p, "TPU v6 lite" v6e).
PEAK_TFLOPS = (
    ("tpu v6 lite", 918.0),
    ("tpu v6e", 918.0),
    ("tpu v5 lite", 197.0),
    ("tpu v5e", 197.0),
    ("tpu v5p", 459.0),
    ("tpu v5", 459.0),
    ("tpu v4", 275.0),
    ("h200", 989.0),
    ("h100 pcie", 756.0),
    ("h100", 989.0),
    ("a100", 312.0),
)


def peak_tflops(device, given: float | None) -> tuple[float | None, str]:
    """``(peak TFLOP/s or None, where it comes from / why there is none)``."""
    if given is not None:
        return float(given), "--peak-tflops"
    kind = str(getattr(device, "device_kind", device.platform))
    for key, value in PEAK_TFLOPS:
        if key in kind.lower():
            return value, f"dense bf16 peak of {kind!r}"
    return None, (
        f"no peak FLOP/s known for {device.platform} device {kind!r}; pass --peak-tflops "
        f"(TFLOP/s of this device) for an MFU"
    )


def step_flops(cfg, params, *, batch: int, views: int, frames: int, height: int, width: int) -> dict:
    """Analytic model FLOPs of one train step (module docstring): ``{"flops", "matmul_flops",
    "attention_flops", "attention_flops_by_kind", "block_params", "video_tokens", "text_tokens"}``;
    ``attention_flops_by_kind`` splits the attention into ``"self"`` (the spatial or the full
    layout's), ``"temporal"`` and ``"cross"`` (text), which run different kernels
    (``attn_impl`` / ``local_attn_impl``); ``flops`` is None for layouts the formula does not model
    (cross-view attention)."""
    import jax

    pt, ph, pw = cfg.patch
    ft, s = frames // pt, (height // ph) * (width // pw)
    n, txt, d = views * ft * s, (cfg.text_len if cfg.controls.text else 0), cfg.width
    full = cfg.layout == "full"
    matmul = block_params = 0
    by_kind = {"self": 0, "temporal": 0, "cross": 0}  # forward FLOPs; x3 for the step below
    modelled = full or cfg.multiview == "joint"
    for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
        name = jax.tree_util.keystr(path, simple=True, separator="/")
        if not name.startswith("layers_"):
            continue
        size = math.prod(leaf.shape)
        block_params += size
        if not name.endswith("kernel") or "_linear/" in name:  # adaLN modulation: per frame
            continue
        cross = "cross_attn/" in name
        if cross and ("/to_k/" in name or "/to_v/" in name):
            tokens = txt
        else:
            tokens = n + txt if full else n
        matmul += 2 * size * tokens * batch
        if name.endswith("/to_q/kernel"):
            layers = size // (d * d)  # > 1 for scanned layers
            if cross:
                kind, pairs = "cross", n * txt
            elif full:
                kind, pairs = "self", (n + txt) ** 2
            elif "temporal/" in name or "attn_temp/" in name:
                kind, pairs = "temporal", views * s * ft**2
            else:
                kind, pairs = "self", ft * (views * s) ** 2
            by_kind[kind] += 4 * pairs * d * layers * batch
    attn = sum(by_kind.values())
    flops = 3 * (matmul + attn) if modelled else None
    return dict(
        flops=flops,
        matmul_flops=3 * matmul,
        attention_flops=3 * attn,
        attention_flops_by_kind={k: 3 * v for k, v in by_kind.items()},
        block_params=block_params,
        video_tokens=batch * n,
        text_tokens=batch * txt,
    )


def measured_peak_tflops(size: int, dtype: str = "bfloat16", repeats: int = 5) -> float:
    """TFLOP/s of one jitted ``[size, size] @ [size, size]`` matmul in ``dtype`` on the default
    device (median of ``repeats``): the dense matmul peak this device reaches in practice."""
    import jax
    import jax.numpy as jnp

    from jaxdrive.bench.report import median_time

    a = jax.random.normal(jax.random.key(0), (size, size), dtype)
    b = jax.random.normal(jax.random.key(1), (size, size), dtype)
    dot = jax.jit(lambda a, b: jnp.matmul(a, b, preferred_element_type=jnp.float32))
    return 2 * size**3 / median_time(lambda: jax.block_until_ready(dot(a, b)), repeats=repeats) / 1e12
