"""Saved models: a directory with ``model.json`` (the kind and its config) and ``params/`` (an
orbax checkpoint of the float32 parameters).

``save_pretrained(path, model, params)`` writes into a temporary sibling directory and renames it
into place, so a crash never leaves a half-written model at ``path``. ``load_pretrained(path)``
returns ``(model, params)``; a missing or corrupt file raises ``ValueError`` naming it. Restoring
accepts ``shardings`` (a tree of ``jax.sharding.Sharding``, e.g. from
:func:`jaxdrive.parallel.param_shardings`) to place parameters straight onto a mesh.

Model kinds register here by their config class: ``"vae"`` is
:class:`jaxdrive.models.vae.model.CausalVAE`.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import uuid
from pathlib import Path

import jax
import numpy as np

from jaxdrive.atomic import move_into_place

MODEL_FILE = "model.json"
PARAMS_DIR = "params"
FORMAT_VERSION = 1


def _kinds() -> dict:
    from jaxdrive.models.vae.model import CausalVAE, VAEConfig

    return {"vae": (CausalVAE, VAEConfig)}


def _kind_of(model) -> str:
    for kind, (cls, _) in _kinds().items():
        if isinstance(model, cls):
            return kind
    raise ValueError(f"model: expected one of {[c.__name__ for c, _ in _kinds().values()]}, got {type(model).__name__}")


def _config_json(config) -> dict:
    return {
        f.name: list(v) if isinstance(v := getattr(config, f.name), tuple) else v for f in dataclasses.fields(config)
    }


def save_pretrained(path, model, params, *, overwrite: bool = False) -> Path:
    """Write ``model`` (its config) and ``params`` to the directory ``path``, atomically."""
    import orbax.checkpoint as ocp

    path = Path(path).absolute()
    kind = _kind_of(model)
    if path.exists() and not overwrite:
        raise ValueError(f"path: expected a path that does not exist (or overwrite=True), got {str(path)!r}")
    path.parent.mkdir(parents=True, exist_ok=True)
    staging = path.parent / f".{path.name}.tmp-{uuid.uuid4().hex[:8]}"
    try:
        staging.mkdir()
        host = jax.tree_util.tree_map(lambda x: np.asarray(x, np.float32), params)
        checkpointer = ocp.StandardCheckpointer()
        checkpointer.save(staging / PARAMS_DIR, host)
        checkpointer.wait_until_finished()
        meta = {"format": FORMAT_VERSION, "kind": kind, "config": _config_json(model.config)}
        (staging / MODEL_FILE).write_text(json.dumps(meta, indent=2) + "\n")
        move_into_place(staging, path)
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)
    return path


def load_pretrained_model(path, **config_overrides):
    """The model (no parameters) of a directory written by :func:`save_pretrained`: what
    ``model.json`` describes, with ``config_overrides`` applied."""
    path = Path(path).absolute()
    meta_file = path / MODEL_FILE
    if not meta_file.is_file():
        raise ValueError(f"path: expected a saved jaxdrive model with {MODEL_FILE}, got {str(path)!r}")
    try:
        meta = json.loads(meta_file.read_text())
        cls, config_cls = _kinds()[meta["kind"]]
        fields = {f.name for f in dataclasses.fields(config_cls)}
        config = {k: tuple(v) if isinstance(v, list) else v for k, v in meta["config"].items() if k in fields}
    except (json.JSONDecodeError, KeyError, TypeError) as e:
        raise ValueError(f"{meta_file}: not a valid saved-model description ({e!r})") from e
    return cls(config_cls(**{**config, **config_overrides}))


def load_pretrained(path, *, shardings=None, **config_overrides):
    """``(model, params)`` from a directory written by :func:`save_pretrained`.

    ``config_overrides`` change inference settings (e.g. a VAE's ``mode`` or ``tiling``)."""
    import orbax.checkpoint as ocp

    path = Path(path).absolute()
    model = load_pretrained_model(path, **config_overrides)
    abstract = jax.eval_shape(model.init, jax.random.PRNGKey(0))
    if shardings is not None:
        abstract = jax.tree_util.tree_map(
            lambda a, s: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=s), abstract, shardings
        )
    try:
        params = ocp.StandardCheckpointer().restore(path / PARAMS_DIR, abstract)
    except Exception as e:  # orbax raises many types for a damaged directory
        raise ValueError(f"{path / PARAMS_DIR}: cannot restore the parameters ({type(e).__name__}: {e})") from e
    return model, params
