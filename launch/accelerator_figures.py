"""The figures of ``launch/accelerator_bench.sh``, gathered from its steps' logs.

    python launch/accelerator_figures.py WORK OUT [--print]

WORK holds ``steps.tsv`` (step, status, seconds, last lines) and one ``STEP.log`` per step (the
benchmarks' JSON figure lines among the rest); writes OUT/figures.jsonl (every figure with its
``step``), OUT/figures.md (the tables) and OUT/profile_top.json (the largest device costs of the
train setting with the most tokens/s). ``--print`` prints figures.md. Reads text only (no JAX), so
the script can run it after every step.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path


def figures(work: Path) -> list[dict]:
    """Every JSON figure line (``bench``, ``figure``, ``value``, ...) of the step logs, with ``step``."""
    rows = []
    for line in (work / "steps.tsv").read_text().splitlines():
        name = line.split("\t")[0]
        log = work / f"{name}.log"
        if not log.exists():
            continue
        for text in log.read_text(errors="replace").splitlines():
            if not text.startswith("{"):
                continue
            try:
                row = json.loads(text)
            except ValueError:
                continue
            if isinstance(row, dict) and "bench" in row and "figure" in row:
                rows.append({"step": name, **row})
    return rows


def _table(header: list[str], rows: list[list]) -> list[str]:
    cell = lambda v: "" if v is None else (f"{v:.4g}" if isinstance(v, float) else str(v))
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)] + [
        "| " + " | ".join(cell(v) for v in r) + " |" for r in rows
    ]


def _value(rows, step, figure, **match):
    for r in rows:
        if r["step"] == step and r["figure"] == figure and all(r.get(k) == v for k, v in match.items()):
            return r
    return None


def _gib(mib):
    return None if mib is None else round(mib / 1024, 2)


def markdown(work: Path, rows: list[dict]) -> tuple[str, dict | None]:
    """figures.md's text and the best train setting's profile summary (or None)."""
    lines = ["# Accelerator figures", ""]
    for name, keep in (("preflight.log", ("python ", "backend ")), ("env.txt", ("XLA_FLAGS",))):
        if (work / name).exists():
            lines += [f"    {t}" for t in (work / name).read_text(errors="replace").splitlines() if t.startswith(keep)]
    lines.append("")
    steps = [line.split("\t") for line in (work / "steps.tsv").read_text().splitlines() if line.strip()]
    lines += (
        ["## Steps", ""]
        + _table(
            ["step", "status", "seconds", "last lines (failed steps)"],
            [[s[0], s[1], s[2], s[3] if s[1] != "ok" and len(s) > 3 else ""] for s in steps],
        )
        + [""]
    )

    train = sorted({r["step"] for r in rows if r["bench"] == "train"})
    best, best_tps = None, -1.0
    table = []
    for step in train:
        get = lambda f: (_value(rows, step, f) or {}).get("value")
        mfu_m = _value(rows, step, "mfu_measured") or {}
        tps = get("tokens_per_s")
        if tps is not None and tps > best_tps:
            best, best_tps = step, tps
        shape = (_value(rows, step, "step_time") or {}).get("shape")
        table.append(
            [
                step.removeprefix("train-"),
                get("batch"),
                shape and "x".join(map(str, shape[1:])),
                get("step_time"),
                tps,
                get("achieved_tflops"),
                get("mfu"),
                mfu_m.get("value"),
                mfu_m.get("peak_tflops"),
                _gib(get("peak_device_memory")),
                _gib(get("step_memory")),
                get("compile_time"),
            ]
        )
    profile = None
    if train:
        model = next((r for r in rows if r["bench"] == "train" and r["figure"] == "params"), {})
        what = f"{model['model']}, {model['value']} parameters, " if model else ""
        lines += [f"## Train step ({what}bf16 compute, fp32 master weights, scanned layers)", ""]
        lines += _table(
            [
                "remat",
                "batch",
                "V x F x h x w",
                "step ms",
                "tokens/s",
                "TFLOP/s",
                "MFU (vendor peak)",
                "MFU (measured peak)",
                "measured bf16 TFLOP/s",
                "peak GiB",
                "compiled GiB",
                "compile s",
            ],
            table,
        ) + [""]
    if best is not None:
        costs = sorted(
            (r for r in rows if r["step"] == best and r["figure"] == "profile_cost"), key=lambda r: r["rank"]
        )
        if costs:
            profile = {
                "setting": best,
                "device_ms_per_step": costs[0].get("device_ms_per_step"),
                "top": [{k: r.get(k) for k in ("rank", "op", "category", "value", "share", "kernel")} for r in costs],
                "trace": costs[0].get("trace"),
            }
            top_file = Path(costs[0]["trace"]).parents[3] / "top_costs.json" if costs[0].get("trace") else None
            if top_file is not None and top_file.exists():
                profile.update(json.loads(top_file.read_text()), setting=best)
            lines += [
                f"## Largest device costs of {best} (jax.profiler, {profile['device_ms_per_step']} ms of "
                f"device time a step)",
                "",
            ]
            lines += _table(
                ["rank", "op", "category", "ms / step", "share", "kernel"],
                [[r["rank"], r["op"], r["category"], r["value"], r["share"], (r["kernel"] or "")[:60]] for r in costs],
            ) + [""]
            if profile.get("categories"):
                lines += [
                    "by category (ms / step): " + ", ".join(f"{k} {v}" for k, v in profile["categories"].items()),
                    "",
                ]

    vae = sorted({r["step"] for r in rows if r["bench"] == "vae"})
    if vae:
        first = _value(rows, vae[0], "decode_seconds") or {}
        lines += [
            f"## VAE decode ({first.get('config')}, {first.get('frames')} frames at {first.get('height')} x "
            f"{first.get('width')}, {first.get('dtype')})",
            "",
        ]
        vrows = []
        for step in vae:
            for r in rows:
                if r["step"] == step and r["figure"] == "decode_seconds":
                    get = lambda f: (_value(rows, step, f, mode=r["mode"]) or {}).get("value")
                    vrows.append(
                        [
                            r["mode"],
                            r["value"],
                            get("decode_frames_per_s"),
                            _gib(get("decode_peak_device_memory")),
                            _gib(get("decode_compiled_temp_memory")),
                            get("decode_compile_time"),
                        ]
                    )
        lines += _table(["mode", "seconds", "frames/s", "peak GiB", "compiled temp GiB", "compile s"], vrows) + [""]

    seen, lrows = set(), []
    for r in rows:
        if r["bench"] != "longvideo" or r["figure"] != "seconds" or (r["strategy"], r["frames"]) in seen:
            continue
        seen.add((r["strategy"], r["frames"]))
        get = lambda f: (_value(rows, r["step"], f, strategy=r["strategy"], frames=r["frames"]) or {}).get("value")
        lrows.append(
            [
                r["strategy"],
                r["frames"],
                r["value"],
                get("seconds_per_frame"),
                get("sequential_sampler_calls"),
                get("peak_device_memory"),
                get("compiled_programs"),
            ]
        )
    if lrows:
        lines += ["## Long video (tiny recipe's models, random weights)", ""]
        lines += _table(
            ["strategy", "frames", "seconds", "s / frame", "sequential calls", "peak MiB", "programs"], lrows
        ) + [""]
        ratio = next((r for r in rows if r["figure"] == "coarse_fine_145_over_one_window"), None)
        if ratio:
            lines += [f"coarse-fine, 145 frames: {ratio['value']} x the time of one window", ""]
    return "\n".join(lines), profile


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) not in (2, 3) or (len(argv) == 3 and argv[2] != "--print"):
        print(__doc__.split("\n\n")[1], file=sys.stderr)
        return 2
    work, out = Path(argv[0]), Path(argv[1])
    rows = figures(work)
    with open(out / "figures.jsonl", "w") as f:
        for r in rows:
            f.write(json.dumps(r, sort_keys=True) + "\n")
    text, profile = markdown(work, rows)
    (out / "figures.md").write_text(text + "\n")
    if profile is not None:
        (out / "profile_top.json").write_text(json.dumps(profile, indent=1) + "\n")
        trace = Path(profile["trace"]) if profile.get("trace") else None
        if trace is not None and trace.exists() and trace.stat().st_size < 15 * 2**20:
            shutil.copy(trace, out / "profile_trace.json.gz")
    if len(argv) == 3:
        print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
