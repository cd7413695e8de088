"""The train-step benchmark: its JSON figures (one compile of the tiny comparison model against
diffusers' PyTorch step) and its analytic FLOPs against hand-counted ones."""

import gzip
import json

import flax.linen as nn
import pytest

from jaxdrive.bench import flops as model_flops
from jaxdrive.bench import train as bench
from jaxdrive.bench.fit import largest_batch
from jaxdrive.bench.report import trace_costs
from jaxdrive.bench.train_steps import diffusers_config
from jaxdrive.convert.diffusers_dit import config_from_diffusers
from jaxdrive.models.dit import DiT
from jaxdrive.models.dit.presets import preset


def _rows(out):
    return [json.loads(line) for line in out.splitlines() if line.startswith("{")]


@pytest.mark.slow(seconds=14)
def test_train_benchmark_prints_tokens_per_s_and_the_torch_ratio(capsys):
    pytest.importorskip("torch")
    pytest.importorskip("diffusers")
    from jaxdrive.cli import main

    main(
        [
            "bench",
            "train",
            "--presets",
            "tiny",
            "--compare-only",
            "--repeats",
            "1",
            "--frames",
            "2",
            "--height",
            "4",
            "--width",
            "4",
            "--no-ops",
        ]
    )
    rows = _rows(capsys.readouterr().out)
    assert all(r["bench"] == "train" for r in rows)
    tps = {r["impl"]: r["value"] for r in rows if r["figure"] == "tokens_per_s"}
    assert tps["jaxdrive"] > 0 and tps["torch"] > 0
    params = {r["impl"]: r["value"] for r in rows if r["figure"] == "params"}
    assert params["jaxdrive"] == params["torch"] > 0
    ratio = next(r for r in rows if r["figure"] == "torch_ratio")
    assert ratio["value"] == pytest.approx(tps["jaxdrive"] / tps["torch"], rel=1e-2)
    mfu = next(r for r in rows if r["figure"] == "mfu")
    assert mfu["value"] is None and "--peak-tflops" in mfu["reason"]  # a CPU has no known peak
    flops = next(r for r in rows if r["figure"] == "model_flops_per_step")
    assert flops["value"] > 0 and next(r for r in rows if r["figure"] == "compile_time")["value"] > 0


@pytest.mark.slow(seconds=6)
def test_json_rows_hold_the_step_and_single_op_comparisons(capsys):
    pytest.importorskip("torch")
    pytest.importorskip("diffusers")
    from jaxdrive.cli import main

    main(
        [
            "bench",
            "train",
            "--presets",
            "tiny",
            "--compare-only",
            "--repeats",
            "1",
            "--frames",
            "2",
            "--height",
            "4",
            "--width",
            "4",
            "--json",
        ]
    )
    lines = [line for line in capsys.readouterr().out.splitlines() if line.strip()]
    rows = [json.loads(line) for line in lines]  # every line is one JSON object
    steps = {r["impl"]: r for r in rows if r["model"] == "tiny-full/diffusers"}
    assert set(steps) == {"jaxdrive", "torch"}
    for r in steps.values():
        assert {"model", "impl", "step_ms", "tokens_per_s", "ratio_to_torch"} <= set(r) and r["step_ms"] > 0
    assert steps["jaxdrive"]["ratio_to_torch"] == pytest.approx(
        steps["jaxdrive"]["tokens_per_s"] / steps["torch"]["tokens_per_s"], rel=2e-2
    )
    ops = [r for r in rows if r["model"].startswith("op: ")]
    names = {r["model"] for r in ops}
    assert any(n.startswith("op: matmul ") for n in names) and any("softmax" in n for n in names)
    assert len(ops) == 2 * len(names)  # each op in both implementations
    for name in names:
        pair = {r["impl"]: r for r in ops if r["model"] == name}
        assert pair["jaxdrive"]["ratio_to_torch"] == pytest.approx(
            pair["torch"]["step_ms"] / pair["jaxdrive"]["step_ms"], rel=2e-2
        )
    matmul = next(r for r in ops if r["model"].startswith("op: matmul ") and r["impl"] == "jaxdrive")
    assert matmul["gflops"] > 0


def _flops(cfg, **shapes):
    params = nn.unbox(DiT(cfg).abstract_params(views=1, frames=shapes["frames"]))
    return model_flops.step_flops(cfg, params, views=1, **shapes)


