"""Device memory: what a compiled program holds on one device, and the budget a caller plans
against before anything runs (``jaxdrive sample --device-memory``).

The budget is per device. Given, it is taken as it is; otherwise on a GPU/TPU it is what the
device reports free (``memory_stats()``: ``bytes_limit - bytes_in_use``, the smallest over the
process's devices) plus what the caller says it already holds there and counts again (the
params a program takes as arguments), times :data:`DEVICE_FRACTION` (the allocator's
fragmentation and what the next program, a VAE decode, holds beside it need room). A CPU reports nothing: its budget is
:data:`CPU_HOST_FRACTION` of the host's memory shared among its devices, and it is not a hard
limit (``strict`` False): a caller that can split its work finely should, on a CPU, since a CPU
runs a batched call about as fast as its members one by one (``jaxdrive bench longvideo``).
"""

from __future__ import annotations

import math
import os
import re
import weakref

import jax

CPU_HOST_FRACTION = 0.25
DEVICE_FRACTION = 0.9
UNITS = {
    "": 1,
    "b": 1,
    "kb": 10**3,
    "mb": 10**6,
    "gb": 10**9,
    "tb": 10**12,
    "kib": 2**10,
    "mib": 2**20,
    "gib": 2**30,
    "tib": 2**40,
}


def shard_bytes(x: jax.Array) -> int:
    """Bytes of ``x`` one of its devices holds (its shard), from its sharding: nothing is read.
    Not ``x.addressable_shards[i].data.nbytes``: each shard's ``data`` is a new array that stays
    alive with ``x``, so :func:`live_device_bytes` would count it again, and each count would take
    longer than the last."""
    return math.prod(x.sharding.shard_shape(x.shape)) * x.dtype.itemsize


def live_device_bytes() -> int:
    """Bytes the live arrays of this process hold on its devices, each replica counted: the
    device memory a CPU, which reports none (``memory_stats()``), is using."""
    return int(sum(shard_bytes(x) * len(x.sharding.addressable_devices) for x in jax.live_arrays()))


_ANALYSES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # compiled program -> its analysis


def memory_analysis(compiled):
    """``compiled.memory_analysis()`` (None where the backend has none), read once per program:
    a long sample asks after each of its calls."""
    if compiled not in _ANALYSES:
        _ANALYSES[compiled] = compiled.memory_analysis()
    return _ANALYSES[compiled]


def temp_bytes(compiled) -> int:
    """The temporary memory a compiled program holds on one device while it runs (0 without an
    analysis)."""
    return int(getattr(memory_analysis(compiled), "temp_size_in_bytes", 0) or 0)


def footprint_bytes(compiled) -> int | None:
    """Everything a compiled program holds on one device while it runs: its arguments, outputs and
    temporary memory, less the outputs that alias (donated) arguments (``memory_analysis()``), or
    None where the backend has no analysis."""
    a = memory_analysis(compiled)
    if a is None:
        return None
    return int(a.argument_size_in_bytes + a.output_size_in_bytes + a.temp_size_in_bytes - a.alias_size_in_bytes)


def parse_bytes(text, name: str = "device_memory") -> int:
    """``"80GiB"``, ``"16GB"``, ``"512MiB"``, ``"1e9"`` (or a number of bytes) -> bytes, a positive
    int; ``ValueError`` naming ``name`` otherwise."""
    m = (
        None
        if isinstance(text, bool)
        else re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:e[0-9]+)?)\s*([a-z]*)\s*", str(text), re.IGNORECASE)
    )
    unit = m and m.group(2).lower()
    if not m or unit not in UNITS or float(m.group(1)) * UNITS[unit] < 1:
        raise ValueError(
            f"{name}: expected a positive size like 80GiB, 16GB or 512MiB (units "
            f"{', '.join(u for u in UNITS if u)}), got {text!r}"
        )
    return int(float(m.group(1)) * UNITS[unit])


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
        return parse_bytes(device_memory), "device_memory", True
    devices = jax.local_devices()
    stats = [d.memory_stats() for d in devices if d.platform != "cpu"]
    stats = [s for s in stats if s and "bytes_limit" in s]
    if stats:
        free = min(int(s["bytes_limit"]) - int(s.get("bytes_in_use", 0)) for s in stats)
        return int(DEVICE_FRACTION * (free + int(counted_bytes))), f"{DEVICE_FRACTION:g} of free device memory", True
    share = int(host_memory_bytes() * CPU_HOST_FRACTION / max(len(devices), 1))
    return share, f"CPU: {CPU_HOST_FRACTION:g} of host memory over {len(devices)} devices", False
