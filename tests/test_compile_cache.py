"""JAX's persistent compilation cache (``jaxdrive.compile_cache``): on by default, a second run
reads its compiled train step from it, and ``train.compile_cache`` moves or disables it."""

from __future__ import annotations

from pathlib import Path

import jax
import pytest

from jaxdrive import compile_cache
from jaxdrive.config import load_config

from train_fixtures import MACHINERY

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def restore_cache():
    previous = jax.config.jax_compilation_cache_dir
    yield
    compile_cache.enable(previous or "off")


@pytest.mark.slow(seconds=27)
def test_a_second_run_reads_its_compiled_step_from_the_cache(clips21, tmp_path, restore_cache):
    from jaxdrive.train.run import train

    folder = tmp_path / "xla"
    config = load_config(
        ROOT / "configs" / "tiny.py",
        [
            f"data.path={clips21}",
            "data.views=2",
            "data.frames=5",
            "model.depth=1",
            *MACHINERY,
            "train.steps=1",
            "train.checkpoint_every=0",
            "mesh.data=2",
            "mesh.seq=4",
            f"train.compile_cache={folder}",
        ],
    )
    first = train(config, tmp_path / "a", progress=False)
    second = train(config, tmp_path / "b", progress=False)
    assert first["compile_cache"]["folder"] == str(folder) and first["compile_cache"]["hits"] == 0
    assert first["compile_cache"]["requests"] >= 1 and any(folder.iterdir())  # the step was written
    assert second["compile_cache"]["hits"] >= 1, second["compile_cache"]  # ... and read back
    assert second["compile_cache"]["saved_seconds"] > 0 and second["first_step_seconds"] > 0
    assert second["loss"] == first["loss"]  # the same program


def test_the_cache_setting_moves_keeps_or_disables_it(tmp_path, restore_cache, monkeypatch):
    jax.config.update("jax_compilation_cache_dir", str(tmp_path / "users"))
    assert compile_cache.enable("default") == tmp_path / "users"  # a folder the user gave JAX wins
    assert compile_cache.enable(str(tmp_path / "mine")) == tmp_path / "mine"
    assert jax.config.jax_compilation_cache_dir == str(tmp_path / "mine") and jax.config.jax_enable_compilation_cache
    assert compile_cache.enable("off") is None and not jax.config.jax_enable_compilation_cache
    monkeypatch.setenv("JAXDRIVE_CACHE_DIR", str(tmp_path / "env"))
    assert compile_cache.default_dir() == tmp_path / "env" / "xla"
    monkeypatch.delenv("JAXDRIVE_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert compile_cache.default_dir() == tmp_path / "xdg" / "jaxdrive" / "xla"
    (tmp_path / "file").write_text("")
    with pytest.raises(ValueError, match="train.compile_cache: expected a folder that can be created, got"):
        compile_cache.enable(str(tmp_path / "file" / "cache"))
    with pytest.raises(ValueError, match="train.compile_cache: expected 'default', 'off' or a folder, got 3"):
        compile_cache.enable(3)
