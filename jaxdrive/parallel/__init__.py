"""Meshes, logical-axis sharding rules and host-to-global arrays (the sequence-sharded attention
kernels live in :mod:`jaxdrive.attention`, which builds on this package).

``rules.py`` is the only place that maps logical axis names to the mesh axes ``data``, ``fsdp``,
``seq`` and ``tensor``.
"""

from .host import Processes, global_to_host_local, host_local_to_global, initialize_distributed, wait_for_all_processes
from .mesh import MESH_AXES, batch_axes, batch_shards, make_hybrid_mesh, make_mesh, parse_mesh_spec
from .rules import (
    ACTIVATION_RULES,
    LOGICAL_AXIS_RULES,
    PARAM_RULES,
    constrain,
    logical_to_spec,
    param_shardings,
    shard_params,
)

__all__ = [
    "ACTIVATION_RULES",
    "LOGICAL_AXIS_RULES",
    "MESH_AXES",
    "PARAM_RULES",
    "Processes",
    "constrain",
    "global_to_host_local",
    "host_local_to_global",
    "initialize_distributed",
    "logical_to_spec",
    "batch_axes",
    "batch_shards",
    "make_hybrid_mesh",
    "make_mesh",
    "param_shardings",
    "parse_mesh_spec",
    "shard_params",
    "wait_for_all_processes",
]
