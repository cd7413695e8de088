"""launch/accelerator_bench.sh end to end at toy sizes on the CPU (--tiny): every step writes its
figures, and figures.md gathers them."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow(seconds=79)
def test_tiny_run_writes_every_figure(tmp_path):
    out = tmp_path / "out"
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_PLATFORMS")}
    # the test's XLA flags but its 8 fake devices: the bench counts the machine's own
    env["XLA_FLAGS"] = " ".join(f for f in os.environ["XLA_FLAGS"].split() if "device_count" not in f)
    env.update(PYTHON=sys.executable, TMPDIR=str(tmp_path))
    done = subprocess.run(
        ["bash", str(ROOT / "launch" / "accelerator_bench.sh"), "--tiny", "--out", str(out)],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=1800,
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert sorted(p.name for p in out.iterdir()) == [
        "figures.jsonl",
        "figures.md",
        "log.txt",
        "profile_top.json",
        "profile_trace.json.gz",
    ]
    rows = [json.loads(line) for line in (out / "figures.jsonl").read_text().splitlines()]
    by = lambda step, figure: [r for r in rows if r["step"] == step and r["figure"] == figure]
    for remat in ("dots", "full"):
        step = f"train-{remat}"
        (batch,) = by(step, "batch")
        assert 1 <= batch["value"] <= 2 and batch["probes"][0][0] == 1 and batch["limit"] > 0
        assert by(step, "step_time")[0]["value"] > 0 and by(step, "tokens_per_s")[0]["value"] > 0
        assert by(step, "mfu_measured")[0]["value"] > 0
        costs = by(step, "profile_cost")
        assert [c["rank"] for c in costs] == list(range(1, len(costs) + 1)) and costs
        assert all(c["value"] >= 0 and c["op"] for c in costs)
    for mode in ("chunked", "whole"):
        (sec,) = by(f"vae-{mode}", "decode_seconds")
        assert sec["mode"] == mode and sec["value"] > 0 and sec["frames"] == 9
    long = by("longvideo-coarse-fine", "sequential_sampler_calls")
    assert {(r["strategy"], r["frames"]) for r in long} == {("rollout", 9), ("coarse-fine", 17)}
    assert all(r["value"] >= 1 for r in long)
    md = (out / "figures.md").read_text()
    steps = [line for line in md.splitlines() if line.startswith(("| train-", "| vae-", "| longvideo-", "| preflight"))]
    assert len(steps) == 6 and all("| ok |" in line for line in steps), md
    for title in ("## Train step", "## Largest device costs", "## VAE decode", "## Long video"):
        assert title in md
    top = json.loads((out / "profile_top.json").read_text())
    assert top["setting"] in ("train-dots", "train-full") and top["top"]
    assert "world: skipped (--tiny)" in done.stdout
