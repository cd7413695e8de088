"""XLA flags that jaxdrive sets before JAX starts its backend (``XLA_FLAGS`` is read once, when
the first client is created, so these calls must come before the first computation).

- :func:`add_xla_flags`: append flags to ``XLA_FLAGS``, keeping any the user already set.
- :func:`deterministic_cpu`: turn off XLA:CPU's YNNPACK fusions. With them on (jaxlib 0.10), one
  compiled program called again and again on the same inputs sometimes returns a different result
  when the process has more than one core. The tiny config's train loss was wrong by up to 40% on
  about 1 call in 30 on a 2-core machine, and right every time pinned to one core or with these
  fusions off. jax-ml/jax#39741 (open) reports the same symptom. Bit-exact resume and every
  sharded-versus-single-device test rely on a program giving the same numbers on every call.
  Turning only the dot fusions back on (``--xla_cpu_experimental_ynn_fusion_type=dot``) would make
  the small train step about 4% faster and the tiny one up to 1.8x, but one test's program (the
  foreground-weighted loss, ``tests/test_train_losses.py``) then returns NaN on every call, so
  every YNNPACK fusion stays off. The reduce fusions also crash on some rank-7/8 reductions in this
  jaxlib (jax-ml/jax#39257, #40412).
  ``jaxdrive`` commands, the benchmarks and the tests call it. Library users on CPU call it first
  thing, or set the flag in ``XLA_FLAGS`` themselves. ``JAXDRIVE_CPU_FLAGS=0`` leaves it out: XLA
  aborts at start on a flag its version does not know, and this one is experimental, so a jaxlib
  that dropped it (``launch/accelerator_bench.sh`` checks) runs without it.
- :func:`fast_compiling_cpu`: XLA:CPU's older (non-MLIR) fusion emitters, for runs whose time is
  compiling small programs, as a CPU test suite's is. The tiny config's train step (depth 1, 2 views,
  5 frames, 8 fake devices, most optimisations off) compiles in 11 s instead of 19 (21.5 against
  37.7 CPU-seconds, 1092 fusions instead of 1464) and runs a step in 1.0 s instead of 0.8. The HLO
  is the same, the kernels differ: numbers agree to float rounding, not bit for bit. It also
  compiles each program's LLVM module in one piece (:data:`CPU_SERIAL_CODEGEN`): XLA:CPU splits
  it into parts to compile them on several threads, but splitting costs time of its own (8% of
  the tiny train step's compile under ``perf``), and a test suite already keeps every core busy
  with its workers. Serial, the same step compiled with 9.4-9.9 CPU-seconds instead of 11.6-13.0
  (one device; the same loss, bit for bit), and five compile-heavy tests took 100 CPU-seconds
  instead of 107. The tests (``tests/conftest.py``) call it; jaxdrive's commands do not, their
  steps run many times.
"""

from __future__ import annotations

import os
from importlib import metadata

# Empty: no op kind is fused into a YNNPACK call (checked on jaxlib 0.10.2; older jaxlibs are left alone).
CPU_DETERMINISTIC = "--xla_cpu_experimental_ynn_fusion_type="
# XLA:CPU's loop and reduction fusions compiled by the older emitters, not the MLIR ones.
CPU_FAST_COMPILE = "--xla_cpu_use_fusion_emitters=false"
# Each program's LLVM module compiled whole, on the compiling thread, not split into parts.
CPU_SERIAL_CODEGEN = "--xla_cpu_parallel_codegen_split_count=1"


def add_xla_flags(*flags: str) -> None:
    """Append each ``--name=value`` flag to ``XLA_FLAGS`` unless a flag of that name is there."""
    for flag in flags:
        if not flag.startswith("--") or "=" not in flag:
            raise ValueError(f"flags: expected '--name=value', got {flag!r}")
        current = os.environ.get("XLA_FLAGS", "")
        if flag.split("=")[0] + "=" not in current:
            os.environ["XLA_FLAGS"] = (current + " " + flag).strip()


def _jaxlib_version() -> tuple[int, ...]:
    try:
        return tuple(int(p) for p in metadata.version("jaxlib").split(".")[:2])
    except (metadata.PackageNotFoundError, ValueError):
        return (0,)


def _add_cpu_flag(flag: str) -> bool:
    """Add an XLA:CPU ``flag`` that jaxlib 0.10 knows (XLA aborts on an unknown one) unless
    ``JAXDRIVE_CPU_FLAGS`` is ``0``. Returns whether the flag was added or already set."""
    if _jaxlib_version() < (0, 10) or os.environ.get("JAXDRIVE_CPU_FLAGS") == "0":
        return False
    add_xla_flags(flag)
    return True


def deterministic_cpu() -> bool:
    """Add :data:`CPU_DETERMINISTIC` (the same numbers on every call), as :func:`_add_cpu_flag` does."""
    return _add_cpu_flag(CPU_DETERMINISTIC)


def fast_compiling_cpu() -> bool:
    """Add :data:`CPU_FAST_COMPILE` (faster compiles, slower kernels) and :data:`CPU_SERIAL_CODEGEN`
    (less compiling work, on one thread), as :func:`_add_cpu_flag` does."""
    return _add_cpu_flag(CPU_FAST_COMPILE) & _add_cpu_flag(CPU_SERIAL_CODEGEN)
