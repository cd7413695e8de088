"""Reading diffusers model folders: ``config.json`` and safetensors weights (never pickle).

A folder holds ``<stem>.safetensors`` or a sharded ``<stem>.safetensors.index.json`` with the
files it names. Pickle formats (``.bin``, ``.pt``, ``.ckpt``, ``.pth``) are refused: unpickling
runs arbitrary code. Every problem raises ``ValueError`` naming the file.
"""

from __future__ import annotations

import json
import pathlib

import jax
import numpy as np

PICKLE_SUFFIXES = (".bin", ".pt", ".pth", ".ckpt", ".pkl")


def read_config(folder, name: str = "config.json") -> dict:
    """The JSON config of a diffusers model folder."""
    path = pathlib.Path(folder) / name
    if not path.is_file():
        raise ValueError(f"{path}: expected a diffusers config file, but it does not exist")
    try:
        config = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: expected a JSON config, got a file that does not parse ({e})") from None
    if not isinstance(config, dict):
        raise ValueError(f"{path}: expected a JSON object, got {type(config).__name__}")
    return config


def _weight_files(folder: pathlib.Path, stem: str) -> list[pathlib.Path]:
    single = folder / f"{stem}.safetensors"
    index = folder / f"{stem}.safetensors.index.json"
    if single.is_file():
        return [single]
    if index.is_file():
        try:
            weight_map = json.loads(index.read_text())["weight_map"]
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as e:
            raise ValueError(f"{index}: expected a safetensors index with a 'weight_map', got an unreadable "
                             f"file ({e!r})") from None
        files = sorted({folder / name for name in weight_map.values()})
        for f in files:
            if not f.is_file():
                raise ValueError(f"{f}: named by {index.name} but missing")
        return files
    pickles = sorted(p.name for p in folder.glob(f"{stem}*") if p.suffix in PICKLE_SUFFIXES)
    if pickles:
        raise ValueError(f"{folder}: expected {single.name} (safetensors), found only pickle weights "
                         f"{pickles}; jaxdrive never unpickles (it can run code): convert them to safetensors")
    raise ValueError(f"{single}: expected safetensors weights (or {index.name}), but neither exists")


def read_safetensors(folder, stem: str = "diffusion_pytorch_model") -> dict[str, np.ndarray]:
    """All tensors of a model folder as float32 NumPy arrays, by name (bf16/fp16 upcast)."""
    from safetensors import SafetensorError, safe_open

    out: dict[str, np.ndarray] = {}
    for path in _weight_files(pathlib.Path(folder), stem):
        try:
            # the flax framework reads bfloat16 (NumPy cannot); keep the arrays on the host
            with jax.default_device(jax.devices("cpu")[0]), safe_open(str(path), framework="flax") as f:
                for key in f.keys():
                    out[key] = np.asarray(f.get_tensor(key), np.float32)
        except (SafetensorError, OSError, ValueError, TypeError) as e:
            raise ValueError(f"{path}: expected a readable safetensors file, got an error ({e})") from None
    return out
