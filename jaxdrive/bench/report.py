"""Shared output and timing helpers of the benchmarks."""

from __future__ import annotations

import contextlib
import json
import logging
import time

import jax

from jaxdrive.parallel.memory import footprint_bytes  # noqa: F401  (re-exported: the benches read it here)
from jaxdrive.xla_flags import add_xla_flags, deterministic_cpu


def ensure_devices(n: int) -> None:
    """Ask for ``n`` fake CPU devices (for sharded figures on a CPU host); it only works before JAX
    initialises its backend, so call it first thing in a benchmark's ``main``."""
    add_xla_flags(f"--xla_force_host_platform_device_count={n}")
    deterministic_cpu()


@contextlib.contextmanager
def quiet(name: str):
    """The logger ``name`` at WARNING while the block runs: the INFO line a library call logs each
    time it runs, of which a benchmark's table already holds the figures."""
    logger = logging.getLogger(name)
    level = logger.level
    logger.setLevel(logging.WARNING)
    try:
        yield
    finally:
        logger.setLevel(level)


def emit(bench: str, figure: str, value, unit: str, **context) -> dict:
    """Print one figure as a JSON line (``{"bench", "figure", "value", "unit", ...}``)."""
    row = {"bench": bench, "figure": figure, "value": value, "unit": unit, **context}
    print(json.dumps(row, sort_keys=True), flush=True)
    return row


def table(rows: list[dict], columns: list[str]) -> str:
    """A plain-text table of ``rows`` restricted to ``columns``."""
    cells = [[str(r.get(c, "")) for c in columns] for r in rows]
    widths = [max(len(c), *(len(row[i]) for row in cells)) for i, c in enumerate(columns)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(columns, widths)), "  ".join("-" * w for w in widths)]
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


def peak_device_bytes(device=None) -> int | None:
    """The most bytes ``device`` (default: the first) has held at once in this process
    (``memory_stats()["peak_bytes_in_use"]``: it never goes down, so a figure for one measurement
    wants a process of its own), or None where the device keeps no such count (a CPU)."""
    device = jax.devices()[0] if device is None else device
    stats = device.memory_stats() if hasattr(device, "memory_stats") else None
    return int(stats["peak_bytes_in_use"]) if stats and "peak_bytes_in_use" in stats else None


# Threads of a trace that repeat the device's work at another level (whole modules, steps, name
# scopes) rather than being it: left out of the sums so that nothing counts twice.
_DERIVED_LINES = ("xla modules", "steps", "xla ops", "framework", "tensorflow", "source", "xla tracemes")
_CATEGORIES = (
    ("attention", ("fmha", "flash", "cudnn", "attention", "sdpa")),  # before matmul: wgmma inside
    # before matmul: an fp32 or tf32 GEMM in a bf16 step is a matmul that left the tensor cores' bf16 path
    ("matmul fp32/tf32", ("f32f32", "s1688gemm", "sgemm", "gemmsn_nn_kernel<float")),
    ("matmul", ("gemm", "cublas", "cutlass", "xmma", "nvjet", "matmul", "dot", "ynn_fusion")),
    ("memory copy", ("memcpy", "memset", "copy")),
    ("collective", ("nccl", "all-reduce", "all-gather", "reduce-scatter", "all-to-all")),
)


def _category(*names: str) -> str:
    text = " ".join(n.lower() for n in names if n)
    return next((cat for cat, keys in _CATEGORIES if any(k in text for k in keys)), "other (fusions, elementwise)")


def trace_costs(log_dir, *, steps: int = 1, top: int = 3) -> dict:
    """The largest device costs of the newest ``jax.profiler.trace(log_dir, create_perfetto_trace=True)``
    under ``log_dir``: the durations of its device events (a GPU's or TPU's kernels; on a CPU the
    XLA thunks, the events that name an ``hlo_op``) summed by the HLO operation they ran (else by
    their name), per step. Returns ``{"trace", "steps", "device_ms_per_step", "top": [{"op", "ms_per_step",
    "share", "events", "kernel", "category"}, ...], "categories": {category: ms_per_step}}``; ``category``
    is a guess from the names (matmul, attention, memory copy, collective, other); the summary is also
    written to
    ``log_dir/top_costs.json``."""
    import glob
    import gzip
    import os
    from collections import defaultdict

    found = sorted(
        glob.glob(os.path.join(str(log_dir), "**", "perfetto_trace.json.gz"), recursive=True), key=os.path.getmtime
    )
    if not found:
        raise ValueError(f"log_dir: expected a perfetto_trace.json.gz under {str(log_dir)!r}, found none")
    with gzip.open(found[-1], "rt") as f:
        trace = json.load(f)
    events = trace["traceEvents"] if isinstance(trace, dict) else trace
    processes, threads = {}, {}
    for e in events:
        if e.get("ph") == "M" and e.get("name") == "process_name":
            processes[e.get("pid")] = str(e.get("args", {}).get("name", ""))
        elif e.get("ph") == "M" and e.get("name") == "thread_name":
            threads[(e.get("pid"), e.get("tid"))] = str(e.get("args", {}).get("name", ""))
    device = {pid for pid, name in processes.items() if name.startswith("/device:")}
    spans = [e for e in events if e.get("ph") == "X" and "dur" in e]
    if device:
        spans = [
            e
            for e in spans
            if e.get("pid") in device
            and not threads.get((e.get("pid"), e.get("tid")), "").lower().startswith(_DERIVED_LINES)
        ]
    else:
        spans = [e for e in spans if "hlo_op" in (e.get("args") or {})]
    total = defaultdict(float)
    count = defaultdict(int)
    kernel = {}
    categories = defaultdict(float)
    for e in spans:
        args = e.get("args") or {}
        op = str(args.get("hlo_op") or e.get("name"))
        if op.startswith("command_buffer"):
            # a GPU command buffer (one CUDA graph of many fused ops) names all its kernels after
            # itself: the kernel's own name says what ran
            op = str(e.get("name"))
        total[op] += float(e["dur"])
        count[op] += 1
        kernel.setdefault(op, str(e.get("name")))
        categories[_category(op, str(e.get("name")))] += float(e["dur"])
    whole = sum(total.values())
    ranked = sorted(total, key=total.get, reverse=True)[:top]
    result = {
        "trace": found[-1],
        "steps": steps,
        "device_ms_per_step": round(whole / 1e3 / steps, 3),
        "top": [
            {
                "op": op,
                "ms_per_step": round(total[op] / 1e3 / steps, 3),
                "share": round(total[op] / whole, 4) if whole else None,
                "events": count[op],
                "kernel": kernel[op][:200],
                "category": _category(op, kernel[op]),
            }
            for op in ranked
        ],
        "categories": {c: round(d / 1e3 / steps, 3) for c, d in sorted(categories.items(), key=lambda kv: -kv[1])},
    }
    with open(os.path.join(str(log_dir), "top_costs.json"), "w") as f:
        json.dump(result, f, indent=1)
    return result
