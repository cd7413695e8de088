"""Reading the evaluation networks' weights files (torch state dicts or safetensors copies) into JAX
parameters: one home for the loader and for folding a convolution's batch norm."""

from __future__ import annotations

from pathlib import Path

import jax.numpy as jnp
import numpy as np


def read_state_dict(path, *, option: str = "path") -> dict:
    """The tensors of a ``.pth`` state dict (torch's ``weights_only`` loader) or a ``.safetensors``
    file, as NumPy arrays; an unreadable file is a ``ValueError`` naming ``option``."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{option}: expected a weights file, got {str(path)!r} (not found)")
    if path.suffix == ".safetensors":
        from jaxdrive.convert.safetensors_io import read_tensors

        try:
            return read_tensors(path)
        except ValueError as e:
            raise ValueError(f"{option}: {e}") from None
    try:
        import torch
    except ImportError:
        raise ValueError(
            f"{option}: reading {path.name} needs torch; convert it once with 'jaxdrive convert "
            f"{option.lstrip('-')} --from {path} --out WEIGHTS.safetensors'"
        ) from None
    try:
        state = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises several types for a truncated or foreign file
        raise ValueError(
            f"{option}: could not read {path} as a state dict ({type(e).__name__}: {str(e)[:200]})"
        ) from None
    if not isinstance(state, dict):
        raise ValueError(f"{option}: expected a state dict in {path}, got {type(state).__name__}")
    return {k: v.detach().cpu().numpy() for k, v in state.items() if hasattr(v, "detach")}


def conv_batch_norm(
    state: dict, conv: str, bn: str | None, shape: tuple, eps: float, *, source: str, what: str, bias: bool = False
) -> dict:
    """One convolution of a torch state dict as ``{"kernel": [..spatial, in, out], "scale",
    "shift"}``: ``conv.weight`` of ``shape`` (out, in, ..spatial) transposed, and the batch norm
    ``bn`` (eval mode) folded in, ``y = conv(x) * scale + shift`` (no ``bn``: scale 1, shift the
    conv's ``bias``). A missing or misshapen tensor is a ``ValueError`` naming ``source`` and the
    tensor (``what`` formats the missing one: ``{key!r}``)."""
    want = {f"{conv}.weight": tuple(shape)}
    if bn is not None:
        want.update({f"{bn}.{k}": (shape[0],) for k in ("weight", "bias", "running_mean", "running_var")})
    if bias:
        want[f"{conv}.bias"] = (shape[0],)
    for key, size in want.items():
        if key not in state:
            raise ValueError(f"{source}: expected {what.format(key=key)}, got a file without it ({len(state)} tensors)")
        if tuple(np.shape(state[key])) != size:
            raise ValueError(f"{source}: tensor {key!r}: expected shape {list(size)}, got {list(np.shape(state[key]))}")
    g = lambda k: np.asarray(state[k], np.float64)
    kernel = np.moveaxis(g(f"{conv}.weight"), (0, 1), (-1, -2))
    if bn is None:
        scale = np.ones(shape[0])
        shift = g(f"{conv}.bias") if bias else np.zeros(shape[0])
    else:
        scale = g(f"{bn}.weight") / np.sqrt(g(f"{bn}.running_var") + eps)
        shift = g(f"{bn}.bias") - g(f"{bn}.running_mean") * scale
    return {
        "kernel": jnp.asarray(kernel, jnp.float32),
        "scale": jnp.asarray(scale, jnp.float32),
        "shift": jnp.asarray(shift, jnp.float32),
    }
