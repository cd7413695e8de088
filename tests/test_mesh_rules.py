"""Meshes, logical-axis rules, parameter sharding and host-local arrays on 8 fake CPU devices."""

import logging

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.sharding import AxisType, NamedSharding
from jax.sharding import PartitionSpec as P

from jaxdrive.parallel import (
    ACTIVATION_RULES,
    PARAM_RULES,
    batch_axes,
    batch_shards,
    constrain,
    global_to_host_local,
    host_local_to_global,
    logical_to_spec,
    make_hybrid_mesh,
    make_mesh,
    param_shardings,
    parse_mesh_spec,
    shard_params,
)
from jaxdrive.parallel.host import _first_host, _resolve
from jaxdrive.parallel.rules import LOGICAL_AXIS_RULES

AXES = ("data", "fsdp", "seq", "tensor")


# ---------------------------------------------------------------- mesh
@pytest.mark.parametrize(
    "kw, shape",
    [
        ({"data": 8}, (8, 1, 1, 1)),
        ({"data": 2, "seq": 4}, (2, 1, 4, 1)),
        ({"data": 2, "fsdp": 2, "tensor": 2}, (2, 2, 1, 2)),
        ({"seq": -1, "tensor": 2}, (1, 1, 4, 2)),
    ],
)
def test_make_mesh_shape_names_types(kw, shape):
    mesh = make_mesh(**kw)
    assert mesh.axis_names == AXES
    assert tuple(mesh.axis_sizes) == shape
    assert mesh.axis_types == (AxisType.Explicit,) * 4
    assert sorted(d.id for d in mesh.devices.flat) == list(range(8))


def test_make_mesh_auto_types_and_device_subset():
    mesh = make_mesh(data=2, devices=jax.devices()[:2], axis_types=AxisType.Auto)
    assert mesh.axis_types == (AxisType.Auto,) * 4
    assert tuple(mesh.axis_sizes) == (2, 1, 1, 1)


@pytest.mark.parametrize(
    "kw, match",
    [
        ({"data": 3}, "make_mesh: expected axis sizes whose product is 8"),
        ({"data": 0}, "data: expected a positive integer or -1, got 0"),
        ({"data": -1, "seq": -1}, "at most one axis of size -1"),
        ({"data": 3, "seq": -1}, "seq: expected the other axes' product 3 to divide 8"),
        ({"tensor": 2.0}, "tensor: expected a positive integer"),
        ({"axis_types": (AxisType.Explicit,)}, "axis_types: expected one AxisType or 4"),
    ],
)
def test_make_mesh_errors(kw, match):
    with pytest.raises(ValueError, match=match):
        make_mesh(**kw)


def test_make_hybrid_mesh_single_process():
    mesh = make_hybrid_mesh(ici={"data": 2, "seq": -1})
    assert mesh.axis_names == AXES and tuple(mesh.axis_sizes) == (2, 1, 4, 1)
    assert mesh.axis_types == (AxisType.Explicit,) * 4
    with pytest.raises(ValueError, match="dcn: expected axis sizes whose product is 1"):
        make_hybrid_mesh(ici={"data": 4}, dcn={"data": 2})
    with pytest.raises(ValueError, match="ici: expected axis names"):
        make_hybrid_mesh(ici={"model": 8})


def test_parse_mesh_spec():
    assert parse_mesh_spec("data=2,seq=4") == {"data": 2, "seq": 4}
    assert parse_mesh_spec(" tensor = 2 , fsdp=-1 ") == {"tensor": 2, "fsdp": -1}
    assert parse_mesh_spec("") == {}
    assert tuple(make_mesh(**parse_mesh_spec("data=2,seq=-1")).axis_sizes) == (2, 1, 4, 1)
    for bad in ("data=2,data=4", "model=2", "data", "data=x", "data=0"):
        with pytest.raises(ValueError, match="mesh spec: expected"):
            parse_mesh_spec(bad)


