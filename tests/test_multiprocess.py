"""Two JAX processes x 4 CPU devices (gloo collectives) agree with one process x 8 devices.

Each worker builds ``make_mesh(data=2, seq=4)`` over the 8 global devices, assembles a global
batch from its host-local rows with ``host_local_to_global``, runs a jitted reduction, a jitted
matmul, a cross-process contraction and ring attention (forward and input gradient), and writes
its results; the test recomputes the same in this process and compares. Each worker also places
host parameters with ``shard_params`` on a data x tensor mesh: every device holds its slice, and
no array is gathered across processes to check that they agree.
"""

import os
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from jaxdrive.parallel import logical_to_spec, make_mesh

ROOT = Path(__file__).resolve().parents[1]
TIMEOUT_S = 120

WORKER = textwrap.dedent("""
    import sys
    import jax
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.config.update("jax_num_cpu_devices", 4)
    import numpy as np
    from jax.sharding import NamedSharding
    from jaxdrive.parallel import (global_to_host_local, host_local_to_global,
                                   initialize_distributed, logical_to_spec, make_hybrid_mesh,
                                   make_mesh)
    sys.path.insert(0, sys.argv[4])
    from test_multiprocess import compute, global_inputs

    port, pid, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
    assert initialize_distributed(f"localhost:{port}", 2, pid) == "explicit"
    assert jax.process_count() == 2 and jax.device_count() == 8 and jax.local_device_count() == 4
    mesh = make_mesh(data=2, seq=4)
    hybrid = make_hybrid_mesh(ici={"seq": 4}, dcn={"data": 2})
    hybrid_ok = all(d.process_index == i for i in range(2) for d in hybrid.devices[i].flat)
    x, w = global_inputs()
    # The rows of x this process's devices hold, in order: its host-local slice.
    sharding = NamedSharding(mesh, logical_to_spec(("batch", "tokens"), mesh=mesh))
    rows = sorted({idx[0].start or 0 for idx in
                   sharding.addressable_devices_indices_map(x.shape).values()})
    local = np.concatenate([x[r:r + 4] for r in rows])  # 4 rows per data shard
    xg = host_local_to_global(local, mesh, ("batch", "tokens"))
    wg = host_local_to_global(w, mesh, (None, None))
    assert xg.shape == x.shape and wg.shape == w.shape
    total, y, gram, att, datt = compute(mesh, xg, wg)
    # host parameters placed shard by shard, with no cross-process gather: each device holds its slice
    import flax.linen as nn
    from jaxdrive.parallel import shard_params
    tp = make_mesh(data=2, tensor=4)
    host = {"w": nn.LogicallyPartitioned(np.arange(6 * 8, dtype=np.float32).reshape(6, 8), ("embed", "mlp")),
            "b": np.linspace(-1, 1, 8, dtype=np.float32)}
    from jax.experimental import multihost_utils
    gathers, real_assert_equal = [], multihost_utils.assert_equal
    multihost_utils.assert_equal = lambda *a, **k: gathers.append(a) or real_assert_equal(*a, **k)
    placed = shard_params(host, tp)
    multihost_utils.assert_equal = real_assert_equal
    params_ok = not gathers and placed["w"].sharding.spec == jax.sharding.PartitionSpec("fsdp", "tensor") and all(
        np.array_equal(np.asarray(s.data), host["w"].value[s.index]) for s in placed["w"].addressable_shards
    ) and all(np.array_equal(np.asarray(s.data), host["b"]) for s in placed["b"].addressable_shards)
    back = global_to_host_local({"x": xg, "y": y, "att": att, "datt": datt})
    np.savez(out, rows=np.asarray(rows), local=local, x_back=back["x"], y=back["y"],
             att=back["att"], datt=back["datt"],
             total=np.asarray(total.addressable_data(0)), gram=np.asarray(gram.addressable_data(0)),
             hybrid_ok=hybrid_ok, params_ok=params_ok)
    jax.distributed.shutdown()
""")


def global_inputs():
    x = (np.arange(8 * 8 * 4, dtype=np.float32).reshape(8, 8, 4) % 7 - 3) / 3
    w = (np.arange(4 * 5, dtype=np.float32).reshape(4, 5) % 5 - 2) / 2
    return x, w


def compute(mesh, x, w):
    """Jitted reduction, matmul, a contraction over both sharded axes (all-reduce), and ring
    attention over the seq axis (tokens as one head) with its input gradient."""
    from jaxdrive.attention import attention

    def ring(x):
        h = x[:, :, None, :]
        return attention(h, h, h, impl="ring", mesh=mesh, causal_block=2)[:, :, 0, :]

    with jax.set_mesh(mesh):
        total = jax.jit(lambda x: jnp.sum(x * x))(x)
        y = jax.jit(lambda x, w: jnp.einsum("btc,cd->btd", x, w))(x, w)
        gram = jax.jit(lambda x: jnp.einsum("btc,bte->ce", x, x, out_sharding=P()))(x)
        att = jax.jit(ring)(x)
        datt = jax.jit(jax.grad(lambda x: jnp.sum(ring(x) * jnp.cos(x))))(x)
    return total, y, gram, att, datt


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _gloo_available() -> bool:
    from jax._src.lib import _jax

    return hasattr(_jax, "make_gloo_tcp_collectives")


@pytest.mark.slow(seconds=9)
@pytest.mark.skipif(not _gloo_available(), reason="jaxlib built without gloo CPU collectives")
def test_two_processes_match_one(tmp_path):
    script = tmp_path / "worker.py"
    script.write_text(WORKER)
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env.update(JAX_PLATFORMS="cpu", PYTHONPATH=str(ROOT))
    port = _free_port()
    procs = [
        subprocess.Popen(
            [sys.executable, str(script), str(port), str(i), str(tmp_path / f"out{i}.npz"), str(Path(__file__).parent)],
            env=env,
            cwd=tmp_path,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for i in range(2)
    ]
    logs = []
    try:
        for p in procs:
            logs.append(p.communicate(timeout=TIMEOUT_S)[0])
    except subprocess.TimeoutExpired:
        for p in procs:
            p.kill()
        pytest.fail(f"workers did not finish in {TIMEOUT_S} s")
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    for i, (p, log) in enumerate(zip(procs, logs)):
        assert p.returncode == 0, f"worker {i} failed:\n{log[-4000:]}"

    x, w = global_inputs()
    mesh = make_mesh(data=2, seq=4)
    xs = jax.device_put(x, NamedSharding(mesh, logical_to_spec(("batch", "tokens"), mesh=mesh)))
    total, y, gram, att, datt = (np.asarray(a) for a in compute(mesh, xs, jnp.asarray(w)))
    np.testing.assert_allclose(total, np.sum(x * x), rtol=1e-5)  # the reference itself
    seen = []
    for i in range(2):
        r = np.load(tmp_path / f"out{i}.npz")
        assert bool(r["hybrid_ok"]), "make_hybrid_mesh: data axis should run across processes"
        assert bool(r["params_ok"]), "shard_params: a device holds other values than its slice of the host parameters"
        rows = np.concatenate([np.arange(s, s + 4) for s in r["rows"]])
        seen.extend(rows.tolist())
        np.testing.assert_array_equal(r["x_back"], r["local"])
        np.testing.assert_allclose(r["y"], y[rows], rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(r["total"], total, rtol=1e-5)
        np.testing.assert_allclose(r["gram"], gram, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(r["att"], att[rows], rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(r["datt"], datt[rows], rtol=1e-5, atol=1e-5)
    assert sorted(seen) == list(range(8)), "each batch row held by exactly one process"
