"""Multi-process setup and host-local <-> global arrays.

Each process loads only its share of a batch (its "host-local" slice along axis 0).
:func:`host_local_to_global` stitches those slices into one global ``jax.Array`` sharded over the
mesh; :func:`global_to_host_local` is the inverse, for outputs and metrics. With one process both
are plain ``device_put`` / ``np.asarray``.

:func:`initialize_distributed` picks the coordinator from, in order:

1. explicit arguments (``coordinator_address`` given; ``num_processes`` and ``process_id`` then
   required);
2. the environment ``JAXDRIVE_COORDINATOR`` (``host:port``), ``JAXDRIVE_NUM_PROCESSES``,
   ``JAXDRIVE_PROCESS_ID`` (all three);
3. SLURM with ``SLURM_NTASKS > 1``: ``SLURM_PROCID``, first host of ``SLURM_STEP_NODELIST``
   (else ``SLURM_JOB_NODELIST``), port ``JAXDRIVE_COORDINATOR_PORT`` or one derived from
   ``SLURM_JOB_ID`` (in [61440, 65535], as JAX's own SLURM detection does);
4. a multi-host TPU VM (``TPU_WORKER_HOSTNAMES`` lists more than one host, or a multislice job
   sets ``MEGASCALE_COORDINATOR_ADDRESS``): ``jax.distributed.initialize()`` with no arguments,
   which reads the TPU metadata itself;
5. nothing set: a single process; nothing is done.

It returns which of ``"explicit"``, ``"env"``, ``"slurm"``, ``"tpu"``, ``"single"``,
``"already"`` (JAX's distributed client was already up) applied. On GPU nodes running one task per
GPU, pass ``local_device_ids`` (or set ``CUDA_VISIBLE_DEVICES`` per task).
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping, Sequence

import jax
import numpy as np
from jax.sharding import NamedSharding, PartitionSpec

from .rules import ACTIVATION_RULES, Axes, logical_to_spec


def _is_spec_leaf(x) -> bool:
    return isinstance(x, PartitionSpec) or (
        isinstance(x, (tuple, list)) and all(n is None or isinstance(n, str) for n in x)
    )


def _shardings(tree, mesh, spec_or_names, rules):
    """One NamedSharding per leaf: a spec / names for every leaf, or a tree of them."""

    def one(spec):
        if not isinstance(spec, PartitionSpec):
            spec = logical_to_spec(spec, rules, mesh=mesh)
        return NamedSharding(mesh, spec)

    if _is_spec_leaf(spec_or_names):
        s = one(spec_or_names)
        return jax.tree_util.tree_map(lambda _: s, tree)
    specs = jax.tree_util.tree_map(one, spec_or_names, is_leaf=_is_spec_leaf)
    return jax.tree_util.tree_map(lambda _, s: s, tree, specs)


def host_local_to_global(batch_tree, mesh, spec_or_names=("batch",), rules: Mapping[str, Axes] = ACTIVATION_RULES):
    """Global arrays from each process's slice along axis 0 of every leaf.

    ``spec_or_names``: a ``PartitionSpec``, a tuple of logical names (mapped through ``rules``;
    trailing dimensions not named are replicated), or a tree of those matching ``batch_tree``.
    The global leading size is the local one times the number of processes the axis-0 sharding
    spans; every process must pass leaves of the same shape and dtype.
    """
    shardings = _shardings(batch_tree, mesh, spec_or_names, rules)

    def one(x, sharding):
        x = np.asarray(x)
        if x.ndim == 0:
            raise ValueError("batch_tree: expected arrays with a leading batch axis, got a scalar")
        return jax.make_array_from_process_local_data(sharding, x)

    return jax.tree_util.tree_map(one, batch_tree, shardings)


def _local_block(x: jax.Array) -> np.ndarray:
    """This process's shards of ``x`` packed densely (inverse of the process-local mapping)."""
    shards = x.addressable_shards
    if x.is_fully_addressable:
        return np.asarray(x)
    if x.sharding.is_fully_replicated:
        return np.asarray(x.addressable_data(0))
    # Per dimension: the distinct intervals this process holds, in order, placed end to end.
    starts = []
    for d, n in enumerate(x.shape):
        iv = sorted({(s.index[d].start or 0, n if s.index[d].stop is None else s.index[d].stop) for s in shards})
        offs, pos = {}, 0
        for lo, hi in iv:
            offs[lo] = pos
            pos += hi - lo
        starts.append((offs, pos))
    out = np.empty(tuple(p for _, p in starts), dtype=x.dtype)
    for s in shards:
        idx = tuple(
            slice(offs[sl.start or 0], offs[sl.start or 0] + s.data.shape[d])
            for d, (sl, (offs, _)) in enumerate(zip(s.index, starts))
        )
        out[idx] = np.asarray(s.data)
    return out