# ---------------------------------------------------------------- rules
@pytest.mark.parametrize(
    "kw, axes, shards",
    [
        (dict(data=2, fsdp=2, seq=2), ("data", "fsdp"), 4),
        (dict(data=1, fsdp=1, seq=8), ("data", "fsdp"), 1),
        (dict(fsdp=4, tensor=2), ("data", "fsdp"), 4),
    ],
)
def test_a_batch_splits_over_the_data_and_fsdp_axes(kw, axes, shards):
    """The one definition of a batch's mesh axes, which the "batch" rule, the samplers, the
    trainers and the planner share."""
    mesh = make_mesh(**kw)
    assert batch_axes(mesh) == axes and batch_shards(mesh) == shards
    assert LOGICAL_AXIS_RULES["batch"][0] == axes
    assert batch_axes(None) == () and batch_shards(None) == 1


def test_logical_to_spec_tables():
    names = ("batch", "views", "tokens", "embed")
    assert logical_to_spec(names) == P(("data", "fsdp"), None, "seq", None)
    assert logical_to_spec(("embed", "mlp"), PARAM_RULES) == P("fsdp", "tensor")
    assert logical_to_spec(("embed", "heads", "head_dim"), PARAM_RULES) == P("fsdp", "tensor", None)
    assert logical_to_spec(("embed", "mlp"), ACTIVATION_RULES) == P(None, "tensor")
    assert logical_to_spec((None, "tokens")) == P(None, "seq")


def test_logical_to_spec_errors():
    with pytest.raises(ValueError, match="names: expected logical axis names .* got 'tokenz'"):
        logical_to_spec(("batch", "tokenz"))
    with pytest.raises(ValueError, match="mesh axis once per array, got 'tensor'"):
        logical_to_spec(("heads", "mlp"))
    with pytest.raises(ValueError, match="got 'fsdp' for both 'batch' and 'embed'"):
        logical_to_spec(("batch", "embed"), {"batch": ("data", "fsdp"), "embed": "fsdp"})
    with pytest.raises(ValueError, match="names: expected 2 names for shape"):
        logical_to_spec(("batch",), shape=(4, 4))


def test_logical_to_spec_mesh_fallback(caplog):
    mesh = make_mesh(data=2, fsdp=2, seq=2)
    # batch 2 is divisible by data (2) but not data*fsdp (4): keeps the prefix "data".
    with caplog.at_level(logging.WARNING, logger="jaxdrive.parallel.rules"):
        spec = logical_to_spec(("batch", "tokens"), shape=(2, 3), mesh=mesh)
        assert spec == P("data", None)
        logical_to_spec(("batch", "tokens"), shape=(2, 3), mesh=mesh)
    assert sum("sharding fallback" in r.message for r in caplog.records) == 1
    assert logical_to_spec(("batch", "tokens"), shape=(8, 6), mesh=mesh) == P(("data", "fsdp"), "seq")
    # Mesh axes absent from a mesh are dropped.
    small = jax.make_mesh((8,), ("data",), axis_types=(AxisType.Explicit,))
    assert logical_to_spec(("batch", "tokens"), mesh=small) == P("data", None)


def test_constrain_inside_jit_under_mesh():
    mesh = make_mesh(data=2, seq=4)
    x = jnp.arange(4 * 8 * 3, dtype=jnp.float32).reshape(4, 8, 3)
    assert constrain(x, ("batch", "tokens", "embed")) is x  # no mesh: no-op

    @jax.jit
    def f(x):
        y = constrain(x * 2.0, ("batch", "tokens", "embed"))
        assert jax.typeof(y).sharding.spec == P(("data", "fsdp"), "seq", None)
        return y

    with jax.set_mesh(mesh):
        out = f(x)
    assert out.sharding.is_equivalent_to(NamedSharding(mesh, P("data", "seq", None)), 3)  # fsdp=1
    np.testing.assert_array_equal(np.asarray(out), 2.0 * np.asarray(x))
    with pytest.raises(ValueError, match="names: expected 3 names"):
        constrain(x, ("batch",), mesh=mesh)


