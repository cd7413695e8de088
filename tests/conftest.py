"""Every test sees 8 fake CPU devices, fp32, no accelerator."""

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")
# 8 fake devices; and collective rendezvous timeouts far above XLA:CPU's defaults, because the 8
# device threads of a sharded test share 2 cores with other test workers: on a busy machine a
# thread can miss the default deadline, and XLA then aborts the process instead of waiting.
# And XLA:CPU's YNNPACK fusions off: with them a program sometimes gives other numbers on a second
# call with the same inputs (jaxdrive.xla_flags), which made exact-equality tests flaky.
from jaxdrive.xla_flags import CPU_FAST_COMPILE, add_xla_flags, deterministic_cpu, fast_compiling_cpu  # noqa: E402  (imports jax; no backend yet)

add_xla_flags(
    "--xla_force_host_platform_device_count=8",
    "--xla_cpu_collective_timeout_seconds=900",
    "--xla_cpu_collective_call_terminate_timeout_seconds=900",
)
deterministic_cpu()
# XLA:CPU's older fusion emitters: the suite's time is compiling, and with them the tiny train step
# compiles in 11 s instead of 19 (jaxdrive.xla_flags). Numbers agree within the tests' tolerances;
# exact-equality tests compare two runs compiled the same way. And each program's LLVM module
# compiled whole: splitting it for threads costs more than it gives on cores the workers fill.
fast_compiling_cpu()
# Most of XLA's optimisation off (JAX's own switch: LLVM at -O0, its expensive passes skipped):
# the tests' programs are tiny, so compiling them is most of the suite's time, and -O0 halves it
# (the all-controls DiT test: 26 -> 14 s). A test whose time goes into running programs, not
# compiling them, takes it back with @pytest.mark.optimized_xla. Numbers agree within the tests'
# tolerances; exact-equality tests compare two runs compiled the same way. The subprocesses the
# tests launch (the CLI, launch/local.py) inherit the variable.
os.environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")

import gc  # noqa: E402

import jax  # noqa: E402  (its backend starts after the flags above)

from jaxdrive.gc_thresholds import THRESHOLDS  # noqa: E402

# Python's cyclic collector less often, as the jaxdrive command runs it: tracing is most of the
# suite's Python time, and the default thresholds collect every 700 allocations
# (jaxdrive.gc_thresholds; the xdist workers import this file too).
gc.set_threshold(*THRESHOLDS)

jax.config.update("jax_num_cpu_devices", 8)
jax.config.update("jax_disable_most_optimizations", os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"] == "1")

from hypothesis import settings  # noqa: E402

# jit dispatch makes single examples slow to start; deadlines would flake, not find bugs.
settings.register_profile("jaxdrive", deadline=None, max_examples=60, derandomize=True)
settings.load_profile("jaxdrive")

# One persistent compilation cache for the whole test run: the xdist workers (started after the
# controller imported this file, so they inherit the variable) and the subprocesses they launch
# (the jaxdrive CLI, launch/local.py) read and write one folder, so a program that several tests
# build (the tiny DiT's sampler, a recipe's train step) compiles once per run, not once per process.
# Numbers are the same either way; the cache only skips XLA's work. A size limit turns on JAX's
# file lock around each entry, so a worker never reads an entry another is still writing.
import contextlib  # noqa: E402
import tempfile  # noqa: E402

_owns_cache = not os.environ.get("JAXDRIVE_TEST_XLA_CACHE")  # the controller (or a run without xdist)
_cache = os.environ.get("JAXDRIVE_TEST_XLA_CACHE") or tempfile.mkdtemp(prefix="jaxdrive-xla-cache-")
os.environ["JAXDRIVE_TEST_XLA_CACHE"] = _cache
jax.config.update("jax_compilation_cache_dir", _cache)
os.environ.setdefault("JAXDRIVE_CACHE_DIR", _cache)  # subprocesses (jaxdrive CLI, launch/local.py) too, not ~/.cache
jax.config.update("jax_compilation_cache_max_size", 64 << 30)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


import pytest  # noqa: E402

# Session fixtures that train a model: a test that asks for one is slow (-m "not slow" skips it).
TRAINED_FIXTURES = {"tiny_dit", "tiny_warp_dit", "segmenter_run", "never_killed"}


def pytest_collection_modifyitems(config, items):
    """Tests that use a trained fixture are marked slow. The run keeps the files' order: sorting the
    longest tests first under xdist's ``worksteal`` made it longer (2 cores, same tests: 46 min and
    5369 worker-seconds against 43 min and 5088; CI 2162 -> 2721 s), the heavy multi-threaded tests
    then running side by side instead of beside light ones."""
    for item in items:
        if TRAINED_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.slow)