def test_full_layout_flops_are_6_params_tokens_plus_attention():
    dcfg = diffusers_config(preset("tiny-full"), frames=3, height=4, width=6)
    cfg = config_from_diffusers(dcfg)
    f = _flops(cfg, batch=2, frames=3, height=4, width=6)
    d, depth, seq = cfg.width, cfg.depth, 3 * 2 * 3 + cfg.text_len  # [text; video] per clip
    assert f["video_tokens"] == 2 * 18 and f["text_tokens"] == 2 * cfg.text_len
    assert f["matmul_flops"] == 6 * depth * 12 * d * d * 2 * seq  # qkv + out 4 D^2, MLP 8 D^2
    assert f["attention_flops"] == 3 * depth * 4 * seq**2 * d * 2
    assert f["flops"] == f["matmul_flops"] + f["attention_flops"]


def test_one_layer_flops_are_the_hand_count():
    """depth 1, width 64 (4 heads x 16), text 8, batch 2, 3 x 4 x 6 latents in 2 x 2 patches: 18
    video + 8 text = 26 tokens a clip. Matmuls: 12 * 64^2 weights (q, k, v, out 4 D^2; MLP 8 D^2),
    6 FLOPs per weight and token (forward 2, backward 4): 6 * 49152 * 26 * 2 = 15,335,424.
    Attention: QK^T and AV, 4 * 26^2 * 64 forward, x 3 with the backward, x 2 clips: 1,038,336."""
    dcfg = diffusers_config(preset("tiny-full").replace(depth=1), frames=3, height=4, width=6)
    f = _flops(config_from_diffusers(dcfg), batch=2, frames=3, height=4, width=6)
    assert f["matmul_flops"] == 15_335_424 and f["attention_flops"] == 1_038_336
    assert f["flops"] == 16_373_760


def test_factorized_flops_count_spatial_temporal_and_text_attention():
    cfg = preset("tiny")
    f = _flops(cfg, batch=1, frames=3, height=4, width=4)
    d, depth, s, nf, txt = cfg.width, cfg.depth, 4, 3, cfg.text_len
    n = nf * s
    # two blocks a layer (spatial, temporal), each: self-attention 4 D^2, text cross-attention q / out
    # 2 D^2 on video tokens and k / v 2 D^2 on text tokens, MLP 8 D^2
    assert f["matmul_flops"] == 6 * depth * 2 * (14 * d * d * n + 2 * d * d * txt)
    assert f["attention_flops"] == 3 * depth * 4 * d * (nf * s**2 + s * nf**2 + 2 * n * txt)
    # the split by the kernel each runs in (attn_impl: self; local_attn_impl: temporal, cross)
    assert f["attention_flops_by_kind"] == {
        "self": 3 * depth * 4 * d * nf * s**2,
        "temporal": 3 * depth * 4 * d * s * nf**2,
        "cross": 3 * depth * 4 * d * 2 * n * txt,
    }


def test_peak_is_known_for_accelerators_and_given_on_cpu():
    class Dev:
        platform, device_kind = "tpu", "TPU v5 lite"

    assert model_flops.peak_tflops(Dev(), None) == (197.0, "dense bf16 peak of 'TPU v5 lite'")
    Dev.platform, Dev.device_kind = "cpu", "cpu"
    assert model_flops.peak_tflops(Dev(), None)[0] is None
    assert model_flops.peak_tflops(Dev(), 1.5) == (1.5, "--peak-tflops")


@pytest.mark.slow(seconds=14)
def test_accelerator_settings_reach_the_model_and_the_measured_peak_gives_an_mfu(capsys, monkeypatch):
    seen, step = [], bench.jax_step
    monkeypatch.setattr(bench, "jax_step", lambda cfg, *a, **k: seen.append(cfg) or step(cfg, *a, **k))
    rows = bench.main(
        [
            "--presets",
            "tiny",
            "--no-torch",
            "--dtype",
            "bfloat16",
            "--remat",
            "full",
            "--scan-layers",
            "--attn-impl",
            "blockwise",
            "--local-attn-impl",
            "blockwise",
            "--cross-attn-impl",
            "xla",
            "--measure-peak",
            "64",
            "--json",
            "--repeats",
            "1",
            "--frames",
            "2",
            "--height",
            "4",
            "--width",
            "4",
        ]
    )
    assert [(c.dtype, c.remat, c.scan_layers, c.attn_impl, c.local_attn_impl, c.cross_impl) for c in seen] == [
        ("bfloat16", "full", True, "blockwise", "blockwise", "xla")
    ]
    (row,) = rows
    assert row["model"] == "tiny" and row["measured_peak_tflops"] > 0
    assert row["mfu_measured"] == pytest.approx(row["tflops"] / row["measured_peak_tflops"], rel=2e-2)
    printed = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.strip()]
    assert [r["model"] for r in printed] == ["tiny"]


