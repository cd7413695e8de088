"""Cloud TPU slices as compile-only devices: a TPU program compiled on any host, no TPU needed.

``topology_devices("v5p-64")`` returns the 32 chips of a v5p-64 slice as JAX devices that XLA:TPU
compiles for (``jax.experimental.topologies.get_topology_desc``, through libtpu: the ``tpu``
extra, ``pip install -e ".[tpu]"``). Nothing runs on them: ``jit(f).lower(...).compile()`` gives
the TPU's buffer assignment (``memory_analysis()``) and cost model (``cost_analysis()``), which is
what ``jaxdrive plan --topology`` and ``jaxdrive bench train --topology`` read.

Names are Cloud TPU accelerator types, as ``gcloud compute tpus`` and MaxText's
``accelerator_to_spec_map`` spell them: the number after a v5e or v6e counts chips, after a v5p or
v4 TensorCores (two a chip, one JAX device a chip: megacore). ``slices`` > 1 is a multi-slice job
(the devices carry ``slice_index``; :func:`jaxdrive.parallel.mesh.make_hybrid_mesh` puts the
``data`` axis across them, over the data-centre network).
"""

from __future__ import annotations

import functools
import importlib.util
import os
from dataclasses import dataclass

from jaxdrive.validate import check_positive_int


@dataclass(frozen=True)
class Topology:
    """One Cloud TPU slice type."""

    name: str  # accelerator type, e.g. "v5p-64"
    generation: str  # "v4", "v5e", "v5p", "v6e"
    shape: str  # chip grid, e.g. "2x4x4"
    chips: int
    chip_memory: int  # HBM bytes per chip (the peak FLOP/s are jaxdrive.bench.flops's, by device kind)

    @property
    def jax_name(self) -> str:
        """The name ``get_topology_desc`` takes (``"v5p:2x4x4"``)."""
        return f"{self.generation}:{self.shape}"


GiB = 1 << 30
# generation -> (HBM per chip, TensorCores per chip in the name's count)
_CHIPS = {"v5e": (16 * GiB, 1), "v6e": (32 * GiB, 1), "v5p": (95 * GiB, 2), "v4": (32 * GiB, 2)}
_SHAPES = {
    # 2-D tori (chips): v5e and v6e
    "v5e": ("1x1", "2x2", "2x4", "4x4", "4x8", "8x8", "8x16", "16x16"),
    "v6e": ("1x1", "2x2", "2x4", "4x4", "4x8", "8x8", "8x16", "16x16"),
    # 3-D tori (chips): v5p and v4
    "v5p": ("2x2x1", "2x2x2", "2x2x4", "2x4x4", "4x4x4", "4x4x8", "4x8x8", "8x8x8", "8x8x16", "8x16x16"),
    "v4": ("2x2x1", "2x2x2", "2x2x4", "2x4x4", "4x4x4", "4x4x8", "4x8x8", "8x8x8", "8x8x16", "8x16x16"),
}


def _table() -> dict[str, Topology]:
    out = {}
    for gen, shapes in _SHAPES.items():
        memory, cores = _CHIPS[gen]
        for shape in shapes:
            chips = 1
            for n in shape.split("x"):
                chips *= int(n)
            name = f"{gen}-{chips * cores}"
            out[name] = Topology(name, gen, shape, chips, memory)
    return out


TOPOLOGIES: dict[str, Topology] = _table()


def topology(name: str) -> Topology:
    """The :class:`Topology` named ``name`` (e.g. ``"v5e-256"``); ValueError listing the known names."""
    if name not in TOPOLOGIES:
        raise ValueError(f"topology: expected one of {', '.join(TOPOLOGIES)}, got {name!r}")
    return TOPOLOGIES[name]


@functools.cache
def _devices(jax_name: str, generation: str, slices: int) -> tuple:
    os.environ.setdefault("TPU_SKIP_MDS_QUERY", "1")  # no metadata server off a TPU VM: don't wait for one
    # compile-only devices claim no chip: several processes (test workers, a planner beside a
    # training job) may load libtpu at once, which its lockfile /tmp/libtpu_lockfile forbids otherwise
    os.environ.setdefault("ALLOW_MULTIPLE_LIBTPU_LOAD", "1")
    if importlib.util.find_spec("libtpu") is None:  # the compiler; get_topology_desc fails obscurely without it
        raise ValueError('topology: compiling for a TPU needs libtpu: pip install -e ".[tpu]" (the libtpu of this jax)')
    from jax.experimental import topologies

    kwargs = {"chip_config_name": "megacore"} if generation == "v4" else {}  # v4: one device a chip, as on a VM
    if jax_name.endswith(":1x1"):  # one chip: less than a host's default 2x2x1, which must divide the grid
        kwargs["chips_per_host_bounds"] = (1, 1, 1)
    if slices > 1:
        kwargs["num_slices"] = slices
    return tuple(topologies.get_topology_desc(topology_name=jax_name, platform="tpu", **kwargs).devices)


def topology_devices(name: str, slices: int = 1) -> list:
    """The compile-only devices of ``slices`` slices of ``name`` (chips x slices of them)."""
    top = topology(name)
    check_positive_int("slices", slices)
    return list(_devices(top.jax_name, top.generation, int(slices)))


def device_memory(devices) -> int | None:
    """HBM bytes per chip of ``devices`` when they are TPUs of a known generation, else None."""
    kinds = {"TPU v5 lite": "v5e", "TPU v6 lite": "v6e", "TPU v5": "v5p", "TPU v5p": "v5p", "TPU v4": "v4"}
    first = next(iter(devices), None)
    gen = None if first is None else kinds.get(str(getattr(first, "device_kind", "")))
    return None if gen is None else _CHIPS[gen][0]
