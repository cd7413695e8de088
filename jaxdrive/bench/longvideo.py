"""Long video: seconds, sequential sampler calls and peak device memory of each strategy, side by
side, for several lengths, on the tiny recipe's models (``configs/tiny.py``, random weights: the
figures are about cost, not quality). Each figure is the second of two runs (compiling is left out).

    python -m jaxdrive.bench.longvideo [--frames 33 145 721] [--steps 10] [--views 6] [--strategies streaming ...]

Also the ratio of ``coarse-fine``'s time for 145 frames to the time of one window (LongDWM
reports 145 frames in 70 s where Vista needs 95 s for 25) and to ``rollout``'s time for the same
frames. On a CPU a batched call costs about as much as its segments would one by one, so the
sequential calls are the figure that transfers to an accelerator. ``coarse-fine`` runs at its
default, ``segment_batch="auto"`` (the largest group of segments per fine call that fits the
per-device budget, ``--device-memory``; its ``segment_batch`` column), which keeps device memory
flat in the length; ``coarse-fine (all in one)`` stacks every segment in one call, the fewest
sequential calls, its memory growing with the length.
``streaming`` (STAGE) is the tiny model with an HTFT layer, its buffer of 10 frames fusing
-1, -5, -10: one sequential call per frame, so its figure is ``s_per_frame``; ``programs`` is
the number of programs each run compiled (streaming: one, whatever the length).
``--strategies`` keeps only the rows named (``coarse-fine-all`` is the all-in-one row); on an
accelerator the peak memory is the device's peak so far in the process, so a strategy's own figure
wants a process of its own (``--strategies`` one at a time).
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

from jaxdrive.bench.report import emit, quiet, table

NAME = "longvideo"
# each row's --strategies name (the all-in-one coarse-fine row has its own)
KEYS = {
    "rollout": "rollout",
    "coarse-to-refine": "coarse-to-refine",
    "coarse-fine": "coarse-fine",
    "coarse-fine (all in one)": "coarse-fine-all",
    "streaming": "streaming",
}
CONFIG = Path(__file__).resolve().parents[2] / "configs" / "tiny.py"


def _models(config, views: int, steps: int):
    from jaxdrive.generate.windows import WindowModel
    from jaxdrive.models.dit.model import DiT

    d = config.data
    dit = DiT(config.model)
    window = d.frames
    params = jax.tree_util.tree_map(
        jax.numpy.asarray,
        dit.init_params(0, batch=1, views=views, frames=window, height=d.height // 4, width=d.width // 4),
    )
    base = WindowModel(dit, params, window=window, cond_frames=config.flow.cond_frames, steps=steps)
    refine = dataclasses.replace(base, jdc_anchor_rate=0.75)
    from jaxdrive.generate.streaming import WINDOW

    stage = DiT(config.model.replace(htft_layers=(0,)))
    stage_params = jax.tree_util.tree_map(
        jax.numpy.asarray,
        stage.init_params(0, batch=1, views=views, frames=WINDOW, height=d.height // 4, width=d.width // 4),
    )
    stream = WindowModel(
        stage,
        stage_params,
        window=WINDOW,
        cond_frames=1,
        steps=steps,
        streaming=True,
        stream_buffer=10,
        stream_taps=(-1, -5, -10),
    )
    return {
        "main": base,
        "refine": refine,
        "coarse": dataclasses.replace(base, cond_frames=1, stride=window - 1),
        "fine": dataclasses.replace(base, cond_frames=1, patterns=("prefix", "ends")),
        "stream": stream,
    }


def _horizon(config, frames: int, views: int):
    """A synthetic clip of ``frames`` frames as model inputs (the controls of every frame)."""
    from jaxdrive.data.batches import model_inputs
    from jaxdrive.data.pipeline import CONDITIONS
    from jaxdrive.data.synthetic import generate_clip
    from jaxdrive.data.transforms import collate, sample_clip

    d = config.data
    clip = generate_clip(0, views=views, frames=frames, height=d.height, width=d.width)
    batch = collate([sample_clip(clip, size=(d.height, d.width), frames=frames)])
    batch["drop"] = {n: np.zeros((1,), bool) for n in CONDITIONS}
    return model_inputs(batch, config.model)


def run(frames_list, steps: int, views: int, strategies=None, device_memory=None):
    from jaxdrive.config import load_config
    from jaxdrive.generate.long_video import sample_long
    from jaxdrive.generate.strategies import Models
    from jaxdrive.models.latents import LatentCodec

    config = load_config(CONFIG)
    codec = LatentCodec.from_config(config.latents)
    m = _models(config, views, steps)
    cases = [
        ("rollout", Models(m["main"]), {}),
        ("coarse-to-refine", Models(m["refine"]), {}),
        ("coarse-fine", Models(m["coarse"], m["fine"]), {"device_memory": device_memory}),
        ("coarse-fine (all in one)", Models(m["coarse"], m["fine"]), {"segment_batch": 10**9}),
        ("streaming", Models(m["stream"]), {}),
    ]
    keep = lambda label, frames: (
        not strategies or KEYS[label] in strategies or (label == "rollout" and frames == config.data.frames)
    )  # the one window
    rows, seconds = [], {}
    out = Path(tempfile.mkdtemp(prefix="jaxdrive-bench-longvideo-"))
    for frames in [config.data.frames] + list(frames_list):
        inputs = _horizon(config, frames, views)
        first = np.asarray(codec.encode(None, inputs["video"][:, :, : config.flow.cond_frames]))
        for label, models, options in cases:
            name = label.split(" ")[0]
            if (frames == config.data.frames and name != "rollout") or not keep(label, frames):
                continue  # one window: the rollout's single call
            given = 1 if name in ("coarse-fine", "streaming") else config.flow.cond_frames
            # compile outside the figure: a first run of the same length (coarse-fine's batched
            # call has a shape of its own for every length)
            with quiet("jaxdrive.generate.long_video"):
                sample_long(
                    name,
                    models,
                    codec,
                    inputs["cond"],
                    first[:, :, :given],
                    frames,
                    out / "warm",
                    key=jax.random.key(0),
                    **options,
                )
                t = time.perf_counter()
                report = sample_long(
                    name,
                    models,
                    codec,
                    inputs["cond"],
                    first[:, :, :given],
                    frames,
                    out / label,
                    key=jax.random.key(0),
                    **options,
                )
                wall = time.perf_counter() - t
            seconds[(label, frames)] = wall
            row = dict(
                strategy=label,
                frames=frames,
                seconds=round(wall, 2),
                s_per_frame=round(wall / frames, 4),
                sequential_calls=report["sequential_sampler_calls"],
                peak_mib=round(report["peak_device_bytes"] / 2**20, 1),
                programs=report["compiled_programs"],
                segment_batch=report.get("segment_batch", {}).get("segment_batch", ""),
            )
            rows.append(row)
            ctx = dict(strategy=label, frames=frames, views=views, steps=steps, backend=jax.default_backend())
            emit(NAME, "seconds", row["seconds"], "s", **ctx)
            emit(NAME, "sequential_sampler_calls", row["sequential_calls"], "calls", **ctx)
            emit(NAME, "peak_device_memory", row["peak_mib"], "MiB", **ctx)
            emit(NAME, "seconds_per_frame", row["s_per_frame"], "s", **ctx)
            emit(NAME, "compiled_programs", row["programs"], "programs", **ctx)
    print(
        table(
            rows,
            [
                "strategy",
                "frames",
                "seconds",
                "s_per_frame",
                "sequential_calls",
                "peak_mib",
                "programs",
                "segment_batch",
            ],
        )
    )
    window = seconds[("rollout", config.data.frames)]
    if ("coarse-fine", 145) in seconds:
        cf = seconds[("coarse-fine", 145)]
        emit(NAME, "coarse_fine_145_over_one_window", round(cf / window, 2), "x", window_frames=config.data.frames)
        print(f"coarse-fine 145 frames: {cf / window:.1f} x one window ({window:.2f} s)")
        if ("rollout", 145) in seconds:
            emit(NAME, "coarse_fine_145_over_rollout_145", round(cf / seconds[("rollout", 145)], 2), "x")
            print(f"coarse-fine 145 frames: {cf / seconds[('rollout', 145)]:.2f} x rollout's 145 frames")
    peak = {(r["strategy"], r["frames"]): r["peak_mib"] for r in rows}
    if ("coarse-fine", 145) in peak and ("coarse-fine", 721) in peak:
        ratio = peak[("coarse-fine", 721)] / peak[("coarse-fine", 145)]
        emit(NAME, "coarse_fine_peak_721_over_145", round(ratio, 3), "x")
        print(f"coarse-fine at its default: peak device memory of 721 frames = {ratio:.3f} x that of 145")
    for (label, frames), wall in sorted(seconds.items()):
        if label == "coarse-fine (all in one)" and ("coarse-fine", frames) in seconds:
            ratio = seconds[("coarse-fine", frames)] / wall
            emit(NAME, "coarse_fine_default_over_all_in_one", round(ratio, 3), "x", frames=frames)
            print(f"coarse-fine {frames} frames: the default takes {ratio:.2f} x the all-in-one call's time")
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(prog="jaxdrive bench longvideo", description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--frames",
        type=int,
        nargs="+",
        default=[33, 145, 721],
        help="pixel frames (1 + 8n for the tiny coarse-fine models)",
    )
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--views", type=int, default=6)
    parser.add_argument(
        "--device-memory",
        help="coarse-fine's per-device budget of its automatic segment batch "
        "(default: the device's free memory, or a CPU's share)",
    )
    parser.add_argument(
        "--strategies",
        nargs="+",
        choices=list(KEYS.values()),
        help="only these rows (and rollout's one window, the reference)",
    )
    args = parser.parse_args(argv)
    bad = [f for f in args.frames if (f - 1) % 8]
    if bad:
        parser.error(f"--frames: expected 1 + 8n frames (keyframes every 8 frames), got {bad}")
    return run(args.frames, args.steps, args.views, args.strategies, args.device_memory)


if __name__ == "__main__":
    main()
