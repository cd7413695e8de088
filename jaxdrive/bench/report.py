"""Shared output and timing helpers of the benchmarks."""

from __future__ import annotations

import json
import time

import jax

from jaxdrive.xla_flags import add_xla_flags, deterministic_cpu


def ensure_devices(n: int) -> None:
    """Ask for ``n`` fake CPU devices (for sharded figures on a CPU host); it only works before JAX
    initialises its backend, so call it first thing in a benchmark's ``main``."""
    add_xla_flags(f"--xla_force_host_platform_device_count={n}")
    deterministic_cpu()


def emit(bench: str, figure: str, value, unit: str, **context) -> dict:
    """Print one figure as a JSON line (``{"bench", "figure", "value", "unit", ...}``)."""
    row = {"bench": bench, "figure": figure, "value": value, "unit": unit, **context}
    print(json.dumps(row, sort_keys=True), flush=True)
    return row


def table(rows: list[dict], columns: list[str]) -> str:
    """A plain-text table of ``rows`` restricted to ``columns``."""
    cells = [[str(r.get(c, "")) for c in columns] for r in rows]
    widths = [max(len(c), *(len(row[i]) for row in cells)) for i, c in enumerate(columns)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(columns, widths)),
             "  ".join("-" * w for w in widths)]
    lines += ["  ".join(v.ljust(w) for v, w in zip(row, widths)) for row in cells]
    return "\n".join(lines)


def best_time(fn, *, repeats: int = 5) -> float:
    """Best wall time in seconds of ``fn()`` over ``repeats`` runs, blocking on its outputs."""
    jax.block_until_ready(fn())  # warm-up
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - start)
    return best


def median_time(fn, *, repeats: int) -> float:
    """Median wall time in seconds of ``fn()`` over ``repeats`` calls after one warm-up call;
    ``fn`` blocks on its own result (a JAX function wrapped in ``jax.block_until_ready``, or a
    PyTorch CPU call, which returns when done)."""
    import statistics
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def temp_bytes(compiled) -> int | None:
    """Temporary (scratch) memory of a compiled program, or None where the backend has no analysis."""
    analysis = compiled.memory_analysis()
    return None if analysis is None else int(analysis.temp_size_in_bytes)


def footprint_bytes(compiled) -> int | None:
    """Everything a compiled program holds on one device while it runs: its arguments, outputs and
    temporary memory, less the outputs that alias (donated) arguments (``memory_analysis()``), or
    None where the backend has no analysis."""
    a = compiled.memory_analysis()
    if a is None:
        return None
    return int(a.argument_size_in_bytes + a.output_size_in_bytes + a.temp_size_in_bytes
               - a.alias_size_in_bytes)
