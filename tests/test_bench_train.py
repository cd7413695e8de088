"""The train-step benchmark: its JSON figures (one compile of the tiny comparison model against
diffusers' PyTorch step) and its analytic FLOPs against hand-counted ones."""

import json

import flax.linen as nn
import pytest

from jaxdrive.bench import train as bench
from jaxdrive.convert.diffusers_dit import config_from_diffusers
from jaxdrive.models.dit import DiT
from jaxdrive.models.dit_presets import preset


def _rows(out):
    return [json.loads(line) for line in out.splitlines() if line.startswith("{")]


def test_train_benchmark_prints_tokens_per_s_and_the_torch_ratio(capsys):
    pytest.importorskip("torch")
    pytest.importorskip("diffusers")
    from jaxdrive.cli import main
    main(["bench", "train", "--presets", "tiny", "--compare-only", "--repeats", "1", "--frames", "2",
          "--height", "4", "--width", "4", "--no-ops"])
    rows = _rows(capsys.readouterr().out)
    assert all(r["bench"] == "train" for r in rows)
    tps = {r["impl"]: r["value"] for r in rows if r["figure"] == "tokens_per_s"}
    assert tps["jaxdrive"] > 0 and tps["torch"] > 0
    params = {r["impl"]: r["value"] for r in rows if r["figure"] == "params"}
    assert params["jaxdrive"] == params["torch"] > 0
    ratio = next(r for r in rows if r["figure"] == "torch_ratio")
    assert ratio["value"] == pytest.approx(tps["jaxdrive"] / tps["torch"], rel=1e-2)
    mfu = next(r for r in rows if r["figure"] == "mfu")
    assert mfu["value"] is None and "--peak-tflops" in mfu["reason"]         # a CPU has no known peak
    flops = next(r for r in rows if r["figure"] == "model_flops_per_step")
    assert flops["value"] > 0 and next(r for r in rows if r["figure"] == "compile_time")["value"] > 0


def test_json_rows_hold_the_step_and_single_op_comparisons(capsys):
    pytest.importorskip("torch")
    pytest.importorskip("diffusers")
    from jaxdrive.cli import main
    main(["bench", "train", "--presets", "tiny", "--compare-only", "--repeats", "1", "--frames", "2",
          "--height", "4", "--width", "4", "--json"])
    lines = [line for line in capsys.readouterr().out.splitlines() if line.strip()]
    rows = [json.loads(line) for line in lines]                   # every line is one JSON object
    steps = {r["impl"]: r for r in rows if r["model"] == "tiny-full/diffusers"}
    assert set(steps) == {"jaxdrive", "torch"}
    for r in steps.values():
        assert {"model", "impl", "step_ms", "tokens_per_s", "ratio_to_torch"} <= set(r) and r["step_ms"] > 0
    assert steps["jaxdrive"]["ratio_to_torch"] == pytest.approx(
        steps["jaxdrive"]["tokens_per_s"] / steps["torch"]["tokens_per_s"], rel=2e-2)
    ops = [r for r in rows if r["model"].startswith("op: ")]
    names = {r["model"] for r in ops}
    assert any(n.startswith("op: matmul ") for n in names) and any("softmax" in n for n in names)
    assert len(ops) == 2 * len(names)                            # each op in both implementations
    for name in names:
        pair = {r["impl"]: r for r in ops if r["model"] == name}
        assert pair["jaxdrive"]["ratio_to_torch"] == pytest.approx(
            pair["torch"]["step_ms"] / pair["jaxdrive"]["step_ms"], rel=2e-2)
    matmul = next(r for r in ops if r["model"].startswith("op: matmul ") and r["impl"] == "jaxdrive")
    assert matmul["gflops"] > 0


def _flops(cfg, **shapes):
    params = nn.unbox(DiT(cfg).abstract_params(views=1, frames=shapes["frames"]))
    return bench.step_flops(cfg, params, views=1, **shapes)


def test_full_layout_flops_are_6_params_tokens_plus_attention():
    dcfg = bench.diffusers_config(preset("tiny-full"), frames=3, height=4, width=6)
    cfg = config_from_diffusers(dcfg)
    f = _flops(cfg, batch=2, frames=3, height=4, width=6)
    d, depth, seq = cfg.width, cfg.depth, 3 * 2 * 3 + cfg.text_len            # [text; video] per clip
    assert f["video_tokens"] == 2 * 18 and f["text_tokens"] == 2 * cfg.text_len
    assert f["matmul_flops"] == 6 * depth * 12 * d * d * 2 * seq               # qkv + out 4 D^2, MLP 8 D^2
    assert f["attention_flops"] == 3 * depth * 4 * seq ** 2 * d * 2
    assert f["flops"] == f["matmul_flops"] + f["attention_flops"]


def test_one_layer_flops_are_the_hand_count():
    """depth 1, width 64 (4 heads x 16), text 8, batch 2, 3 x 4 x 6 latents in 2 x 2 patches: 18
    video + 8 text = 26 tokens a clip. Matmuls: 12 * 64^2 weights (q, k, v, out 4 D^2; MLP 8 D^2),
    6 FLOPs per weight and token (forward 2, backward 4): 6 * 49152 * 26 * 2 = 15,335,424.
    Attention: QK^T and AV, 4 * 26^2 * 64 forward, x 3 with the backward, x 2 clips: 1,038,336."""
    dcfg = bench.diffusers_config(preset("tiny-full").replace(depth=1), frames=3, height=4, width=6)
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
    assert f["attention_flops"] == 3 * depth * 4 * d * (nf * s ** 2 + s * nf ** 2 + 2 * n * txt)


def test_peak_is_known_for_accelerators_and_given_on_cpu():
    class Dev:
        platform, device_kind = "tpu", "TPU v5 lite"
    assert bench.peak_tflops(Dev(), None) == (197.0, "dense bf16 peak of 'TPU v5 lite'")
    Dev.platform, Dev.device_kind = "cpu", "cpu"
    assert bench.peak_tflops(Dev(), None)[0] is None
    assert bench.peak_tflops(Dev(), 1.5) == (1.5, "--peak-tflops")


def test_accelerator_settings_reach_the_model_and_the_measured_peak_gives_an_mfu(capsys, monkeypatch):
    seen, step = [], bench.jax_step
    monkeypatch.setattr(bench, "jax_step", lambda cfg, *a, **k: seen.append(cfg) or step(cfg, *a, **k))
    rows = bench.main(["--presets", "tiny", "--no-torch", "--dtype", "bfloat16", "--remat", "full",
                       "--scan-layers", "--attn-impl", "blockwise", "--measure-peak", "64", "--json",
                       "--repeats", "1", "--frames", "2", "--height", "4", "--width", "4"])
    assert [(c.dtype, c.remat, c.scan_layers, c.attn_impl) for c in seen] == [("bfloat16", "full", True, "blockwise")]
    (row,) = rows
    assert row["model"] == "tiny" and row["measured_peak_tflops"] > 0
    assert row["mfu_measured"] == pytest.approx(row["tflops"] / row["measured_peak_tflops"], rel=2e-2)
    printed = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.strip()]
    assert [r["model"] for r in printed] == ["tiny"]


def test_arguments_are_checked():
    with pytest.raises(SystemExit):
        bench.main(["--presets", "tiny", "--dtype", "bfloat16"])               # torch compares float32
    with pytest.raises(SystemExit):
        bench.main(["--no-torch", "--compare-only"])
    with pytest.raises(SystemExit):
        bench.main(["--repeats", "0"])
