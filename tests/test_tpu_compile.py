"""Compiled for a TPU on this CPU host: Cloud TPU topologies as compile-only devices (libtpu, the
``tpu`` extra), the tiny train step through XLA:TPU with splash in ``shard_map`` on a sharded batch
and with ring attention on a ``seq`` mesh, the planner's TPU figures and its bad inputs."""

from pathlib import Path

import pytest

from jaxdrive.cli import main as cli
from jaxdrive.config import load_config
from jaxdrive.parallel.topology import TOPOLOGIES, topology, topology_devices
from jaxdrive.train.plan import out_of_memory, plan_memory
from jaxdrive.train.program import f32_dots, unlisted_f32_dots

TINY = str(Path(__file__).resolve().parents[1] / "configs" / "tiny.py")
GiB = 1 << 30


def test_accelerator_types_map_to_chip_grids_and_memory():
    # Cloud TPU's names: v5e / v6e count chips, v5p / v4 TensorCores (two a chip)
    grid = lambda name: (topology(name).shape, topology(name).chips, topology(name).chip_memory // GiB)
    assert grid("v5p-64") == ("2x4x4", 32, 95) and grid("v5e-256") == ("16x16", 256, 16)
    assert grid("v4-8") == ("2x2x1", 4, 32) and grid("v6e-64") == ("8x8", 64, 32)
    assert topology("v6e-64").jax_name == "v6e:8x8"
    assert {"v5e-4", "v5p-8", "v5p-1024", "v6e-4", "v6e-256", "v4-8"} <= set(TOPOLOGIES)


def test_topology_devices_are_the_slices_chips():
    for name, top in TOPOLOGIES.items():  # every name the planner accepts gives its chips (v5e-1 once did not)
        assert len(topology_devices(name)) == top.chips, name
    devices = topology_devices("v5p-8")
    assert len(devices) == 4 and {d.platform for d in devices} == {"tpu"}
    assert len(topology_devices("v4-8")) == 4  # megacore: one device a chip, as on a v4 VM
    two = topology_devices("v5e-4", slices=2)
    assert len(two) == 8 and sorted({d.slice_index for d in two}) == [0, 1]


def test_a_multislice_mesh_puts_data_across_the_slices():
    from jaxdrive.parallel.mesh import make_mesh

    mesh = make_mesh(data=2, fsdp=4, devices=topology_devices("v5e-4", slices=2))
    grid = mesh.devices  # [data, fsdp, seq, tensor]
    assert {d.slice_index for d in grid[0].flat} == {0} and {d.slice_index for d in grid[1].flat} == {1}
    with pytest.raises(ValueError, match="data: expected a multiple of the 2 TPU slices .* got data=1"):
        make_mesh(fsdp=8, devices=topology_devices("v5e-4", slices=2))


def test_meshes_that_split_a_physical_axis_are_laid_on_the_torus():
    from jaxdrive.parallel.mesh import _physical_grid, make_mesh

    # v6e's 8x8 has no layout with fsdp=32 on whole physical axes: mesh_utils raised
    # NotImplementedError unless told it may split one (jax.make_mesh allows that on v5e only)
    devices = topology_devices("v6e-64")
    for fsdp, seq in [(32, 2), (16, 4), (64, 1)]:
        mesh = make_mesh(fsdp=fsdp, seq=seq, devices=devices)
        assert mesh.devices.shape == (1, fsdp, seq, 1)
        assert sorted(d.id for d in mesh.devices.flat) == sorted(d.id for d in devices)
    grid = make_mesh(fsdp=8, seq=8, devices=devices).devices[0, :, :, 0]
    # whole physical axes where they exist: each seq group is one row of the torus
    assert all(len({d.coords[1] for d in row}) == 1 for row in grid)

    def never(split):
        raise NotImplementedError("Failed to find assignment for logical_axis_index 1")

    with pytest.raises(ValueError, match="mesh: expected axis sizes that can be laid on the devices' physical grid"):
        _physical_grid(never, (1, 64, 1, 1), devices)


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(mesh="fsdp=4", topology="v5q-4"), "topology: expected one of v5e-1, v5e-4, .*got 'v5q-4'"),
        (dict(mesh="fsdp=8", topology="v5e-4"), "mesh: expected axis sizes whose product is the device count 4.*v5e-4"),
        (dict(mesh="fsdp=4", topology="v5e-4", slices=2), "device count 8, got 'fsdp=4' \\(product 4\\)"),
        (
            dict(mesh="fsdp=8", topology="v5e-4", slices=2),
            "data axis the 2 slices.*data=1",
        ),
        (dict(mesh="fsdp=4", topology="v5e-4", slices=0), "slices: expected an integer >= 1, got 0"),
        (dict(mesh="fsdp=2", slices=2), "slices: expected 1 without a topology, got 2"),
    ],
)
def test_bad_targets_name_the_argument_and_both_numbers(kwargs, match):
    config = load_config(TINY)
    mesh = kwargs.pop("mesh")
    with pytest.raises(ValueError, match=match):
        plan_memory(config, mesh, compile_step=False, **kwargs)