def test_constrain_auto_mesh_and_explicit_argument():
    x = jnp.ones((8, 4))
    auto = make_mesh(data=2, seq=4, axis_types=AxisType.Auto)
    out = jax.jit(lambda x: constrain(x + 1, ("batch", "tokens"), mesh=auto))(x)
    assert out.sharding.is_equivalent_to(NamedSharding(auto, P("data", "seq")), 2)
    explicit = make_mesh(data=8)
    out = constrain(x, ("batch", None), mesh=explicit)
    assert out.sharding.is_equivalent_to(NamedSharding(explicit, P("data", None)), 2)


# ---------------------------------------------------------------- params
class _Block(nn.Module):
    """Attention-like projection + MLP with logically named parameters, written for Explicit
    meshes: each weight is gathered over fsdp at use (``constrain`` with the activation rules)
    and contractions over a tensor-sharded dimension name their output sharding."""

    heads: int = 2
    head_dim: int = 4
    hidden: int = 16

    def _w(self, name, shape, names, init=nn.initializers.normal(0.5)):
        w = self.param(name, nn.with_logical_partitioning(init, names), shape)
        return constrain(w, names)

    @staticmethod
    def _out(names):
        mesh = jax.sharding.get_abstract_mesh()
        return None if mesh.empty else logical_to_spec(names, mesh=mesh)

    @nn.compact
    def __call__(self, x):  # x [B, L, D]
        d = x.shape[-1]
        x = constrain(x, ("batch", "tokens", "embed"))
        wq = self._w("wq", (d, self.heads, self.head_dim), ("embed", "heads", "head_dim"))
        wo = self._w("wo", (self.heads, self.head_dim, d), ("heads", "head_dim", "embed"))
        scale = self._w("scale", (d,), ("embed",), nn.initializers.ones)
        w1 = self._w("w1", (d, self.hidden), ("embed", "mlp"))
        w2 = self._w("w2", (self.hidden, d), ("mlp", "embed"))
        h = jnp.einsum("bld,dhk->blhk", x * scale, wq)
        x = x + jnp.einsum("blhk,hkd->bld", jnp.tanh(h), wo, out_sharding=self._out(("batch", "tokens", "embed")))
        y = nn.gelu(jnp.einsum("bld,dm->blm", x, w1))
        x = x + jnp.einsum("blm,md->bld", y, w2, out_sharding=self._out(("batch", "tokens", "embed")))
        return constrain(x, ("batch", "tokens", "embed"))


@pytest.mark.slow(seconds=8)
def test_params_sharded_by_rules_and_forward_matches():
    model = _Block()
    x = jax.random.normal(jax.random.key(1), (4, 8, 8))
    boxed = model.init(jax.random.key(0), x)
    mesh = make_mesh(data=2, fsdp=2, tensor=2)

    abstract = jax.eval_shape(model.init, jax.random.key(0), x)
    shardings = param_shardings(abstract, mesh)
    params = nn.unbox(boxed)
    assert jax.tree.structure(shardings) == jax.tree.structure(params)
    p = shardings["params"]
    assert p["wq"].spec == P("fsdp", "tensor", None)
    assert p["wo"].spec == P("tensor", None, "fsdp")
    assert p["scale"].spec == P("fsdp")
    assert p["w1"].spec == P("fsdp", "tensor")
    assert p["w2"].spec == P("tensor", "fsdp")

    sharded = shard_params(boxed, mesh)
    w = sharded["params"]["w1"]
    assert w.sharding.spec == P("fsdp", "tensor")
    assert w.addressable_shards[0].data.shape == (4, 8)

    ref = model.apply(params, x)
    xs = jax.device_put(x, NamedSharding(mesh, logical_to_spec(("batch", "tokens", "embed"))))
    with jax.set_mesh(mesh):
        out = jax.jit(model.apply)(sharded, xs)
    np.testing.assert_allclose(np.asarray(out), np.asarray(ref), rtol=1e-5, atol=1e-5)

    def loss(p, x):
        return jnp.mean(model.apply(p, x) ** 2)

    g_ref = jax.grad(loss)(params, x)
    with jax.set_mesh(mesh):
        g = jax.jit(jax.grad(loss))(sharded, xs)
    assert g["params"]["w1"].sharding.spec == P("fsdp", "tensor")  # grads sharded like params
    for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(g_ref)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-6)


