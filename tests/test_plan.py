"""The memory planner (``jaxdrive plan``): the state's bytes against the arrays a real run makes,
per-device bytes falling with the mesh, bad inputs, and the command's JSON."""

import dataclasses
import json
from pathlib import Path

import jax
import numpy as np
import pytest

from jaxdrive.cli import main as cli
from jaxdrive.config import MeshConfig, load_config
from jaxdrive.train.plan import parse_bytes, parse_mesh, plan_memory

TINY = str(Path(__file__).resolve().parents[1] / "configs" / "tiny.py")
# the tiny config made smaller still for fast compiles (one layer, no final convolutions, two views,
# conditions off but the condition frames), with a batch of 8 (fsdp up to 8) and 8 frames of 8 x 8
# tokens (seq up to 8 divides both)
SMALLER = [
    "model.depth=1",
    "model.final_conv=0",
    "data.views=2",
    "data.batch_size=8",
    "data.frames=8",
    "data.height=32",
    "data.width=64",
    "model.controls.text=none",
    "model.controls.fps=false",
    "model.controls.camera=false",
    "model.controls.waypoints=false",
    "model.controls.reference_frame=none",
]


@pytest.fixture(scope="module")
def config():
    return load_config(TINY, SMALLER)


def nbytes(tree) -> int:
    return sum(x.nbytes for x in jax.tree_util.tree_leaves(tree))


def test_state_bytes_equal_a_real_runs_arrays(config):
    """On one device the planned parameters, optimizer state and EMA are the bytes of the arrays
    a run initialises (AdamW: two moments per parameter plus scalar counters; EMA = parameters)."""
    from jaxdrive.train.run import Run

    plan = plan_memory(config, {"data": 1}, compile_step=False)
    pd = plan["per_device"]
    one = dataclasses.replace(config, mesh=MeshConfig(data=1))
    state, _, _ = Run(one, devices=jax.devices()[:1]).init_state()
    params = nbytes(state.params)
    assert pd["params"] == params > 0
    assert pd["ema"] == params
    assert pd["opt_state"] == nbytes(state.opt_state)
    assert 2 * params <= pd["opt_state"] <= 2 * params + 64
    assert pd["replicated"] == pd["params"] + pd["opt_state"] + pd["ema"]  # one device: nothing split
    video = 8 * 2 * 8 * 32 * 64 * 3 * 4  # float32 clips [A=1, b=8, V, F, H, W, 3]
    assert video <= pd["batch"] < 1.1 * video
    assert pd["temp"] is None and plan["fits"] is None


def test_fsdp_divides_the_sharded_state(config):
    """fsdp = 1, 2, 4, 8: parameters, optimizer state and EMA that the rules split (``embed`` on
    ``fsdp``) take 1/N per device (within 15%); what stays whole is the same on every mesh (the
    caption encoder, biases, ...); the batch splits N ways too."""
    plans = {n: plan_memory(config, {"fsdp": n}, compile_step=False)["per_device"] for n in (1, 2, 4, 8)}
    state = lambda pd: pd["params"] + pd["opt_state"] + pd["ema"]
    whole = plans[2]["replicated"]
    assert 0 < whole < 0.5 * state(plans[1])
    for n in (2, 4, 8):
        assert plans[n]["replicated"] == whole
        split = state(plans[n]) - whole
        assert abs(split - (state(plans[1]) - whole) / n) <= 0.15 * (state(plans[1]) - whole) / n, n
        assert plans[n]["batch"] * n == pytest.approx(plans[1]["batch"], rel=0.01)


@pytest.mark.slow(seconds=37)
def test_seq_divides_the_activations(config):
    """seq = 1, 2, 4, 8 (compiled): the step's temporaries are a part that seq splits (the DiT's
    activations: its tokens are split) plus a part it does not (the latents, noise and loss terms
    outside the DiT, whole on every device of a seq group: the batch is split over data and fsdp
    only). Fitted as ``temp(N) = whole + split / N`` over N = 2, 4, 8, every N is within 15% of
    it and the split part is most of the temporaries; one device, a program without resharding,
    holds at least ``whole + split``. The state is not split by seq."""
    plans = {n: plan_memory(config, {"seq": n})["per_device"] for n in (1, 2, 4, 8)}
    ns = np.array([2.0, 4.0, 8.0])
    temps = np.array([plans[int(n)]["temp"] for n in ns], float)
    (whole, split), *_ = np.linalg.lstsq(np.stack([np.ones_like(ns), 1 / ns], 1), temps, rcond=None)
    assert split > 2 * whole > 0, (whole, split)
    for n, t in zip(ns, temps):
        assert abs((t - whole) - split / n) <= 0.15 * split / n, (n, t, whole, split)
    assert plans[1]["temp"] >= whole + split
    assert all(plans[n]["params"] == plans[1]["params"] for n in plans)


