"""What a compiled train step holds, read from its optimised HLO text (``compiled.as_text()``).

- :func:`program_ops`: counts of the ops that tell a kernel or a collective is there (a Pallas
  TPU kernel is a ``tpu_custom_call``; ring attention rotates K/V with collective-permutes).
- :func:`f32_dots`: every ``dot`` and ``convolution`` whose operands are float32, with the model
  path of the JAX operation it came from (``metadata={op_name=...}``, the named scopes). In a
  bfloat16 step each is a matmul at a fraction of the chip's bf16 rate (the H100 profile put 18%
  of device time in fp32 / tf32 GEMMs): :data:`F32_DOTS_ALLOWED` names those that stay float32,
  each with its reason, and :func:`unlisted_f32_dots` the rest.
"""

from __future__ import annotations

import re

# HLO ops a plan counts in the optimised program
PROGRAM_OPS = {
    "mosaic_kernels": 'custom_call_target="tpu_custom_call"',  # Pallas TPU kernels (splash)
    "collective_permutes": " collective-permute(",  # ring attention's K/V rotation (and its -start form)
    "all_gathers": " all-gather(",
    "all_reduces": " all-reduce(",
}


def program_ops(hlo_text: str) -> dict:
    """Counts of :data:`PROGRAM_OPS` in a compiled program's HLO text (async ``-start`` forms
    included)."""
    count = lambda needle: hlo_text.count(needle) + hlo_text.count(needle.replace("(", "-start("))
    return {k: (hlo_text.count(v) if k == "mosaic_kernels" else count(v)) for k, v in PROGRAM_OPS.items()}


# An instruction line: its name, its result's element type (None for a tuple) and its op; the
# optimised text names operands without their types, so those come from the operands' own lines.
_INSTRUCTION = re.compile(r"^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=\s*(?:(\w+)\[|\()[^=]*?\s([\w\-]+)\((.*)$")
_SHAPES = re.compile(r"\[[^\]]*\]|\{[^}]*\}")  # shapes and layouts, whose commas are not separators
_OP_NAME = re.compile(r'op_name="([^"]*)"')

# Scopes of op_name whose float32 matmuls are deliberate, and why. None has a weight of the trained
# model in it; all but the VAE's contract over 3 to 90 elements.
F32_DOTS_ALLOWED: dict[str, str] = {
    "Encoder3D": "the frozen VAE encoder computes in the dtype its model.json names (CogVideoX's "
    "float32): latents encoded in the step must equal `jaxdrive data encode`'s precomputed ones; "
    "forward only, no gradient (a VAE saved with dtype bfloat16 encodes in bf16)",
    "geometry": "poses, box corners and projections (jaxdrive.geometry) in metres and pixels, "
    "where bf16's 8 bits of mantissa would move a corner 50 m away by 0.2 m; contraction 3 or 4",
    "dct_lowpass": "STAGE's DCT low-pass of the float32 condition latents (data augmentation, "
    "no parameters; contraction h or w of the latent grid)",
    "high_pass": "LongDWM's structure loss: the dense 2D DFT in complex64, which has no bf16 "
    "form (contraction h or w of the latent grid)",
    "hsd,hsd->hs": "splash's backward (JAX's kernel wrapper): rowsum(dO * O) in float32, a "
    "reduction over head_dim written as an einsum",
}


def _operands(rest: str) -> list[str]:
    """The first two operand names of an instruction's argument text, in any of the printed forms:
    ``%a, %b`` (optimised), ``a.1, b.1`` (as lowered) or ``f32[4,4]{1,0} %a, ...`` (typed)."""
    names = [part.split()[-1].lstrip("%") for part in _SHAPES.sub("", rest.split(")", 1)[0]).split(",") if part.strip()]
    return names[:2]


def f32_dots(hlo_text: str) -> list[dict]:
    """``[{"op", "result", "operands", "path"}, ...]``: the dots and convolutions of ``hlo_text``
    with a float32 operand (``path``: the op_name JAX recorded, "" where none)."""
    types, found = {}, []
    for line in hlo_text.splitlines():
        m = _INSTRUCTION.match(line)
        if m is None:
            continue
        name, dtype, op, rest = m.groups()
        types[name] = dtype
        if op in ("dot", "convolution"):
            found.append((op, dtype, _operands(rest), _OP_NAME.search(line)))
    out = []
    for op, dtype, operands, name in found:
        kinds = [types.get(o) for o in operands]
        if "f32" in kinds:
            out.append({"op": op, "result": dtype, "operands": kinds, "path": "" if name is None else name.group(1)})
    return out


def _in_scope(key: str, path: str) -> bool:
    """Whether ``key`` is a whole scope of the op_name ``path``: ``a/key/b``, also under a
    transformation (``jvp(key)/...``, ``transpose(jvp(key))/...``), not ``a/key_0/b``."""
    return re.search(rf"(?<![\w.]){re.escape(key)}(?![\w.])", path) is not None


def unlisted_f32_dots(dots: list[dict], allowed: dict[str, str] = F32_DOTS_ALLOWED) -> list[dict]:
    """The entries of ``dots`` in none of the scopes that ``allowed`` names."""
    return [d for d in dots if not any(_in_scope(key, d["path"]) for key in allowed)]