def test_without_libtpu_the_command_says_what_to_install(monkeypatch, capsys):
    import importlib.util

    from jaxdrive.parallel import topology as top

    top._devices.cache_clear()
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "libtpu" else real(name, *a))
    assert cli(["plan", "--config", TINY, "--mesh", "fsdp=4", "--topology", "v5e-4", "--no-compile"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and 'pip install -e ".[tpu]"' in err
    top._devices.cache_clear()


def test_the_compilers_out_of_memory_is_a_verdict_with_the_bytes_it_needs():
    error = RuntimeError(
        "RESOURCE_EXHAUSTED: XLA:TPU compile permanent error. Ran out of memory in memory space hbm. "
        "Used 20.51G of 15.48G hbm. Exceeded hbm capacity by 5.03G.\n\nTotal hbm usage >= 21.0G:"
    )
    found = out_of_memory(error)
    assert found["needs"] == int(20.51 * GiB) and found["temp"] is None and "Ran out of memory" in found["message"]
    assert out_of_memory(RuntimeError("INVALID_ARGUMENT: something else")) is None
    # what XLA:TPU printed for stdit3_xl (remat=dots) on v6e-64 at fsdp=64
    temps = out_of_memory(
        RuntimeError(
            "RESOURCE_EXHAUSTED: Ran out of memory on HBM, the total memory required for HLO temporaries "
            "(43.19G) exceeds available HBM (31.25G)."
        )
    )
    assert temps["temp"] == int(43.19 * GiB) and temps["needs"] is None


def test_f32_dots_are_read_from_the_operands_own_lines():
    hlo = """
  %p0 = f32[8,64]{1,0} parameter(0)
  %p1 = bf16[64,64]{1,0} parameter(1)
  %c = bf16[8,64]{1,0} convert(%p0)
  %dot.1 = f32[8,64]{1,0} dot(%c, %p1), lhs_contracting_dims={1}, metadata={op_name="jit(f)/DiT/mlp/fc1/dot_general"}
  %convolution.2 = f32[8,64]{1,0} convolution(%p0, %p1), dim_labels=bf_io->bf, metadata={op_name="jit(f)/loss/dot"}
  ROOT %t = (f32[8,64]{1,0}) tuple(%dot.1)
"""
    found = f32_dots(hlo)
    assert found == [{"op": "convolution", "result": "f32", "operands": ["f32", "bf16"], "path": "jit(f)/loss/dot"}]
    assert unlisted_f32_dots(found, {"loss": "the loss in float32"}) == []
    assert unlisted_f32_dots(found, {}) == found
    assert unlisted_f32_dots(found, {"los": "a prefix of a scope is not the scope"}) == found


def test_allowed_scopes_match_under_jvp_and_transpose_but_not_a_longer_name():
    def dot(path):
        return {"op": "dot", "result": "f32", "operands": ["f32", "f32"], "path": path}

    inside = [dot("jit(step)/jvp(dct_lowpass)/dot_general"), dot("jit(step)/transpose(jvp(geometry))/dot_general")]
    inside.append(dot("jit(step)/Decoder/Encoder3D/conv_in/conv_general_dilated"))
    outside = [dot("jit(step)/DiT/geometry_embed/dot_general"), dot("jit(step)/Encoder3D_old/conv")]
    allowed = {"dct_lowpass": "", "geometry": "", "Encoder3D": ""}
    assert unlisted_f32_dots(inside + outside, allowed) == outside


def test_f32_dots_in_a_lowered_program_and_in_typed_operands():
    import jax
    import jax.numpy as jnp

    def lowered(a_dtype):
        f = jax.jit(lambda a, b: jnp.dot(a, b.astype(a_dtype), preferred_element_type=jnp.float32))
        return f.lower(jnp.ones((4, 4), a_dtype), jnp.ones((4, 4), jnp.bfloat16)).as_text(dialect="hlo")

    assert [d["operands"] for d in f32_dots(lowered(jnp.float32))] == [["f32", "f32"]]
    assert f32_dots(lowered(jnp.bfloat16)) == []  # bf16 operands, f32 accumulation: not an f32 dot
    typed = """
  %a = f32[4,4]{1,0} parameter(0)
  %b = bf16[4,4]{1,0} parameter(1)
  %dot = f32[4,4]{1,0} dot(f32[4,4]{1,0} %a, bf16[4,4]{1,0} %b), lhs_contracting_dims={1}
"""
    assert [d["operands"] for d in f32_dots(typed)] == [["f32", "bf16"]]


@pytest.mark.slow(seconds=60)
def test_tiny_bf16_step_compiles_for_a_v5e_with_splash_in_shard_map_and_no_f32_matmul():
    # the batch over fsdp, the heads over tensor: each chip calls the Mosaic kernel on its own
    # examples and heads (a kernel XLA cannot partition); "auto" picks splash from the mesh's TPUs.
    # In the bf16 step no dot or convolution takes a float32 operand but those the allow-list
    # names (before: 38, the XLA attention's scores and probabilities and their transposes)
    plan = plan_memory(load_config(TINY, ["train.compute_dtype=bfloat16"]), "fsdp=2,tensor=2", topology="v5e-4")
    assert plan["target"].startswith("v5e-4 (4 TPU v5 lite chips")
    assert plan["program"]["mosaic_kernels"] > 0  # forward and backward splash kernels
    assert unlisted_f32_dots(plan["program"]["f32_dots"]) == []
    pd = plan["per_device"]
    assert pd["temp"] > 0 and pd["total"] >= pd["temp"] + pd["params"]
    assert plan["device_memory"] == 16 * GiB and plan["fits"] is True


@pytest.mark.slow(seconds=60)
def test_tiny_step_compiles_for_a_v5e_with_ring_attention_on_a_seq_mesh():
    # the tiny step with one layer, two views and no controls: 18 s of XLA:TPU instead of 47
    smaller = ["model.depth=1", "model.final_conv=0", "data.views=2", "model.controls.text=none"]
    plan = plan_memory(load_config(TINY, smaller), "fsdp=2,seq=2", topology="v5e-4")
    ops = plan["program"]
    assert ops["collective_permutes"] > 0 and ops["mosaic_kernels"] == 0  # K/V travel round the seq ring
    assert plan["per_device"]["total"] > 0 and plan["fits"] is True


def test_extrapolating_two_depths_to_the_model_depth():
    from jaxdrive.bench.roofline import extrapolate

    one, two = {"flops": 10.0, "bytes accessed": 4.0}, {"flops": 16.0, "bytes accessed": 5.0}
    assert extrapolate(one, two, 1) == one and extrapolate(one, two, 2) == two
    assert extrapolate(one, two, 28) == {"flops": 10.0 + 27 * 6.0, "bytes accessed": 4.0 + 27 * 1.0}


def test_roofline_adds_only_the_attentions_that_run_in_splash():
    # XLA counts its own attention's matmuls: adding them again from the model count would count
    # the text cross-attention (by default XLA's, local_attn_impl="xla") twice
    from jaxdrive.bench.roofline import kernel_attention_kinds
    from jaxdrive.models.dit import DiT
    from jaxdrive.models.dit.model import param_trace_shapes
    from jaxdrive.models.dit.presets import preset

    assert kernel_attention_kinds(preset("tiny")) == ("self",)
    assert kernel_attention_kinds(preset("tiny", attn_impl="xla")) == ()
    local = preset("tiny", local_attn_impl="splash", cross_attn_impl=None)
    assert kernel_attention_kinds(local) == ("self", "temporal", "cross")
    # the cross-attention alone (the lever of docs/guides/plan.md: temporal stays on XLA)
    assert kernel_attention_kinds(preset("tiny", cross_attn_impl="splash")) == ("self", "cross")
    assert kernel_attention_kinds(local.replace(cross_attn_impl="xla")) == ("self", "temporal")
    # and a TPU-only local kernel still traces its parameters on this CPU host (it raised here)
    assert DiT(local).abstract_params(**param_trace_shapes(local)) == DiT(preset("tiny")).abstract_params(
        **param_trace_shapes(preset("tiny"))
    )


@pytest.mark.slow(seconds=100)
def test_roofline_counts_every_layer_and_the_attention_kernels():
    # XLA:TPU counts a scanned body once and splash's kernels not at all: the estimate extrapolates
    # two unrolled depths to the model's (here 3, checked against the 3-layer program itself) and
    # adds the attention's FLOPs from the model count
    from jaxdrive.bench.roofline import FLASH_EXECUTED, _abstract_step, compiled_costs, roofline
    from jaxdrive.models.dit.presets import preset
    from jaxdrive.parallel import make_mesh

    cfg = preset("tiny", dtype="bfloat16", depth=3)
    shapes = dict(batch=2, frames=5, height=16, width=16)
    r = roofline(cfg, "v5e-4", **shapes)
    mesh = make_mesh(devices=topology_devices("v5e-4")[:1])
    unrolled = compiled_costs(_abstract_step(cfg.replace(scan_layers=False), mesh, **shapes).compile())
    scanned = compiled_costs(_abstract_step(cfg.replace(scan_layers=True), mesh, **shapes).compile())
    assert r["xla_flops"] == pytest.approx(unrolled["flops"], rel=0.01)
    assert scanned["flops"] < 0.8 * unrolled["flops"]  # what the correction is for
    # the same program with XLA's self-attention: XLA counts its matmuls, 3 x 2 of S_q S_k D a
    # layer as in the model count, where the splash program counted none; the kernels' FLOPs are
    # the self-attention's alone (the temporal and text attention are XLA's in both programs).
    # Within 20%: the splash program's own scaling and padding, the dense one's softmax
    dense = compiled_costs(_abstract_step(cfg.replace(scan_layers=False, attn_impl="xla"), mesh, **shapes).compile())
    model_attention = r["attention_kernel_flops"] / FLASH_EXECUTED
    assert dense["flops"] - unrolled["flops"] == pytest.approx(model_attention, rel=0.2)
    assert r["step_s"] == max(r["compute_s"], r["memory_s"]) > 0
    assert 0 < r["roofline_mfu"] < 1 and r["peak_tflops"] == 197.0


def test_bench_train_topology_rejects_what_it_cannot_do():
    from jaxdrive.bench.train import main as bench_train

    for flags in (["--batch", "auto", "--no-torch"], ["--compare-only"]):
        with pytest.raises(SystemExit):
            bench_train(["--topology", "v5e-4", *flags])
    with pytest.raises(ValueError, match="topology: expected one of .*v5e-4.*, got 'v5x-4'"):
        bench_train(["--topology", "v5x-4", "--presets", "tiny"])


def test_the_samplers_compile_for_one_chip(capsys):
    """sample_window (splash in the denoising loop), the decode and STAGE's streaming frame with
    its HTFT buffer, on one v5e chip, compile only."""
    from jaxdrive.bench.sampler_compile import main

    stage = str(Path(TINY).with_name("stage.py")) + ":size=tiny,stage=3"
    out = main(["--config", stage, "--topology", "v5e-1", "--set", "model.depth=2", "--set", "data.views=2"])
    assert out["device"].startswith("TPU v5") and out["window"]["latent_frames"] == 3
    assert out["sample_window"]["mosaic_kernels"] > 0 and out["sample_window"]["temp_gib"] > 0
    assert out["streaming"]["taps"] == [-1, -5, -10] and out["streaming"]["mosaic_kernels"] > 0
    assert out["vae_decode"]["codec"] == "space_to_depth"
    assert "sample_window:" in capsys.readouterr().out
    with pytest.raises(ValueError, match="topology: expected one of"):
        main(["--config", TINY, "--topology", "v9z-4"])
