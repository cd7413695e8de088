"""Starting a run from another model's parameters (``train.init_from``): the staged recipes.

Every staged recipe of the papers starts this way: MiLA stages 1-3 and STAGE stages 1-3 each from
the previous stage's run, MagicDrive-V2's video stages from its image stage (temporal blocks
added), LongDWM's coarse model from CogVideoX's weights.

    params, report = init_from(new_params, "runs/stage1", ema=True, name_map=(r"^blocks_(\\d+)=layers_\\1",))

The source is a jaxdrive run directory (its ``config.json`` and newest readable checkpoint; the
EMA parameters by default, the raw ones with ``ema=False``) or a diffusers
``CogVideoXTransformer3DModel`` folder (:func:`jaxdrive.convert.load_diffusers_transformer`).
Parameters are matched by their path (``"layers_0/attn/to_q/kernel"``): a path of the new model
that the source has takes the source's value, placed with the new parameter's sharding; one the
source lacks keeps the new run's initialisation (a module added in a later stage); a shape that
differs is a ``ValueError`` naming the parameter and both shapes. Layers are matched one by one
across scanned runs (``layers_0_13``: layers 0 .. 12 stacked) and unrolled layers (``layers_13``),
so a stage may split or join the source's runs (STAGE's stage 2 adds an HTFT layer inside a run).
``name_map`` renames source paths first: ``"regex=replacement"`` entries (``re.sub``, applied in
order), for layouts that moved. The source is read into the target of ``jax.eval_shape`` with the
new mesh's shardings, never into a freshly initialised copy.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import jax
import numpy as np
from flax.traverse_util import flatten_dict, unflatten_dict

from jaxdrive.train.common import CONFIG_FILE, abstract_train_state, load_run_config

DIFFUSERS_WEIGHTS = ("diffusion_pytorch_model.safetensors", "diffusion_pytorch_model.safetensors.index.json")


@dataclasses.dataclass(frozen=True)
class InitReport:
    """What :func:`init_from` did: parameters loaded, kept at their initialisation (the source has
    none of that name), and source parameters left unused (the new model has none of that name)."""

    source: str
    loaded: tuple[str, ...]
    kept: tuple[str, ...]
    unused: tuple[str, ...]

    def summary(self) -> str:
        kept = f"; kept the new initialisation of {len(self.kept)} (e.g. {list(self.kept[:3])})" if self.kept else ""
        unused = f"; {len(self.unused)} source parameters unused (e.g. {list(self.unused[:3])})" if self.unused else ""
        return f"init_from {self.source}: loaded {len(self.loaded)} parameters{kept}{unused}"


def parse_name_map(name_map) -> list[tuple[re.Pattern, str]]:
    """``"regex=replacement"`` entries -> compiled pairs; ``ValueError`` naming a bad entry."""
    out = []
    for entry in name_map or ():
        if "=" not in entry:
            raise ValueError(f"train.init_map: expected 'regex=replacement' entries, got {entry!r}")
        pattern, repl = entry.split("=", 1)
        try:
            out.append((re.compile(pattern), repl))
        except re.error as e:
            raise ValueError(f"train.init_map: expected a regular expression before '=', got {pattern!r} ({e})") from e
    return out


def _rename(path: str, rules) -> str:
    for rx, repl in rules:
        path = rx.sub(repl, path)
    return path


def source_params(path, *, mesh, ema: bool = True, target_model=None) -> dict:
    """The parameters of the source at ``path`` (a run directory or a diffusers transformer
    folder) as a nested dict: a run's are restored onto ``mesh`` (sharded as its own model would
    be), a diffusers folder's are float32 NumPy arrays."""
    p = Path(path)
    if any((p / name).is_file() for name in DIFFUSERS_WEIGHTS):
        from jaxdrive.convert import load_diffusers_transformer

        overrides = {} if target_model is None else {"scan_layers": target_model.scan_layers}
        return load_diffusers_transformer(p, **overrides)[1]
    from jaxdrive.train.checkpoint import Checkpoints

    if not (p / CONFIG_FILE).is_file():
        raise ValueError(
            f"train.init_from: expected a jaxdrive run directory (with {CONFIG_FILE}) or a diffusers "
            f"transformer folder (with {DIFFUSERS_WEIGHTS[0]}), got {str(path)!r}"
        )
    src = load_run_config(p)
    abstract, _ = abstract_train_state(src.model, src.optim, src.train.steps, mesh, seed=src.train.seed)
    ckpts = Checkpoints(p, keep=src.train.keep_checkpoints, asynchronous=False, option="train.init_from")
    try:
        restored = ckpts.restore_latest_weights(abstract, ema=ema)
    finally:
        ckpts.close()
    if restored is None:
        raise ValueError(f"train.init_from: expected checkpoints under {p / 'checkpoints'}, found none")
    return restored[1]


