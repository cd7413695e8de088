"""Device meshes with the four jaxdrive axes ``data``, ``fsdp``, ``seq`` and ``tensor``.

Every mesh built here names all four axes in that order, keeping axes of size 1, so that a
``PartitionSpec`` produced by :mod:`jaxdrive.parallel.rules` can always name any axis. Axis types
default to ``Explicit`` (sharding in types, see the JAX "explicit sharding" guide); pass
``axis_types=jax.sharding.AxisType.Auto`` for compiler-chosen propagation.

* :func:`make_mesh` — one mesh over a flat device list (single host, or all global devices).
* :func:`make_hybrid_mesh` — multi-host / multi-slice: each axis size is ``ici * dcn``; the
  ``dcn`` factor runs across slices (TPU ``slice_index``) or, where devices carry no slice index
  (GPU, CPU), across processes; the ``ici`` factor runs within one slice / process.
* :func:`parse_mesh_spec` — the CLI's ``--mesh data=2,seq=4`` flag.

In each of these a size of ``-1`` for one axis means "whatever is left".
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import jax
import numpy as np
from jax.experimental import mesh_utils
from jax.sharding import AxisType, Mesh

MESH_AXES: tuple[str, ...] = ("data", "fsdp", "seq", "tensor")


def _resolve_sizes(sizes: Mapping[str, int], total: int, what: str) -> tuple[int, ...]:
    """Sizes for MESH_AXES (missing axes = 1) whose product is ``total``; one -1 = the rest."""
    for name in sizes:
        if name not in MESH_AXES:
            raise ValueError(f"{what}: expected axis names from {list(MESH_AXES)}, got {name!r}")
    out = []
    for name in MESH_AXES:
        n = sizes.get(name, 1)
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or (n < 1 and n != -1):
            raise ValueError(f"{name}: expected a positive integer or -1, got {n!r}")
        out.append(int(n))
    rest = [name for name, n in zip(MESH_AXES, out) if n == -1]
    if len(rest) > 1:
        raise ValueError(f"{what}: expected at most one axis of size -1, got {rest}")
    known = math.prod(n for n in out if n != -1)
    if rest:
        if total % known:
            raise ValueError(
                f"{rest[0]}: expected the other axes' product {known} to divide {total} "
                f"devices, got a remainder of {total % known}"
            )
        out[MESH_AXES.index(rest[0])] = total // known
    elif known != total:
        shape = dict(zip(MESH_AXES, out))
        raise ValueError(f"{what}: expected axis sizes whose product is {total}, got {shape} (product {known})")
    return tuple(out)


def _axis_types(axis_types) -> tuple[AxisType, ...]:
    if isinstance(axis_types, AxisType):
        return (axis_types,) * len(MESH_AXES)
    types = tuple(axis_types)
    if len(types) != len(MESH_AXES) or not all(isinstance(t, AxisType) for t in types):
        raise ValueError(f"axis_types: expected one AxisType or {len(MESH_AXES)} of them, got {axis_types!r}")
    return types


def make_mesh(
    data: int = 1,
    fsdp: int = 1,
    seq: int = 1,
    tensor: int = 1,
    devices: Sequence[jax.Device] | None = None,
    *,
    axis_types: AxisType | Sequence[AxisType] = AxisType.Explicit,
) -> Mesh:
    """A mesh of shape ``(data, fsdp, seq, tensor)`` over ``devices`` (default ``jax.devices()``).

    The product of the sizes must equal ``len(devices)``; one size may be ``-1`` (the rest).
    Device order follows ``jax.make_mesh`` (topology-aware on TPU / GPU). Devices of several TPU
    slices (a multi-slice job) get :func:`make_hybrid_mesh` with the ``data`` axis across the
    slices, so that only the gradient all-reduce crosses the slow network: ``data`` must then be a
    multiple of the slice count.
    """
    types = _axis_types(axis_types)
    devices = list(jax.devices() if devices is None else devices)
    if not devices:
        raise ValueError("devices: expected at least one device, got none")
    shape = _resolve_sizes({"data": data, "fsdp": fsdp, "seq": seq, "tensor": tensor}, len(devices), "make_mesh")
    slices = tpu_slices(devices)
    if slices > 1:
        if shape[0] % slices:
            raise ValueError(
                f"data: expected a multiple of the {slices} TPU slices the devices span (the data axis runs "
                f"across slices), got data={shape[0]}"
            )
        ici = dict(zip(MESH_AXES, shape), data=shape[0] // slices)
        return make_hybrid_mesh(ici, {"data": slices}, devices, axis_types=types)
    grid = _physical_grid(
        lambda split: mesh_utils.create_device_mesh(shape, devices, allow_split_physical_axes=split), shape, devices
    )
    return Mesh(grid, MESH_AXES, axis_types=types)


def _physical_grid(build, shape: Sequence[int], devices: Sequence[jax.Device]) -> np.ndarray:
    """The device grid of ``build(split)``: first with each mesh axis on whole physical axes
    (the TPU's rings), else with physical axes split between mesh axes.

    ``mesh_utils`` lays a mesh on a TPU torus only where every mesh axis is a product of whole
    physical axes, unless told it may split them (``jax.make_mesh`` allows that on v5e only):
    ``fsdp=32, seq=2`` on v6e's 8x8 has no such layout and raised NotImplementedError. A split
    axis still has its neighbours on ICI, only its collectives lose the wrap-around link.
    """
    try:
        return np.asarray(build(False))
    except NotImplementedError:
        pass
    try:
        return np.asarray(build(True))
    except NotImplementedError as e:
        physical = getattr(devices[0], "coords", None)
        raise ValueError(
            f"mesh: expected axis sizes that can be laid on the devices' physical grid, got "
            f"{dict(zip(MESH_AXES, shape))} on {len(devices)} {devices[0].device_kind} devices "
            f"(coords of the first: {physical}): {e}"
        ) from None


def tpu_slices(devices: Sequence[jax.Device]) -> int:
    """How many TPU slices ``devices`` span (1 for one slice and for devices of other platforms)."""
    attr, n = _granules(devices)
    return n if attr == "slice_index" else 1


def _granules(devices: Sequence[jax.Device]) -> tuple[str, int]:
    """The unit of the slow network: TPU slices (``slice_index``), else processes.

    Only TPU devices use ``slice_index``: multi-process CPU devices carry ``slice_index = 0``
    for every process, and GPU hosts talk over the slow network anyway."""
    if all(d.platform == "tpu" and getattr(d, "slice_index", None) is not None for d in devices):
        return "slice_index", len({d.slice_index for d in devices})
    return "process_index", len({d.process_index for d in devices})


def make_hybrid_mesh(
    ici: Mapping[str, int] | None = None,
    dcn: Mapping[str, int] | None = None,
    devices: Sequence[jax.Device] | None = None,
    *,
    axis_types: AxisType | Sequence[AxisType] = AxisType.Explicit,
) -> Mesh:
    """A multi-host mesh: axis ``a`` has size ``ici[a] * dcn[a]`` (missing entries are 1).

    ``dcn`` splits axes across granules (TPU slices, or processes on GPU / CPU): the product of
    ``dcn`` must equal the number of granules. ``ici`` splits axes within one granule: its
    product must equal the devices per granule. One ``-1`` is allowed in each mapping. Put the
    communication-heavy axes (``tensor``, ``seq``) in ``ici`` and ``data`` (or ``fsdp``) in
    ``dcn``. The result has the axis order of :func:`make_mesh`.
    """
    devices = list(jax.devices() if devices is None else devices)
    if not devices:
        raise ValueError("devices: expected at least one device, got none")
    attr, n_granules = _granules(devices)
    if len(devices) % n_granules:
        raise ValueError(
            f"devices: expected the same number of devices in each of "
            f"{n_granules} granules ({attr}), got {len(devices)} devices"
        )
    dcn_shape = _resolve_sizes(dict(dcn or {}), n_granules, "dcn")
    ici_shape = _resolve_sizes(dict(ici or {}), len(devices) // n_granules, "ici")
    grid = _physical_grid(
        lambda split: mesh_utils.create_hybrid_device_mesh(
            ici_shape, dcn_shape, devices, process_is_granule=(attr == "process_index"), allow_split_physical_axes=split
        ),
        ici_shape,
        devices,
    )
    return Mesh(grid, MESH_AXES, axis_types=_axis_types(axis_types))


def parse_mesh_spec(spec: str) -> dict[str, int]:
    """``"data=2,seq=4"`` -> ``{"data": 2, "seq": 4}`` (``-1`` allowed; empty string -> ``{}``).

    Pass the result as keyword arguments to :func:`make_mesh`.
    """
    if not isinstance(spec, str):
        raise ValueError(f"mesh spec: expected a string like 'data=2,seq=4', got {spec!r}")
    out: dict[str, int] = {}
    for item in filter(None, (s.strip() for s in spec.split(","))):
        name, sep, value = (s.strip() for s in item.partition("="))
        if not sep or name not in MESH_AXES:
            raise ValueError(f"mesh spec: expected items 'axis=size' with axis in {list(MESH_AXES)}, got {item!r}")
        if name in out:
            raise ValueError(f"mesh spec: expected each axis once, got {name!r} twice")
        try:
            size = int(value)
        except ValueError:
            size = 0
        if size < 1 and size != -1:
            raise ValueError(f"mesh spec: expected {name} to be a positive integer or -1, got {value!r}")
        out[name] = size
    return out


# ------------------------------------------------------------------ the context mesh
# Under an Explicit mesh shardings are part of array types: layers read them from the mesh set
# with ``jax.set_mesh`` (an AbstractMesh, also inside ``jit``) and from their inputs' types.


def context_mesh():
    """The mesh set with ``jax.set_mesh`` (an ``AbstractMesh``), or None outside one."""
    mesh = jax.sharding.get_abstract_mesh()
    return None if mesh.empty else mesh


def explicit_mesh():
    """The context mesh when it has an Explicit axis (where outputs need stated shardings)."""
    mesh = context_mesh()
    if mesh is None or not any(t == AxisType.Explicit for t in mesh.axis_types):
        return None
    return mesh


def mesh_platform(mesh=None) -> str:
    """The platform (``"tpu"``, ``"gpu"``, ``"cpu"``) of the devices a program runs on: those of
    ``mesh`` (a ``Mesh``: its devices; an ``AbstractMesh``: its abstract device), else of the
    context mesh, else JAX's default backend. Choices that depend on the hardware (the attention
    kernel, the dtype policy) ask this, not ``jax.default_backend()``: a program compiled ahead of
    time for TPU topology devices on a CPU host runs on TPUs, whatever backend the host started."""
    mesh = context_mesh() if mesh is None else mesh
    if mesh is not None:
        if isinstance(mesh, Mesh) and mesh.devices.size:
            return str(mesh.devices.flat[0].platform)
        device = getattr(mesh, "abstract_device", None)
        if device is not None:
            return str(device.platform)
    return jax.default_backend()


BATCH_AXES = ("data", "fsdp")  # the mesh axes a batch of examples is split over (rules.py's "batch" rule)


def batch_axes(mesh) -> tuple[str, ...]:
    """The mesh axes a batch is sharded over (``data``, ``fsdp``), those ``mesh`` has (none
    without a mesh)."""
    return () if mesh is None else tuple(a for a in BATCH_AXES if a in mesh.axis_names)


def batch_shards(mesh) -> int:
    """How many parts a batch is split into: the product of ``mesh``'s batch axes (1 without)."""
    if mesh is None:
        return 1
    sizes = dict(zip(mesh.axis_names, mesh.axis_sizes))
    return math.prod(int(sizes[a]) for a in batch_axes(mesh))


def mesh_axis_size(name: str) -> int:
    """Size of mesh axis ``name`` in the context mesh (1 without a mesh or without that axis)."""
    mesh = context_mesh()
    if mesh is None or name not in mesh.axis_names:
        return 1
    return int(dict(zip(mesh.axis_names, mesh.axis_sizes))[name])


def spec_of(x) -> tuple:
    """The ``PartitionSpec`` entries of ``x``'s type, one per dimension (None where unsharded)."""
    spec = tuple(getattr(getattr(jax.typeof(x), "sharding", None), "spec", ()) or ())
    return spec + (None,) * (x.ndim - len(spec))


def entry_axes(entry) -> tuple[str, ...]:
    """The mesh axes of one ``PartitionSpec`` entry: None, an axis name or a tuple of names."""
    return () if entry is None else (entry,) if isinstance(entry, str) else tuple(entry)