@pytest.fixture(autouse=True)
def _optimized_xla(request, monkeypatch):
    """``@pytest.mark.optimized_xla``: the test (and the processes it starts) compiles with XLA's
    full optimisation."""
    if request.node.get_closest_marker("optimized_xla") is None:
        yield
        return
    with optimized_xla():
        for name, value in optimized_env().items():
            monkeypatch.setenv(name, value)
        yield


def optimized_env() -> dict[str, str]:
    """The variables that make a new process compile with XLA's full optimisation and XLA:CPU's
    newer fusion emitters, whose kernels run faster (the segmenter's 300 steps: 97 s against 122)."""
    flags = [f for f in os.environ["XLA_FLAGS"].split() if f != CPU_FAST_COMPILE]
    return {"JAX_DISABLE_MOST_OPTIMIZATIONS": "0", "XLA_FLAGS": " ".join(flags)}


@contextlib.contextmanager
def optimized_xla():
    """In this context this process compiles with XLA's full optimisation (the fusion emitters stay
    the older ones: XLA reads its flags once per process; :func:`optimized_env` starts one that
    has both)."""
    before = jax.config.read("jax_disable_most_optimizations")
    jax.config.update("jax_disable_most_optimizations", False)
    try:
        yield
    finally:
        jax.config.update("jax_disable_most_optimizations", before)


# A worker that crashes gets its test run once more (tests/crash_rerun.py says why).
pytest_plugins = ["crash_rerun", "pytester"]


def pytest_unconfigure(config):
    """The process that made the run's cache folder removes it at the end (it holds gigabytes)."""
    if _owns_cache:
        import shutil

        shutil.rmtree(_cache, ignore_errors=True)


def shared(tmp_path_factory, name: str, build):
    """``build(folder)`` once for the whole test run, also across xdist workers: the first worker
    to ask builds it in the run's shared temporary folder under a file lock, the others wait and
    reuse it (a session fixture alone is built once per worker). Returns the folder."""
    from filelock import FileLock

    if os.environ.get("PYTEST_XDIST_WORKER") is None:
        folder = tmp_path_factory.mktemp(name)
        build(folder)
        return folder
    root = tmp_path_factory.getbasetemp().parent  # one per run, shared by its workers
    folder = root / name
    with FileLock(str(root / f"{name}.lock")):
        if not (folder / ".built").exists():
            import shutil

            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            build(folder)
            (folder / ".built").touch()
    return folder


@pytest.fixture(scope="session")
def clips21(tmp_path_factory):
    """2 training scenes and 1 validation scene of 21 frames, 6 views (a session's shared data)."""
    from train_fixtures import write_synthetic

    return (
        shared(
            tmp_path_factory, "clips21", lambda folder: write_synthetic(folder / "data", train=2, frames=21, views=6)
        )
        / "data"
    )


@pytest.fixture(scope="session")
def tiny_dit(clips21, tmp_path_factory):
    """A tiny 6-view DiT trained 1 step on ``clips21`` (``train_fixtures.tiny_run``)."""
    from train_fixtures import tiny_run

    return shared(tmp_path_factory, "tiny_dit", lambda folder: tiny_run(folder / "run", clips21)) / "run"


@pytest.fixture(scope="session")
def tiny_warp_dit(clips21, tmp_path_factory):
    """``tiny_dit`` made warp-guided, its output a correction to the warp from the last given frame
    (configs/world.py:control=warp's controls), trained 1 step on ``clips21``."""
    from train_fixtures import tiny_run

    sets = ("model.controls.warp=true", "model.controls.reference_frame=warp", "data.warp_frame=1")
    return shared(tmp_path_factory, "tiny_warp_dit", lambda folder: tiny_run(folder / "run", clips21, *sets)) / "run"


@pytest.fixture(scope="session")
def segmenter_run(clips21, tmp_path_factory):
    """The segmentation evaluator (``configs/segmenter.py:size=test``) trained on ``clips21``."""
    import subprocess
    import sys
    from pathlib import Path

    config = Path(__file__).resolve().parents[1] / "configs" / "segmenter.py"

    def build(folder):  # 300 steps: running, not compiling, is its time, so a process optimised for it
        argv = ["train", "--config", f"{config}:size=test", "--workdir", str(folder / "run")]
        argv += ["--set", f"data.path={clips21}", "--no-progress"]
        env = {**os.environ, **optimized_env()}
        # and on one device: what it tests is the model it learns, not data parallelism, and 8 fake
        # devices on 2 cores made its steps slower (49 s against 39 s for the 300 steps)
        flags = [f for f in env["XLA_FLAGS"].split() if not f.startswith("--xla_force_host_platform_device_count=")]
        env["XLA_FLAGS"] = " ".join([*flags, "--xla_force_host_platform_device_count=1"])
        done = subprocess.run(
            [sys.executable, "-m", "jaxdrive.cli", *argv],
            env=env,
            capture_output=True,
            text=True,
        )
        assert done.returncode == 0, done.stderr[-4000:]

    return shared(tmp_path_factory, "segmenter", build) / "run"