@pytest.mark.parametrize(
    "text,match",
    [
        ("80GiB", None),
        ("16GB", None),
        ("512MiB", None),
        ("1.5gib", None),
        ("1024", None),
        ("80GiX", "device_memory: expected a positive size"),
        ("-1GB", "device_memory"),
        ("0", "device_memory"),
        ("GB", "device_memory"),
        ("", "device_memory"),
    ],
)
def test_parse_bytes(text, match):
    if match is None:
        assert (
            parse_bytes(text)
            == {
                "80GiB": 80 * 2**30,
                "16GB": 16 * 10**9,
                "512MiB": 512 * 2**20,
                "1.5gib": int(1.5 * 2**30),
                "1024": 1024,
            }[text]
        )
    else:
        with pytest.raises(ValueError, match=match):
            parse_bytes(text)


@pytest.mark.parametrize(
    "spec,devices,match",
    [
        ("data=2,fsdp=2,seq=2,tensor=1", None, None),
        ("fsdp=-1,seq=2", 8, None),
        ("pipe=2", None, "mesh: .*'pipe"),
        ("fsdp=0", None, "mesh: .*fsdp"),
        ("fsdp=-1", None, "mesh"),
        ("fsdp=two", None, "mesh"),
        ("fsdp=2,seq=2", 8, r"^mesh: expected axis sizes whose product is the device count 8.*product 4"),
        ("fsdp=3,seq=-1", 8, "^mesh"),
    ],
)
def test_parse_mesh(spec, devices, match):
    if match is None:
        sizes = parse_mesh(spec, devices)
        assert set(sizes) == {"data", "fsdp", "seq", "tensor"} and np.prod(list(sizes.values())) == 8
    else:
        with pytest.raises(ValueError, match=match):
            parse_mesh(spec, devices)


def test_plan_refuses_more_devices_than_there_are(config):
    with pytest.raises(ValueError, match="mesh: expected at most 8 devices"):
        plan_memory(config, {"fsdp": 16}, compile_step=False)
    with pytest.raises(ValueError, match="device_memory: expected a positive number of bytes"):
        plan_memory(config, {"fsdp": 2}, device_memory=0, compile_step=False)


def test_cli_prints_the_plan_as_json(capsys):
    sets = [a for s in SMALLER for a in ("--set", s)]
    # the program of the seq = 2 plan above: XLA's cache has it
    assert (
        cli(["plan", "--config", TINY, "--mesh", "seq=2", "--device-memory", "1GiB", "--no-fit", "--json", *sets]) == 0
    )
    out = json.loads(capsys.readouterr().out)
    assert out["mesh"] == {"data": 1, "fsdp": 1, "seq": 2, "tensor": 1} and out["devices"] == 2
    pd = out["per_device"]
    for k in ("params", "opt_state", "ema", "frozen", "batch", "temp", "total"):
        assert isinstance(pd[k], int), k
    assert pd["total"] >= pd["temp"] > 0 and out["fits"] == (pd["total"] <= 2**30)
    assert out["bucket"] == "32x64x8" and out["batch"] == 8


@pytest.mark.parametrize(
    "args,match",
    [
        (["--mesh", "fsdp=2,pipe=2"], "--mesh"),
        (["--mesh", "fsdp=2", "--device-memory", "lots"], "--device-memory"),
        (["--mesh", "fsdp=2", "--devices", "8"], "--mesh: expected axis sizes whose product is the device count 8"),
        (["--mesh", "fsdp=2", "--scales", "0,1"], "--scales"),
        (["--mesh", "fsdp=2", "--scales", "nan"], "--scales"),
    ],
)
def test_cli_bad_input_is_exit_code_2(args, match, capsys):
    assert cli(["plan", "--config", TINY, *args]) == 2
    assert match in capsys.readouterr().err


def test_largest_fit_searches_frames_at_each_resolution(config, monkeypatch):
    """The search (doubling, then bisecting the clip length) on a stand-in plan whose total is
    frames x height x width bytes: at 32 x 64, 20 frames fit 20 x 32 x 64 bytes; at half the
    resolution four times as many; a budget below the shortest clip fits none."""
    import jaxdrive.train.plan as plan

    def total(probe, sizes, devices=None, codec=None):
        d = probe.data
        return {"per_device": {"total": d.frames * d.height * d.width}, "exhausted": None}

    monkeypatch.setattr(plan, "plan_memory", total)
    fit = plan.largest_fit(config, {"fsdp": 2}, 20 * 32 * 64, scales=(1.0, 0.5))
    rows = {(r["height"], r["width"]): r for r in fit["resolutions"]}
    assert rows[32, 64]["frames"] == 20 and rows[16, 32]["frames"] == 80
    assert rows[32, 64]["total"] == 20 * 32 * 64 and not rows[32, 64]["capped"]
    big = fit["largest"]  # the most pixels x frames (here both: the budget is their product)
    assert big in fit["resolutions"] and big["frames"] * big["height"] * big["width"] == 20 * 32 * 64
    assert fit["bucket_batch"] == 8
    assert plan.largest_fit(config, {"fsdp": 2}, 100, scales=(1.0,))["resolutions"][0]["frames"] is None
    with pytest.raises(ValueError, match="scales: expected positive"):
        plan.largest_fit(config, {"fsdp": 2}, 100, scales=(0.0,))
    with pytest.raises(ValueError, match="device_memory: expected a positive number of bytes, got 0"):
        plan.largest_fit(config, {"fsdp": 2}, 0)