def test_arguments_are_checked():
    with pytest.raises(SystemExit):
        bench.main(["--presets", "tiny", "--dtype", "bfloat16"])  # torch compares float32
    with pytest.raises(SystemExit):
        bench.main(["--no-torch", "--compare-only"])
    with pytest.raises(SystemExit):
        bench.main(["--repeats", "0"])
    with pytest.raises(SystemExit):
        bench.main(["--batch", "auto"])  # the search is jaxdrive's alone
    with pytest.raises(SystemExit):
        bench.main(["--batch", "many", "--no-torch"])
    with pytest.raises(SystemExit):
        bench.main(["--batch", "auto", "--no-torch"])  # a CPU has no memory limit
    with pytest.raises(SystemExit):
        bench.main(["--batch", "auto", "--no-torch", "--device-memory", "1GiB", "--memory-fraction", "1.5"])


def test_batch_search_predicts_from_two_probes_and_backs_off():
    calls = []

    def footprint(b):  # 10 GB of state, 3 GB a clip, and 1 GB more above 8 clips
        return 10 + 3 * b + (b > 8)

    def probes(bs):
        calls.append(list(bs))
        return [footprint(b) for b in bs]

    batch, seen = largest_batch(probes, 36, 64)
    assert batch == 8 and calls[0] == [1, 2]  # line: 10 + 3b <= 36 -> 8; 8 needs 34
    assert seen[:2] == [(1, 13), (2, 16)] and seen[2] == (8, 34)
    batch, seen = largest_batch(probes, 37, 64)  # 9 needs 38 > 37: back to 8
    assert batch == 8 and [b for b, _ in seen] == [1, 2, 9, 8]
    assert largest_batch(probes, 100, 5)[0] == 5  # capped
    assert largest_batch(probes, 13, 1) == (1, [(1, 13)])
    with pytest.raises(ValueError, match="batch of 1"):
        largest_batch(probes, 12, 64)


def test_trace_costs_sum_device_events_by_op(tmp_path):
    run = tmp_path / "plugins" / "profile" / "2026_01_01"
    run.mkdir(parents=True)
    events = [
        {"ph": "M", "pid": 1, "name": "process_name", "args": {"name": "/device:GPU:0"}},
        {"ph": "M", "pid": 2, "name": "process_name", "args": {"name": "/host:CPU"}},
        {"ph": "M", "pid": 1, "tid": 7, "name": "thread_name", "args": {"name": "XLA Ops"}},
        {"ph": "X", "pid": 1, "tid": 5, "dur": 300.0, "name": "sm90_xmma_gemm_bf16", "args": {"hlo_op": "dot.1"}},
        {"ph": "X", "pid": 1, "tid": 5, "dur": 300.0, "name": "sm90_xmma_gemm_bf16", "args": {"hlo_op": "dot.1"}},
        {
            "ph": "X",
            "pid": 1,
            "tid": 5,
            "dur": 200.0,
            "name": "cudnn_generated_fort_native_sdpa_sm90_flash_fprop_wgmma_f16",
            "args": {"hlo_op": "custom-call.3"},
        },
        {"ph": "X", "pid": 1, "tid": 5, "dur": 100.0, "name": "loop_fusion", "args": {"hlo_op": "fusion.9"}},
        {"ph": "X", "pid": 1, "tid": 5, "dur": 50.0, "name": "input_reduce_fusion", "args": {"hlo_op": "fusion.2"}},
        {"ph": "X", "pid": 1, "tid": 7, "dur": 5000.0, "name": "dot.1"},  # a derived line: not counted
        {"ph": "X", "pid": 2, "tid": 1, "dur": 9000.0, "name": "PjitFunction(step)"},
    ]
    with gzip.open(run / "perfetto_trace.json.gz", "wt") as f:
        json.dump({"traceEvents": events}, f)
    got = trace_costs(tmp_path, steps=2)
    assert got["device_ms_per_step"] == pytest.approx(0.475)
    assert [(t["op"], t["ms_per_step"], t["events"], t["category"]) for t in got["top"]] == [
        ("dot.1", 0.3, 2, "matmul"),
        ("custom-call.3", 0.1, 1, "attention"),
        ("fusion.9", 0.05, 1, "other (fusions, elementwise)"),
    ]
    assert got["top"][0]["share"] == pytest.approx(600 / 950, abs=1e-4)
    assert json.loads((tmp_path / "top_costs.json").read_text())["top"] == got["top"]
    with pytest.raises(ValueError, match="log_dir"):
        trace_costs(tmp_path / "none")
