"""Reading diffusers model directories: ``config.json`` plus safetensors weights, never pickle.

A diffusers directory holds ``config.json`` and either ``diffusion_pytorch_model.safetensors`` or
a sharded set indexed by ``diffusion_pytorch_model.safetensors.index.json``. Tensors are read as
NumPy arrays (no PyTorch needed; bfloat16 comes back as ``ml_dtypes.bfloat16``).
A missing, partial or corrupt file raises ``ValueError`` naming the file.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

WEIGHTS = "diffusion_pytorch_model.safetensors"
INDEX = "diffusion_pytorch_model.safetensors.index.json"
PICKLE_SUFFIXES = (".bin", ".pt", ".pth", ".ckpt", ".pkl")  # unpickling runs arbitrary code


def read_config(path, expected_class: str) -> dict:
    """``config.json`` of the diffusers directory ``path``; its ``_class_name`` must be
    ``expected_class``."""
    file = Path(path) / "config.json"
    if not file.is_file():
        raise ValueError(f"path: expected a diffusers directory with config.json, got {str(path)!r} (no {file})")
    try:
        config = json.loads(file.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{file}: not a valid JSON config ({e})") from e
    name = config.get("_class_name")
    if name != expected_class:
        raise ValueError(f"{file}: expected _class_name {expected_class!r}, got {name!r}")
    return config


# safetensors' own words for a file that ends early (a cut download, the common failure): its
# reader checks the header length and that the tensors cover the file before it reads anything.
_TRUNCATED = ("header too small", "invalid header length", "incomplete metadata")


def _read_file(file: Path) -> dict[str, np.ndarray]:
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(file), framework="numpy") as f:
            return {name: f.get_tensor(name) for name in f.keys()}
    except (SafetensorError, OSError, ValueError) as e:
        what = "not a complete" if any(w in str(e) for w in _TRUNCATED) else "corrupt"
        raise ValueError(f"{file}: {what} safetensors file ({file.stat().st_size} bytes; {e})") from e


def read_tensors(file) -> dict[str, np.ndarray]:
    """Every tensor of one ``.safetensors`` file, by name (``ValueError`` for a damaged file)."""
    return _read_file(Path(file))


def read_weights(path) -> dict[str, np.ndarray]:
    """All tensors of the diffusers directory ``path``, by their PyTorch names."""
    root = Path(path)
    single, index = root / WEIGHTS, root / INDEX
    if single.is_file():
        return _read_file(single)
    if index.is_file():
        try:
            files = sorted(set(json.loads(index.read_text())["weight_map"].values()))
        except (json.JSONDecodeError, KeyError, AttributeError) as e:
            raise ValueError(f"{index}: not a valid safetensors index ({e})") from e
        tensors = {}
        for name in files:
            if not (root / name).is_file():
                raise ValueError(f"{index}: names the shard {name}, which is missing from {root}")
            tensors.update(_read_file(root / name))
        return tensors
    pickles = sorted(p.name for p in root.iterdir() if p.suffix in PICKLE_SUFFIXES) if root.is_dir() else []
    hint = (
        f" (found {pickles}: pickled weights are never loaded; re-save with safe_serialization=True)" if pickles else ""
    )
    raise ValueError(f"path: expected {WEIGHTS} or {INDEX} in {str(root)!r}{hint}")


def assemble_params(
    expected, flat: dict[tuple[str, ...], np.ndarray], source, origin: dict[tuple[str, ...], str] | None = None
) -> dict:
    """Nest ``flat`` (parameter path -> array) into the structure of ``expected`` (a params tree
    of arrays or ``ShapeDtypeStruct``), as float32.

    Raises ``ValueError`` naming ``source`` and listing every unknown key (in ``flat``, not in
    ``expected``; shown by its name in the file when ``origin`` maps paths to those names),
    missing key and shape mismatch, so a wrong or partial checkpoint is never half-loaded."""
    import jax

    origin = origin or {}
    want = {
        tuple(getattr(k, "key", str(k)) for k in path): leaf
        for path, leaf in jax.tree_util.tree_flatten_with_path(expected)[0]
    }
    unknown = sorted(origin.get(k, "/".join(k)) for k in flat.keys() - want.keys())
    missing = sorted("/".join(k) for k in want.keys() - flat.keys())
    shapes = sorted(
        f"{'/'.join(k)}: expected {list(want[k].shape)}, got {list(flat[k].shape)}"
        for k in want.keys() & flat.keys()
        if tuple(want[k].shape) != tuple(flat[k].shape)
    )
    if unknown or missing or shapes:
        parts = [
            f"{label} ({len(items)}): {items[:30]}{' ...' if len(items) > 30 else ''}"
            for label, items in (("unknown keys", unknown), ("missing keys", missing), ("shape mismatches", shapes))
            if items
        ]
        raise ValueError(f"{source}: weights do not match the model; " + "; ".join(parts))
    out: dict = {}
    for path, value in flat.items():
        node = out
        for key in path[:-1]:
            node = node.setdefault(key, {})
        node[path[-1]] = np.asarray(value, dtype=np.float32)
    return out
