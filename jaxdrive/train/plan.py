"""Will it fit? Per-device memory of a config's train step on a mesh, with nothing allocated.

    plan = plan_memory(config, {"fsdp": 4, "seq": 2})        # needs 8 devices (fake CPU ones do)
    plan["per_device"]["total"]                              # bytes one device holds during a step
    fit = largest_fit(config, {"fsdp": 4, "seq": 2}, parse_bytes("80GiB"))

How: :meth:`Run.abstract_state` gives the train state as ``jax.ShapeDtypeStruct`` leaves with
their shardings (``jax.eval_shape``: no parameter exists), so parameters, optimizer state and
EMA are counted per device from each leaf's shard shape. The batch is the abstract global batch of
the config's bucket with the most tokens, built by :func:`~jaxdrive.data.batches.model_inputs`
from a pipeline batch of zero-stride NumPy views (the tree the loop feeds, at no memory), sharded
over ``data`` x ``fsdp`` as :meth:`Run.global_batch` shards it. A VAE that encodes in the step is
the one ``latents.vae_path`` describes (only its ``model.json`` is read) or, where that path holds
none, CogVideoX-2B's (:class:`~jaxdrive.models.vae.model.VAEConfig`'s defaults), its parameters shapes
only. The jitted train step (:meth:`Run.step_fn`) is lowered on these shapes and compiled, and
``compiled.memory_analysis()`` gives its arguments, outputs (less those aliasing the donated
state) and temporaries: activations kept for the backward pass and scratch. ``total`` is what
stays on a device (state, frozen parameters, batch: :func:`resident_bytes`) plus what the step
adds (:func:`transient_bytes`); a VAE the step does not read (stored latents) is no argument of
the compiled program, but it is on the device all the same.

The attention is the one an accelerator runs (:func:`accelerator_attention`). The figures are
XLA:CPU's buffer assignment for the mesh's devices. An accelerator's compiler
fuses and schedules differently, and XLA:CPU computes some bfloat16 operations in float32, so the
temporaries are an estimate of the accelerator's (the state, batch and frozen parameters are
exact); docs/results/memory.md compares the estimate with measured runs.

:func:`largest_fit`: for each resolution (the planned bucket's, scaled by ``scales`` with its
aspect ratio, rounded to the latent patch grid) the longest clip ``1 + temporal k`` frames whose
planned total fits ``device_memory``: doubling ``k`` from the config's clip, then bisecting (one
compile per probe; memory grows with the tokens, so the search assumes it is monotonic in ``k``).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time

import jax
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from jaxdrive.parallel.memory import parse_bytes  # the planner's sizes (also jaxdrive plan's, bench train's)
from jaxdrive.parallel.mesh import MESH_AXES, batch_axes, parse_mesh_spec
from jaxdrive.train.program import f32_dots, program_ops
from jaxdrive.validate import check_positive_int

logger = logging.getLogger(__name__)

STATE_PARTS = ("params", "opt_state", "ema")


def parse_mesh(spec, devices: int | None = None, name: str = "mesh") -> dict[str, int]:
    """``"data=2,fsdp=2,seq=2"`` (or a dict) -> sizes of all four mesh axes. ``-1`` (the rest)
    only with ``devices``; with ``devices`` the product must equal it. ``ValueError`` naming ``name``."""
    try:
        sizes = parse_mesh_spec(spec) if isinstance(spec, str) else dict(spec)
    except (ValueError, TypeError) as e:
        raise ValueError(f"{name}: {e}") from None
    for axis, n in sizes.items():
        if axis not in MESH_AXES:
            raise ValueError(f"{name}: expected axes from {list(MESH_AXES)}, got {axis!r}")
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or (n < 1 and not (n == -1 and devices)):
            raise ValueError(
                f"{name}: expected {axis} to be a positive integer{' or -1' if devices else ''}, got {n!r}"
            )
    sizes = {a: int(sizes.get(a, 1)) for a in MESH_AXES}
    known = math.prod(n for n in sizes.values() if n != -1)
    rest = [a for a, n in sizes.items() if n == -1]
    if len(rest) > 1:
        raise ValueError(f"{name}: expected at most one axis of size -1, got {rest}")
    if rest:
        if devices % known:
            raise ValueError(
                f"{name}: expected the other axes' product {known} to divide {devices} devices, got {spec!r}"
            )
        sizes[rest[0]] = devices // known
    elif devices is not None and known != devices:
        raise ValueError(
            f"{name}: expected axis sizes whose product is the device count {devices}, got {spec!r} (product {known})"
        )
    return sizes


def device_bytes(tree) -> int:
    """Bytes one device holds of the ``jax.ShapeDtypeStruct`` / ``jax.Array`` leaves of ``tree``
    (each leaf's shard shape under its sharding; a leaf without one counts whole)."""
    total = 0
    for x in jax.tree_util.tree_leaves(tree):
        sharding = getattr(x, "sharding", None)
        shape = sharding.shard_shape(x.shape) if sharding is not None else x.shape
        total += math.prod(shape) * np.dtype(x.dtype).itemsize
    return total


def resident_bytes(per_device: dict) -> int:
    """What lives on a device between steps: the state, the frozen parameters and the batch."""
    return sum(per_device[k] for k in (*STATE_PARTS, "state_other", "frozen", "batch"))


def transient_bytes(analysis) -> int:
    """What a compiled step adds while it runs: temporaries and the outputs that do not reuse a
    donated argument's buffer (``memory_analysis()``)."""
    return int(analysis.temp_size_in_bytes + analysis.output_size_in_bytes - analysis.alias_size_in_bytes)


def abstract_codec(latents):
    """The :class:`~jaxdrive.models.latents.LatentCodec` of ``latents`` (a ``LatentConfig``) with a
    VAE's parameters as shapes: the VAE of ``latents.vae_path`` (its ``model.json``) or, where that
    holds none, CogVideoX-2B's. Returns ``(codec, what)``, ``what`` naming the VAE used."""
    from pathlib import Path

    from jaxdrive.models.latents import LatentCodec
    from jaxdrive.models.pretrained import MODEL_FILE, load_pretrained_model
    from jaxdrive.models.vae.model import CausalVAE, VAEConfig

    if latents.source != "vae":
        return LatentCodec.from_config(latents), latents.source
    if (Path(latents.vae_path) / MODEL_FILE).is_file():
        vae = load_pretrained_model(
            latents.vae_path,
            mode=latents.vae_mode,
            frame_wise_batch=latents.vae_frame_batch,
            clip_batch=latents.vae_clip_batch,
        )
        what = latents.vae_path
    else:
        vae = CausalVAE(
            VAEConfig(
                mode=latents.vae_mode, frame_wise_batch=latents.vae_frame_batch, clip_batch=latents.vae_clip_batch
            )
        )
        what = f"CogVideoX-2B ({latents.vae_path!r} has none)"
    params = jax.eval_shape(vae.init, jax.random.PRNGKey(0))
    return LatentCodec("vae", 1, 1.0, vae, params), f"vae {what}"


def _zeros(shape, dtype=np.float32):
    return np.broadcast_to(np.zeros((), dtype), shape)  # a view: no memory at any shape


def pipeline_batch(run, batch: int, height: int, width: int, frames: int) -> dict:
    """A pipeline batch (:func:`jaxdrive.data.transforms.collate`'s fields) of ``batch`` clips whose
    arrays are zero-stride views; the box count and BEV grid are nuScenes' (64 slots, 200 x 200)."""
    from jaxdrive.data.pipeline import CONDITIONS

    d, n_box, bev = run.config.data, 64, (200, 200)
    v, f = d.views, frames
    out = {
        "intrinsics": _zeros((batch, v, 3, 3)),
        "cam_to_ego": _zeros((batch, v, 4, 4)),
        "ego_to_world": _zeros((batch, f, 4, 4)),
        "waypoints": _zeros((batch, f, 2)),
        "fps": _zeros((batch,)),
        "frame_times": _zeros((batch, f)),
        "boxes": _zeros((batch, f, n_box, 7)),
        "box_classes": _zeros((batch, f, n_box), np.int32),
        "box_ids": _zeros((batch, f, n_box), np.int32),
        "box_valid": _zeros((batch, f, n_box), bool),
        "bev_map": _zeros((batch, f, *bev, 8)),
        "caption": ["a driving scene"] * batch,
        "drop": {c: _zeros((batch,), bool) for c in CONDITIONS},
    }
    video = (batch, v, f, height, width, 3)
    if run.config.latents.precomputed:
        sp = run.codec.spatial
        out["latents"] = _zeros((batch, v, run.codec.latent_frames(f), height // sp, width // sp, run.codec.channels))
    else:
        out["video"] = _zeros(video)
    if run.training.model.controls.warp:
        out["warp_video"] = _zeros(video)
    return out


def abstract_batch(run, bucket):
    """The global ``[A, b, ...]`` batch the step takes for ``bucket``, as ``jax.ShapeDtypeStruct``
    leaves sharded like :meth:`Run.global_batch`'s (``b`` over ``data`` x ``fsdp``)."""
    from jaxdrive.data.batches import model_inputs
    from jaxdrive.train.run import check_batch

    _, micro = check_batch(run.config, run.mesh, bucket.batch_size)
    model = run.training.model
    text = run.text
    if model.controls.text == "embeddings" and text is None:  # T5 embeddings: their shape is all that counts
        text = lambda captions: (
            _zeros((len(captions), model.text_len, model.text_dim)),
            _zeros((len(captions), model.text_len), bool),
        )
    inputs = model_inputs(
        pipeline_batch(run, micro, bucket.height, bucket.width, bucket.frames),
        model,
        text,
        foreground=run.training.flow.foreground_k > 0,
        teacher=run.training.teacher,
    )
    sharding = NamedSharding(run.mesh, P(None, batch_axes(run.mesh) or None))
    a = run.config.optim.grad_accum
    return jax.tree_util.tree_map(
        lambda x: jax.ShapeDtypeStruct((a, *np.shape(x)), np.asarray(x).dtype, sharding=sharding), inputs
    )


def abstract_teacher(run):
    """The frozen distillation teacher's parameters as shapes with their shardings (None when
    the run does not distill): what :meth:`Run.frozen_params` restores, at no memory."""
    abstract = run.teacher_abstract_state()
    if abstract is None:
        return None
    return abstract.ema if abstract.ema is not None else abstract.params


def seq_split(run, sizes: dict, bucket) -> dict | None:
    """How the ``seq`` axis splits the planned bucket's video tokens: ``{"seq", "frame_tokens",
    "clip_tokens", "divides", "dividing"}`` (None without a ``seq`` axis). The DiT shards tokens
    over ``seq`` in a frame's layout (``frame_tokens``, one view's patches in a latent frame) and
    in the clip's (``clip_tokens``); a size neither divides leaves them unsharded there
    (:func:`jaxdrive.parallel.rules.spec`'s fallback): every chip of a ``seq`` group then holds
    all of them and the axis saves no memory. ``dividing``: the ``seq`` sizes up to 64 that divide
    ``frame_tokens``."""
    n = sizes.get("seq", 1)
    if n <= 1:
        return None
    m, sp = run.training.model, run.codec.spatial
    frame = (bucket.height // (sp * m.patch[1])) * (bucket.width // (sp * m.patch[2]))
    clip = run.tokens(1, bucket.height, bucket.width, run.codec.latent_frames(bucket.frames))
    return {
        "seq": n,
        "frame_tokens": frame,
        "clip_tokens": clip,
        "divides": frame % n == 0,
        "dividing": [k for k in range(2, 65) if frame % k == 0],
    }


def planned_bucket(run):
    """The bucket whose micro-batch has the most tokens (ties: the first)."""
    return max(
        run.buckets, key=lambda b: run.tokens(b.batch_size, b.height, b.width, run.codec.latent_frames(b.frames))
    )


def accelerator_attention(config, sizes: dict, devices=None):
    """``config`` with the attention an accelerator runs: where ``model.attn_impl`` is "auto" and
    ``seq`` does not split the tokens, "blockwise" (O(L) memory, as the cuDNN / splash kernels that
    "auto" picks on a GPU / TPU), not the dense XLA attention "auto" picks on a CPU for sequences
    under 4096^2 pairs, whose scores ``remat="dots"`` would keep for every layer. On a ``seq`` mesh
    "auto" is the ring kernel everywhere; on accelerator ``devices`` (a TPU topology's) "auto"
    stays: it picks the accelerator's own kernel."""
    platform = "cpu" if not devices else devices[0].platform
    if config.model.attn_impl != "auto" or sizes.get("seq", 1) > 1 or platform != "cpu":
        return config
    return dataclasses.replace(config, model=config.model.replace(attn_impl="blockwise"))


def _with_mesh(config, sizes: dict):
    from jaxdrive.config import MeshConfig

    return dataclasses.replace(config, mesh=MeshConfig(**sizes))


_SIZE = r"([0-9.]+)\s*([KMGT])?"  # the compiler's sizes: "20.51G" (binary units, GiB)


def _bytes(number: str, unit: str | None) -> int:
    return parse_bytes(f"{number}{unit}iB" if unit else number, name="the compiler's size")


def out_of_memory(error) -> dict | None:
    """``{"message", "needs", "temp"}`` when ``error`` is a compiler's RESOURCE_EXHAUSTED (XLA:TPU
    checks that a program fits the chip's HBM when it compiles it): its first line, the bytes it
    says the program uses ("Used X of Y hbm") and those it says its temporaries need ("the total
    memory required for HLO temporaries (X) exceeds available HBM"), None where it says no such
    number; None for any other error."""
    import re

    text = str(error)
    if "RESOURCE_EXHAUSTED" not in text and "Ran out of memory" not in text:
        return None
    line = next((x.strip() for x in text.splitlines() if "memory" in x.lower() or "RESOURCE_EXHAUSTED" in x), text)
    used = re.search(r"Used\s+" + _SIZE + r"\s+of\s+" + _SIZE, text)
    temps = re.search(r"HLO temporaries\s*\(" + _SIZE + r"\)", text)
    return {
        "message": line[:400],
        "needs": None if used is None else _bytes(used.group(1), used.group(2)),
        "temp": None if temps is None else _bytes(temps.group(1), temps.group(2)),
    }


def compile_target(mesh, devices=None, topology: str | None = None, slices: int = 1, device_memory=None):
    """``(mesh sizes, devices, device_memory, target)`` of a compile-only plan: the devices of
    ``topology`` (a Cloud TPU accelerator type, :mod:`jaxdrive.parallel.topology`; ``slices`` of
    it), whose chip memory is the default ``device_memory`` and whose chip count the mesh must
    equal (one axis may be -1), else ``devices`` (default ``jax.devices()``), of which the mesh
    takes the first. ``target`` names them for a report. ValueErrors name the argument."""
    from jaxdrive.parallel.topology import topology as find_topology
    from jaxdrive.parallel.topology import topology_devices

    if device_memory is not None and (
        isinstance(device_memory, bool) or not isinstance(device_memory, (int, np.integer)) or device_memory <= 0
    ):
        raise ValueError(f"device_memory: expected a positive number of bytes, got {device_memory!r}")
    if topology is None:
        if slices != 1:
            raise ValueError(f"slices: expected 1 without a topology, got {slices!r}")
        devices = list(jax.devices() if devices is None else devices)
        sizes = parse_mesh(mesh, None, name="mesh")
        n = math.prod(sizes.values())
        if n > len(devices):
            raise ValueError(
                f"mesh: expected at most {len(devices)} devices (those there are), got {sizes} (product {n})"
            )
        kind = devices[0].platform if devices else "cpu"
        return sizes, devices[:n], device_memory, f"{n} {'fake CPU' if kind == 'cpu' else kind} devices"
    if devices is not None:
        raise ValueError(f"devices: expected None with topology={topology!r} (its devices are the topology's)")
    top = find_topology(topology)  # an unknown name: the ValueError lists the known ones
    check_positive_int("slices", slices)
    chips = top.chips * slices
    try:
        sizes = parse_mesh(mesh, chips, name="mesh")
    except ValueError as e:
        raise ValueError(f"{e}: {topology} x {slices} slice(s) has {chips} chips") from None
    if slices > 1 and sizes["data"] % slices:
        raise ValueError(
            f"slices: expected a mesh whose data axis the {slices} slices split (data runs across slices), "
            f"got data={sizes['data']}"
        )
    devices = topology_devices(topology, slices)
    memory = top.chip_memory if device_memory is None else device_memory
    where = f"{topology}{f' x {slices} slices' if slices > 1 else ''} ({chips} {devices[0].device_kind} chips, XLA:TPU)"
    return sizes, devices, memory, where


def plan_memory(
    config,
    mesh,
    *,
    device_memory: int | None = None,
    devices=None,
    topology: str | None = None,
    slices: int = 1,
    codec=None,
    compile_step: bool = True,
) -> dict:
    """Per-device bytes of ``config``'s train step on ``mesh`` (``{"fsdp": 4, ...}`` or
    ``"fsdp=4,..."``): see the module docstring. The devices are ``topology``'s (a Cloud TPU
    accelerator type such as ``"v5p-64"``, ``slices`` of it: compiled by XLA:TPU on this host,
    libtpu needed; the chip's memory is the default ``device_memory``), else the first of
    ``devices`` (default ``jax.devices()``). Returns ``{"mesh", "devices", "target", "bucket",
    "batch", "tokens", "seq_split" (:func:`seq_split`), "codec", "per_device": {...},
    "compile_seconds", "device_memory", "fits", "exhausted"}``; ``per_device`` holds ``params``,
    ``opt_state``, ``ema``, ``state_other`` (step, key, counters), ``replicated`` (the bytes of the
    first three whose leaves the mesh does not split), ``frozen`` (a VAE's parameters), ``batch``,
    and from the compiled step ``arguments``, ``outputs``, ``aliased``, ``temp`` and ``total`` (None
    with ``compile_step=False``, which compiles nothing); ``program`` counts what the compiled step
    holds (:func:`jaxdrive.train.program.program_ops`, and ``f32_dots``: its matmuls with a float32
    operand). A compile that the TPU compiler stops for want of memory is no error: ``fits`` is
    False, ``exhausted`` the compiler's line and ``total`` the bytes it says it needs."""
    from jaxdrive.train.run import Run

    sizes, devices, device_memory, target = compile_target(mesh, devices, topology, slices, device_memory)
    n = len(devices)
    what = None
    if codec is None:
        codec, what = abstract_codec(config.latents)
    config = accelerator_attention(config, sizes, devices)
    run = Run(_with_mesh(config, sizes), devices=devices, codec=codec, check_data=False)
    state, optimizer = run.abstract_state()
    shardings = jax.tree_util.tree_map(lambda x: x.sharding, state)
    bucket = planned_bucket(run)
    batch = abstract_batch(run, bucket)
    replicated = NamedSharding(run.mesh, P())
    frozen = {
        "codec": jax.tree_util.tree_map(
            lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=replicated), codec.params
        ),
        "teacher": abstract_teacher(run),
    }
    parts = {k: device_bytes(getattr(state, k)) for k in STATE_PARTS}
    whole = [
        x for k in STATE_PARTS for x in jax.tree_util.tree_leaves(getattr(state, k)) if x.sharding.is_fully_replicated
    ]
    per_device = {
        **parts,
        "state_other": device_bytes(state) - sum(parts.values()),
        "replicated": device_bytes(whole),
        "frozen": device_bytes(frozen),
        "batch": device_bytes(batch),
        **dict.fromkeys(("arguments", "outputs", "aliased", "temp", "total")),
    }
    seconds, exhausted, program = None, None, None
    if compile_step:
        t = time.perf_counter()
        try:
            with jax.set_mesh(run.mesh):
                compiled = run.step_fn(optimizer, shardings).lower(state, frozen, batch).compile()
        except jax.errors.JaxRuntimeError as e:
            exhausted = out_of_memory(e)
            if exhausted is None:
                raise
        seconds = round(time.perf_counter() - t, 1)
        if exhausted is None:
            text = compiled.as_text()
            program = {**program_ops(text), "f32_dots": f32_dots(text)}
            a = compiled.memory_analysis()
            per_device.update(
                arguments=int(a.argument_size_in_bytes),
                outputs=int(a.output_size_in_bytes),
                aliased=int(a.alias_size_in_bytes),
                temp=int(a.temp_size_in_bytes),
            )
            per_device["total"] = resident_bytes(per_device) + transient_bytes(a)
        elif exhausted["temp"] is not None:  # what stays resident is known without the program
            per_device["temp"] = exhausted["temp"]
            per_device["total"] = resident_bytes(per_device) + exhausted["temp"]
        else:
            per_device["total"] = exhausted["needs"]
    fits = None
    if exhausted is not None:
        fits = False  # the compiler knows the chip's memory: out of it means no fit, whatever device_memory says
    elif device_memory is not None and compile_step:
        fits = per_device["total"] <= device_memory
    return {
        "mesh": sizes,
        "devices": n,
        "target": target,
        "bucket": "x".join(map(str, bucket.key)),
        "batch": bucket.batch_size,
        "tokens": run.tokens(bucket.batch_size, bucket.height, bucket.width, run.codec.latent_frames(bucket.frames)),
        "seq_split": seq_split(run, sizes, bucket),
        "codec": what or codec.source,
        "per_device": per_device,
        "compile_seconds": seconds,
        "device_memory": device_memory,
        "fits": fits,
        "exhausted": None if exhausted is None else exhausted["message"],
        "program": program,
    }


def largest_fit(
    config,
    mesh,
    device_memory: int | None = None,
    *,
    scales=(1.0,),
    devices=None,
    topology: str | None = None,
    slices: int = 1,
    max_doublings: int = 6,
) -> dict:
    """The longest clip at each resolution that fits ``device_memory`` bytes per device (module
    docstring; ``devices``, ``topology`` and ``slices`` as in :func:`plan_memory`, a topology's
    chip memory the default ``device_memory``). Returns ``{"device_memory", "resolutions":
    [{"height", "width", "frames", "total", "probes"}, ...], "largest": the entry with the most
    tokens}``; ``frames`` is None where not even
    the shortest clip fits. Each probe's total is logged at DEBUG."""
    from jaxdrive.train.run import Run

    sizes, devices, device_memory, _ = compile_target(mesh, devices, topology, slices, device_memory)
    if device_memory is None:
        raise ValueError("device_memory: expected a positive number of bytes (or a topology), got None")
    if not scales or any(not (isinstance(s, (int, float)) and math.isfinite(s) and s > 0) for s in scales):
        raise ValueError(f"scales: expected positive resolution scales, got {scales!r}")
    codec, _ = abstract_codec(config.latents)
    run = Run(_with_mesh(config, sizes), devices=devices, codec=codec, check_data=False)
    bucket, temporal = planned_bucket(run), max(codec.temporal, 1)
    m = run.training.model
    gh, gw = codec.spatial * m.patch[1], codec.spatial * m.patch[2]
    # clip lengths searched in steps of q latent frames: a distillation clip is n dense segments
    # (n (K - 1) + 1 frames, frame-wise latents), any other clip any latent length
    q = run.config.flow.distill_segment_len - 1 if run.config.flow.distill_teacher else 1
    k0 = (bucket.frames - 1) // temporal // q
    k_min = max(1, -(-run.config.flow.cond_frames // (temporal * q)))  # a clip longer than its given frames
    rows = []
    for s in scales:
        h, w = max(gh, round(bucket.height * s / gh) * gh), max(gw, round(bucket.width * s / gw) * gw)
        totals: dict[int, int | None] = {}
        refused: dict[int, str] = {}  # a probe the config or the sharding rules out, and why

        def total(k):
            if k not in totals:
                probe = dataclasses.replace(
                    config,
                    data=dataclasses.replace(
                        config.data,
                        buckets=(),
                        height=h,
                        width=w,
                        frames=1 + temporal * q * k,
                        batch_size=bucket.batch_size,
                    ),
                )
                try:
                    plan = plan_memory(probe, sizes, devices=devices, codec=codec)
                    totals[k] = None if plan["exhausted"] else plan["per_device"]["total"]  # out of HBM: no fit
                except ValueError as e:  # a clip length the config or the mesh rules out
                    totals[k] = None
                    refused[k] = str(e).splitlines()[0][:300]
                logger.debug("  %dx%dx%d: %s", h, w, 1 + temporal * q * k, totals[k])
            return totals[k]

        fits = lambda k: total(k) is not None and total(k) <= device_memory
        lo, hi = None, None  # largest k known to fit, smallest known not to
        k = max(k0, k_min)
        if fits(k):
            lo = k
            for _ in range(max_doublings):
                k = 2 * k
                if not fits(k):
                    hi = k
                    break
                lo = k
        else:
            hi = k
            lo = k_min if k_min < hi and fits(k_min) else None
        while lo is not None and hi is not None and hi - lo > 1:
            mid = (lo + hi) // 2
            lo, hi = (mid, hi) if fits(mid) else (lo, mid)
        rows.append(
            {
                "height": h,
                "width": w,
                "frames": None if lo is None else 1 + temporal * q * lo,
                "total": None if lo is None else totals[lo],
                "probes": len(totals),
                "capped": lo is not None and hi is None,
                # why the shortest clip tried has no total, when it was refused rather than too big
                "refused": None if lo is not None else refused.get(min(totals)),
            }
        )
    found = [r for r in rows if r["frames"]]
    largest = max(found, key=lambda r: r["height"] * r["width"] * r["frames"]) if found else None
    return {"device_memory": device_memory, "bucket_batch": bucket.batch_size, "resolutions": rows, "largest": largest}