# a scanned run of layers ``start .. end - 1`` (``nn.scan``, params stacked on a leading axis):
# "layers_13_28/attn/to_q/kernel"; one layer of an unrolled stack or a scanned one: "layers_13/..."
_RUN = re.compile(r"^(?P<prefix>[A-Za-z]\w*?)_(?P<start>\d+)_(?P<end>\d+)(?P<rest>/.*)$")
_LAYER = re.compile(r"^(?P<prefix>[A-Za-z]\w*?)_(?P<index>\d+)(?P<rest>/.*)$")


def _layer_pieces(src_flat) -> dict:
    """``{"layers_i/rest": (run name, i - start)}`` for every layer of the source's scanned runs."""
    pieces = {}
    for name, value in src_flat.items():
        m = _RUN.match(name)
        if m is None:
            continue
        start, end = int(m["start"]), int(m["end"])
        if np.ndim(value) == 0 or np.shape(value)[0] != end - start:
            continue
        for i in range(start, end):
            pieces[f"{m['prefix']}_{i}{m['rest']}"] = (name, i - start)
    return pieces


def _source_value(name, src_flat, pieces):
    """``(value, source names read)`` of the new parameter ``name``: the source's of that name, else
    assembled layer by layer, so a stack of layers moves between scanned runs of other bounds and
    unrolled layers (STAGE stage 2 adds an HTFT layer, which splits a scanned run in two);
    ``(None, ())`` where the source lacks a layer of it."""
    if name in src_flat:
        return src_flat[name], (name,)

    def layer(key):
        if key in src_flat:
            return src_flat[key], key
        if key in pieces:
            run, i = pieces[key]
            return src_flat[run][i], run
        return None, None

    m = _RUN.match(name)
    if m is None:
        value, src = layer(name) if _LAYER.match(name) else (None, None)
        return (value, (src,)) if value is not None else (None, ())
    got = [layer(f"{m['prefix']}_{i}{m['rest']}") for i in range(int(m["start"]), int(m["end"]))]
    if any(v is None for v, _ in got):
        return None, ()
    values = [v for v, _ in got]
    stack = np.stack if all(isinstance(v, np.ndarray) for v in values) else jax.numpy.stack
    return stack(values), tuple(src for _, src in got)


def merge_params(new_params, source, *, name_map=(), source_name: str = "source"):
    """``(params, report)``: ``new_params`` (a nested dict of arrays) with every parameter the
    ``source`` (nested dict) has under the same path, after ``name_map``, replaced by the
    source's value on the new parameter's sharding (see the module docstring)."""
    rules = parse_name_map(name_map)
    new_flat = flatten_dict(new_params, sep="/")
    src_flat = {}
    for k, v in flatten_dict(source, sep="/").items():
        name = _rename(k, rules)
        if name in src_flat:
            raise ValueError(
                f"train.init_map: expected distinct parameter names after renaming, got two source "
                f"parameters named {name!r}"
            )
        src_flat[name] = v
    pieces = _layer_pieces(src_flat)
    out, loaded, kept, used = {}, [], [], set()
    for name, leaf in new_flat.items():
        value, names = _source_value(name, src_flat, pieces)
        if value is None:
            out[name] = leaf
            kept.append(name)
            continue
        used.update(names)
        if tuple(np.shape(value)) != tuple(leaf.shape):
            raise ValueError(
                f"train.init_from: parameter {name!r}: expected shape {list(leaf.shape)} (the new "
                f"model), got {list(np.shape(value))} in {source_name}"
            )
        sharding = getattr(leaf, "sharding", None)
        value = np.asarray(value, leaf.dtype) if isinstance(value, np.ndarray) else value.astype(leaf.dtype)
        out[name] = jax.device_put(value, sharding) if sharding is not None else jax.numpy.asarray(value)
        loaded.append(name)
    unused = sorted(set(src_flat) - used)
    if not loaded:
        raise ValueError(
            f"train.init_from: expected parameters of the new model in {source_name}, found none of "
            f"its {len(new_flat)} names (e.g. {sorted(new_flat)[:3]}; the source has e.g. "
            f"{sorted(src_flat)[:3]}); rename them with train.init_map"
        )
    report = InitReport(source_name, tuple(loaded), tuple(kept), tuple(unused))
    return unflatten_dict(out, sep="/"), report


def init_from(new_params, path, *, mesh, ema: bool = True, name_map=(), target_model=None):
    """``(params, report)``: :func:`merge_params` of ``new_params`` with the parameters of the
    run directory or diffusers folder ``path`` (:func:`source_params`)."""
    with jax.set_mesh(mesh):
        source = source_params(path, mesh=mesh, ema=ema, target_model=target_model)
        return merge_params(new_params, source, name_map=name_map, source_name=str(path))