def test_largest_fit_of_a_distillation_searches_whole_segments(monkeypatch):
    """A distillation clip is n (K - 1) + 1 frames: the search steps in whole segments (it once
    probed the given frames' length, which the config refuses, and found nothing)."""
    import jaxdrive.train.plan as plan

    config = load_config(str(Path(TINY).parent / "longdwm.py") + ":size=tiny,role=distill")
    step = config.flow.distill_segment_len - 1
    probed = []

    def total(probe, sizes, devices=None, codec=None):
        d = probe.data
        probed.append(d.frames)
        assert (d.frames - 1) % step == 0, d.frames
        return {"per_device": {"total": d.frames * d.height * d.width}, "exhausted": None}

    monkeypatch.setattr(plan, "plan_memory", total)
    h, w = config.data.height, config.data.width
    fit = plan.largest_fit(config, {"fsdp": 1}, (3 * step + 1) * h * w, devices=jax.devices()[:1])
    row = fit["resolutions"][0]
    assert row["frames"] == 3 * step + 1 and row["total"] == (3 * step + 1) * h * w
    assert all((f - 1) % step == 0 for f in probed) and config.data.frames in probed
    assert row["refused"] is None

    def refuse_short(probe, sizes, devices=None, codec=None):  # as a seq axis that does not divide the tokens
        if probe.data.frames < config.data.frames:
            raise ValueError("Sharding spec ('seq',) does not evenly divide the dimension size 226")
        return {"per_device": None, "exhausted": "RESOURCE_EXHAUSTED: out of HBM"}

    monkeypatch.setattr(plan, "plan_memory", refuse_short)
    row = plan.largest_fit(config, {"fsdp": 1}, 1 << 40, devices=jax.devices()[:1])["resolutions"][0]
    assert row["frames"] is None and "does not evenly divide the dimension size 226" in row["refused"]


def test_later_stages_plan_without_their_earlier_runs():
    """A plan reads no weights: STAGE stage 2 needs no stage-1 directory, and LongDWM's
    distillation, with no fine run to read, plans its frozen teacher as its own model's
    parameters (the fine and coarse models are one transformer)."""
    root = Path(TINY).parent
    stage2 = plan_memory(load_config(str(root / "stage.py") + ":size=tiny,stage=2"), {"data": 1}, compile_step=False)
    assert stage2["per_device"]["params"] > 0
    with pytest.raises(ValueError, match="train.init_from"):  # a training run still asks for it
        from jaxdrive.train.run import Run

        Run(load_config(str(root / "stage.py") + ":size=tiny,stage=2"), devices=jax.devices()[:1], check_data=True)
    distill = load_config(str(root / "longdwm.py") + ":size=tiny,role=distill")
    fine = load_config(str(root / "longdwm.py") + ":size=tiny,role=fine")
    pd = plan_memory(distill, {"data": 1}, compile_step=False)["per_device"]
    no_teacher = plan_memory(fine, {"data": 1}, compile_step=False)["per_device"]
    assert pd["frozen"] - no_teacher["frozen"] == pd["params"]  # the teacher: one more copy of the weights


def test_seq_split_names_a_seq_axis_that_leaves_the_tokens_whole(config):
    """The plan says how ``seq`` splits a frame's tokens: 4 x 8 tokens a view's frame (8 frames, 2 views:
    512 a clip) divide over seq=8; at 24 x 56 pixels (3 x 7 tokens) they do not, and the plan lists the
    sizes that would (the divisors of 21); no seq axis, no entry."""
    split = plan_memory(config, {"seq": 8}, compile_step=False)["seq_split"]
    assert split == {
        "seq": 8,
        "frame_tokens": 32,
        "clip_tokens": 512,
        "divides": True,
        "dividing": [2, 4, 8, 16, 32],
    }
    narrow = dataclasses.replace(config, data=dataclasses.replace(config.data, height=24, width=56))
    plan = plan_memory(narrow, {"seq": 8}, compile_step=False)
    split = plan["seq_split"]
    assert (split["frame_tokens"], split["divides"], split["dividing"]) == (21, False, [3, 7, 21])
    from jaxdrive.cli.plan import table

    assert "seq=8 does not divide the 21 tokens of a frame (a clip: 336)" in table({**plan, "config": "tiny"})
    assert "seq sizes that divide them: 3, 7, 21" in table({**plan, "config": "tiny"})
    assert plan_memory(config, {"fsdp": 8}, compile_step=False)["seq_split"] is None
