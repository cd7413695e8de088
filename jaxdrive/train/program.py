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
_OPERAND = re.compile(r"%([\w.\-]+)")
_OP_NAME = re.compile(r'op_name="([^"]*)"')

# Model paths (a substring of op_name) whose float32 matmuls are deliberate, and why.
F32_DOTS_ALLOWED: dict[str, str] = {}


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
            found.append((op, dtype, _OPERAND.findall(rest.split(")", 1)[0])[:2], _OP_NAME.search(line)))
    out = []
    for op, dtype, operands, name in found:
        kinds = [types.get(o) for o in operands]
        if "f32" in kinds:
            out.append({"op": op, "result": dtype, "operands": kinds, "path": "" if name is None else name.group(1)})
    return out


def unlisted_f32_dots(dots: list[dict], allowed: dict[str, str] = F32_DOTS_ALLOWED) -> list[dict]:
    """The entries of ``dots`` whose path no key of ``allowed`` is a substring of."""
    return [d for d in dots if not any(key in d["path"] for key in allowed)]
