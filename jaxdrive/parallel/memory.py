"""Device memory: what a compiled program holds on one device, and the budget a caller plans
against before anything runs (``jaxdrive sample --device-memory``).

The budget is per device. Given, it is taken as it is; otherwise on a GPU/TPU it is what the
device reports free (``memory_stats()``: ``bytes_limit - bytes_in_use``, the smallest over the
process's devices) plus what the caller says it already holds there and counts again (the
params a program takes as arguments). A CPU reports nothing: its budget is
:data:`CPU_HOST_FRACTION` of the host's memory shared among its devices, and it is not a hard
limit (``strict`` False): a caller that can split its work finely should, on a CPU, since a CPU
runs a batched call about as fast as its members one by one (``jaxdrive bench longvideo``).
"""

from __future__ import annotations

import os
import re

import jax

CPU_HOST_FRACTION = 0.25
_UNITS = {"": 1, "B": 1, "KB": 10**3, "MB": 10**6, "GB": 10**9, "TB": 10**12,
          "KIB": 2**10, "MIB": 2**20, "GIB": 2**30, "TIB": 2**40}


def footprint_bytes(compiled) -> int | None:
    """Everything a compiled program holds on one device while it runs: its arguments, outputs and
    temporary memory, less the outputs that alias (donated) arguments (``memory_analysis()``), or
    None where the backend has no analysis."""
    a = compiled.memory_analysis()
    if a is None:
        return None
    return int(a.argument_size_in_bytes + a.output_size_in_bytes + a.temp_size_in_bytes
               - a.alias_size_in_bytes)


def parse_bytes(text, name: str = "--device-memory") -> int:
    """``"16GiB"``, ``"512MiB"``, ``"8e9"``, ``8000000000`` -> bytes (a positive int);
    ``ValueError`` naming ``name`` otherwise."""
    if isinstance(text, bool):
        raise ValueError(f"{name}: expected a byte count like 16GiB or 512MiB, got {text!r}")
    if isinstance(text, (int, float)):
        value = float(text)
    else:
        m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:[eE][0-9]+)?)\s*([A-Za-z]*)\s*", str(text))
        unit = m.group(2).upper() if m else None
        if m is None or unit not in _UNITS:
            raise ValueError(f"{name}: expected a byte count like 16GiB, 512MiB or 8e9, got {text!r}")
        value = float(m.group(1)) * _UNITS[unit]
    if not value >= 1:
        raise ValueError(f"{name}: expected at least 1 byte, got {text!r}")
    return int(value)


def host_memory_bytes() -> int:
    """The host's physical memory (``sysconf``)."""
    return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))


def device_budget(device_memory=None, *, counted_bytes: int = 0) -> tuple[int, str, bool]:
    """The per-device bytes a program may hold, where the figure came from (module docstring),
    and whether it is a hard limit: ``device_memory`` when given (bytes or a string for
    :func:`parse_bytes`), else the devices' free memory plus ``counted_bytes`` (already on the
    device and counted in the program's footprint), else the CPU share of the host (not a
    hard limit: swap, not an out-of-memory error, lies beyond it)."""
    if device_memory is not None:
        return parse_bytes(device_memory), "--device-memory", True
    devices = jax.local_devices()
    stats = [d.memory_stats() for d in devices if d.platform != "cpu"]
    stats = [s for s in stats if s and "bytes_limit" in s]
    if stats:
        free = min(int(s["bytes_limit"]) - int(s.get("bytes_in_use", 0)) for s in stats)
        return free + int(counted_bytes), "free device memory", True
    share = int(host_memory_bytes() * CPU_HOST_FRACTION / max(len(devices), 1))
    return share, f"CPU: {CPU_HOST_FRACTION:g} of host memory over {len(devices)} devices", False