def test_param_shardings_fallback_and_plain_leaves():
    mesh = make_mesh(fsdp=8)
    tree = {
        "w": nn.LogicallyPartitioned(jnp.ones((6, 4)), ("embed", "mlp")),
        "m": nn.Partitioned(jnp.ones((8,)), ("fsdp",)),
        "step": jnp.zeros(()),
    }
    s = param_shardings(tree, mesh)
    assert s["w"].spec == P(None, "tensor")  # 6 rows do not split over fsdp=8: replicated
    assert s["m"].spec == P("fsdp")
    assert s["step"].spec == P()
    placed = shard_params(tree, mesh)
    np.testing.assert_array_equal(np.asarray(placed["w"]), np.ones((6, 4)))


# ---------------------------------------------------------------- host
def test_host_local_to_global_single_process():
    mesh = make_mesh(data=2, seq=4)
    batch = {"x": np.arange(8 * 4 * 2, dtype=np.float32).reshape(8, 4, 2), "ids": np.arange(8, dtype=np.int32)}
    g = host_local_to_global(batch, mesh)
    assert g["x"].shape == (8, 4, 2)
    assert g["x"].sharding.is_equivalent_to(NamedSharding(mesh, P("data")), 3)
    np.testing.assert_array_equal(np.asarray(g["x"]), batch["x"])
    g2 = host_local_to_global(batch, mesh, {"x": ("batch", "tokens"), "ids": P("data")})
    assert g2["x"].sharding.is_equivalent_to(NamedSharding(mesh, P("data", "seq")), 3)
    back = global_to_host_local(g2)
    np.testing.assert_array_equal(back["x"], batch["x"])
    np.testing.assert_array_equal(back["ids"], batch["ids"])
    with pytest.raises(ValueError, match="batch_tree: expected arrays with a leading batch axis"):
        host_local_to_global({"s": np.float32(1.0)}, mesh)


def test_initialize_distributed_resolution():
    assert _resolve(None, None, None, {}) == ("single", None)
    assert _resolve("h:1", 2, 1, {})[1] == dict(coordinator_address="h:1", num_processes=2, process_id=1)
    env = {
        "JAXDRIVE_COORDINATOR": "c:9",
        "JAXDRIVE_NUM_PROCESSES": "4",
        "JAXDRIVE_PROCESS_ID": "3",
        "SLURM_NTASKS": "8",
    }
    assert _resolve(None, None, None, env) == ("env", dict(coordinator_address="c:9", num_processes=4, process_id=3))
    with pytest.raises(ValueError, match="JAXDRIVE_PROCESS_ID: expected"):
        _resolve(None, None, None, {"JAXDRIVE_COORDINATOR": "c:9", "JAXDRIVE_NUM_PROCESSES": "2"})
    slurm = {
        "SLURM_NTASKS": "4",
        "SLURM_PROCID": "2",
        "SLURM_JOB_ID": "100",
        "SLURM_STEP_NODELIST": "gpu[007-010],cpu1",
    }
    src, kw = _resolve(None, None, None, slurm)
    assert src == "slurm" and kw["coordinator_address"] == f"gpu007:{100 + 61440}"
    assert kw["num_processes"] == 4 and kw["process_id"] == 2
    assert _resolve(None, None, None, {"SLURM_NTASKS": "1"}) == ("single", None)
    assert _resolve(None, None, None, {"TPU_WORKER_HOSTNAMES": "a,b"}) == ("tpu", {})
    assert _first_host("n1,n2") == "n1" and _first_host("node[3,5-6]") == "node3"
    with pytest.raises(ValueError, match="num_processes, process_id: expected both"):
        _resolve("h:1", None, None, {})
