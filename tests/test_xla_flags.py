"""jaxdrive.xla_flags: flags are appended without overriding the user's, and with the CPU flags a
compiled train loss gives the same number on every call (XLA:CPU's YNNPACK fusions did not)."""

import os
from pathlib import Path

import jax
import numpy as np
import pytest

from jaxdrive.config import load_config
from jaxdrive.data.batches import model_inputs
from jaxdrive.train import flow_step
from jaxdrive.train.run import Run
from jaxdrive.xla_flags import (
    CPU_DETERMINISTIC,
    CPU_FAST_COMPILE,
    CPU_SERIAL_CODEGEN,
    add_xla_flags,
    deterministic_cpu,
    fast_compiling_cpu,
)

from train_fixtures import write_synthetic

TINY = Path(__file__).resolve().parents[1] / "configs" / "tiny.py"


def test_flags_are_appended_once_and_the_users_value_kept(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_experimental_ynn_fusion_type=reduce --other=1")
    add_xla_flags("--xla_cpu_experimental_ynn_fusion_type=", "--new=2")
    add_xla_flags("--new=3")
    assert os.environ["XLA_FLAGS"] == "--xla_cpu_experimental_ynn_fusion_type=reduce --other=1 --new=2"
    monkeypatch.delenv("XLA_FLAGS")
    assert deterministic_cpu() and os.environ["XLA_FLAGS"] == CPU_DETERMINISTIC
    with pytest.raises(ValueError, match="flags: expected '--name=value', got 'new'"):
        add_xla_flags("new")
    monkeypatch.delenv("XLA_FLAGS")
    monkeypatch.setenv("JAXDRIVE_CPU_FLAGS", "0")  # a jaxlib that no longer knows the flag
    assert not deterministic_cpu() and not fast_compiling_cpu() and "XLA_FLAGS" not in os.environ
    monkeypatch.delenv("JAXDRIVE_CPU_FLAGS")
    assert fast_compiling_cpu() and os.environ["XLA_FLAGS"] == f"{CPU_FAST_COMPILE} {CPU_SERIAL_CODEGEN}"


def test_the_tests_run_with_the_cpu_flags():
    assert CPU_DETERMINISTIC in os.environ["XLA_FLAGS"]
    assert CPU_FAST_COMPILE in os.environ["XLA_FLAGS"] and CPU_SERIAL_CODEGEN in os.environ["XLA_FLAGS"]


@pytest.mark.optimized_xla
def test_an_optimized_test_starts_processes_with_the_newer_fusion_emitters():
    """What an ``optimized_xla`` test launches runs its kernels fast: full optimisation, the MLIR
    fusion emitters, and still the same numbers on every call."""
    flags = os.environ["XLA_FLAGS"].split()
    assert CPU_FAST_COMPILE not in flags and CPU_DETERMINISTIC in flags
    assert os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"] == "0"


@pytest.mark.slow(seconds=3)
def test_a_compiled_train_loss_is_the_same_on_every_call(tmp_path):
    """The tiny config's loss, one jitted program called 24 times on the same inputs: with the
    YNNPACK fusions on, about 1 call in 30 came out different (up to 40%) on 2 cores."""
    write_synthetic(tmp_path / "clips")
    run = Run(
        load_config(
            TINY,
            [
                f"data.path={tmp_path / 'clips'}",
                "data.views=2",
                "data.frames=5",
                "model.depth=1",
                "mesh.data=1",
                "mesh.seq=1",
            ],
        ),
        devices=jax.devices()[:1],
    )
    inputs = model_inputs(next(iter(run.dataset())), run.training.model)
    params = run.training.dit.init_params(0, batch=1, views=2, frames=5, height=8, width=14)
    loss = jax.jit(lambda p, inp, k: flow_step.flow_loss_fn(run.training, p, None, inp, k)[0])
    values = [np.asarray(loss(params, inputs, jax.random.key(3))) for _ in range(24)]
    assert all(v == values[0] for v in values), sorted(set(map(float, values)))