def global_to_host_local(global_tree):
    """NumPy arrays holding this process's part of every global ``jax.Array`` leaf.

    For arrays made by :func:`host_local_to_global` this returns the slice the process passed in;
    replicated arrays come back whole; with one process every leaf comes back whole.
    """
    return jax.tree_util.tree_map(_local_block, global_tree)


class Processes:
    """The processes of this JAX job, for work they share outside a jitted program (e.g. one
    dataset written by all of them, :func:`jaxdrive.data.tfds_io.write_dataset`): ``index``,
    ``count`` and :meth:`gather`."""

    def __init__(self):
        self.index, self.count = jax.process_index(), jax.process_count()

    def gather(self, value: int) -> list[int]:
        """Every process's ``value`` (an int32), in process order; returns when all have called it."""
        from jax.experimental import multihost_utils

        if self.count == 1:
            return [int(value)]
        return [int(v) for v in multihost_utils.process_allgather(np.int32(value))]


def _first_host(nodelist: str) -> str:
    """``'node[001-004,007],other'`` -> ``'node001'``; ``'a,b'`` -> ``'a'``."""
    m = re.match(r"([^,\[]+)(?:\[([^\],\-]+))?", nodelist.strip())
    if not m:
        raise ValueError(f"SLURM_STEP_NODELIST: expected a SLURM host list, got {nodelist!r}")
    return m.group(1) + (m.group(2) or "")


def _int_env(env: Mapping[str, str], key: str) -> int:
    try:
        return int(env[key])
    except ValueError:
        raise ValueError(f"{key}: expected an integer, got {env[key]!r}") from None


def _resolve(coordinator_address, num_processes, process_id, env: Mapping[str, str]):
    """(source, kwargs for jax.distributed.initialize or None)."""
    if coordinator_address is not None:
        if num_processes is None or process_id is None:
            raise ValueError(
                "num_processes, process_id: expected both with coordinator_address, "
                f"got num_processes={num_processes!r}, process_id={process_id!r}"
            )
        return "explicit", dict(
            coordinator_address=coordinator_address, num_processes=int(num_processes), process_id=int(process_id)
        )
    keys = ("JAXDRIVE_COORDINATOR", "JAXDRIVE_NUM_PROCESSES", "JAXDRIVE_PROCESS_ID")
    present = [k for k in keys if env.get(k)]
    if present:
        if len(present) != len(keys):
            missing = [k for k in keys if k not in present]
            raise ValueError(f"{', '.join(missing)}: expected with {', '.join(present)}, got unset")
        return "env", dict(
            coordinator_address=env["JAXDRIVE_COORDINATOR"],
            num_processes=_int_env(env, keys[1]),
            process_id=_int_env(env, keys[2]),
        )
    if env.get("SLURM_NTASKS") and _int_env(env, "SLURM_NTASKS") > 1:
        nodelist = env.get("SLURM_STEP_NODELIST") or env.get("SLURM_JOB_NODELIST")
        if not nodelist or "SLURM_PROCID" not in env:
            raise ValueError(
                "SLURM_STEP_NODELIST, SLURM_PROCID: expected with SLURM_NTASKS > 1 (run under srun), got unset"
            )
        if env.get("JAXDRIVE_COORDINATOR_PORT"):
            port = _int_env(env, "JAXDRIVE_COORDINATOR_PORT")
        else:
            port = _int_env(env, "SLURM_JOB_ID") % 2**12 + (65536 - 2**12) if env.get("SLURM_JOB_ID") else 12355
        return "slurm", dict(
            coordinator_address=f"{_first_host(nodelist)}:{port}",
            num_processes=_int_env(env, "SLURM_NTASKS"),
            process_id=_int_env(env, "SLURM_PROCID"),
        )
    if "," in env.get("TPU_WORKER_HOSTNAMES", "") or env.get("MEGASCALE_COORDINATOR_ADDRESS"):
        return "tpu", {}
    return "single", None


def initialize_distributed(
    coordinator_address: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    local_device_ids: Sequence[int] | None = None,
) -> str:
    """Start JAX's multi-process runtime if this is a multi-process job; see the module docstring.

    Call it before any other JAX call. Returns the source of the settings used.
    """
    if jax.distributed.is_initialized():
        return "already"
    source, kwargs = _resolve(coordinator_address, num_processes, process_id, os.environ)
    if kwargs is None:
        return source
    if local_device_ids is not None:
        kwargs["local_device_ids"] = list(local_device_ids)
    jax.distributed.initialize(**kwargs)
    return source


def wait_for_all_processes(name: str, *, timeout_s: float = 3600.0) -> None:
    """Block until every process of a multi-process job reaches the barrier ``name`` (the same
    name on all processes); nothing with one process. It runs on the coordination service, not
    as a collective, so it waits as long as ``timeout_s`` whereas a CPU collective's first call
    gives up when its peers are 30 s late (gloo's fixed connect timeout)."""
    from jax._src import distributed

    client = distributed.global_state.client
    if jax.process_count() == 1 or client is None:
        return
    client.wait_at_barrier(name, int(timeout_s * 1000))
