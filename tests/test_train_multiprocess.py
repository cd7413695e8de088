"""``jaxdrive train`` as 2 processes x 4 fake CPU devices (gloo), launched by ``launch/local.py``:
a process lost to SIGKILL (after a step, and in the middle of an asynchronous checkpoint write)
and the run relaunched gives the losses of the run that was never killed, bit for bit; a 2 x 4
checkpoint resumes on 1 x 8 and on 1 x 2 with the same losses (so 2 processes compute what 1 does);
SIGTERM to one process alone stops both at the same step with one checkpoint, and unreadable
clips skipped by each process are summed over both.

The dataset holds copies of one clip with exactly the training length and no condition drops,
so every process feeds the same samples whichever clips the data sharding gives it; what is
compared is the engine: global batches from host-local rows, the sharded step, the collectives,
the checkpoints.
"""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from jaxdrive.train.checkpoint import Checkpoints
from jaxdrive.train.metrics import read_metrics

from conftest import shared
from shard_faults import shard_files, truncate
from train_fixtures import MACHINERY, write_same_clips

ROOT = Path(__file__).resolve().parents[1]
STEPS = 6
SETS = [
    "data.views=2",
    "data.frames=5",
    "data.batch_size=2",
    "data.drop_prob=0.0",
    "model.depth=1",
    *MACHINERY,
    f"train.steps={STEPS}",
    "train.log_every=1",
    "train.checkpoint_every=2",
    "train.keep_checkpoints=10",
    "optim.warmup_steps=1",
    "mesh.data=2",
    "mesh.seq=4",
]


@pytest.fixture(scope="session")
def same_clips(tmp_path_factory):
    """One folder for the whole test run (``conftest.shared``): ``never_killed`` trains on it."""
    build = lambda folder: write_same_clips(folder / "data", seed=7, frames=5, copies=4)
    return shared(tmp_path_factory, "same_clips", build) / "data"


def launch(data, workdir, *, kill: str | None = None, processes: int = 2, devices: int = 4, sets=()):
    """``jaxdrive train`` under ``launch/local.py`` (``kill``: ``tests/fault_train.py``'s fault)."""
    train_cmd = (
        [sys.executable, str(ROOT / "tests" / "fault_train.py")] if kill else [sys.executable, "-m", "jaxdrive.cli"]
    )
    cmd = [
        sys.executable,
        str(ROOT / "launch" / "local.py"),
        "--processes",
        str(processes),
        "--cpu-devices",
        str(devices),
        "--grace",
        "5",
        "--",
        *train_cmd,
        "train",
        "--config",
        str(ROOT / "configs" / "tiny.py"),
        "--workdir",
        str(workdir),
        "--no-progress",
    ]
    for s in [f"data.path={data}", *SETS, *sets]:
        cmd += ["--set", s]
    env = dict(os.environ, JAXDRIVE_TEST_KILL=kill or "")
    return subprocess.run(cmd, capture_output=True, text=True, timeout=900, cwd=ROOT, env=env)


def output(proc) -> str:
    return proc.stdout[-6000:] + proc.stderr[-3000:]


def committed(workdir) -> list[int]:
    return Checkpoints(workdir, asynchronous=False).steps()


def resumed_from(proc) -> set[int]:
    """The steps the processes said they resumed from."""
    return {
        int(line.rsplit("(step ", 1)[1].rstrip(")"))
        for line in proc.stdout.splitlines()
        if "resuming from checkpoint" in line
    }


def losses(workdir, key="loss"):
    return [r[key] for r in read_metrics(workdir)]


@pytest.fixture(scope="session")
def never_killed(same_clips, tmp_path_factory):
    """The 2 x 4 run of ``STEPS`` steps, checkpointed every 2, that nothing interrupts: launched
    once per test run, whichever xdist workers its tests land on (``conftest.shared``)."""

    def build(folder):
        proc = launch(same_clips, folder / "run")
        assert proc.returncode == 0, output(proc)

    workdir = shared(tmp_path_factory, "never_killed", build) / "run"
    assert [r["step"] for r in read_metrics(workdir)] == list(range(1, STEPS + 1))
    return workdir


@pytest.mark.slow(seconds=134)
def test_sigkill_of_one_process_then_relaunch_is_bit_exact(same_clips, never_killed, tmp_path):
    workdir = tmp_path / "run"
    # 1. process 1 dies after step 3 (checkpoint 2 was started after step 2)
    first = launch(same_clips, workdir, kill="1:step:3")
    assert first.returncode == 137, output(first)  # 128 + SIGKILL, from the launcher
    assert "[launcher] process 1 was killed by SIGKILL; stopping the others" in first.stdout
    kept = committed(workdir)
    assert set(kept) <= {2}, kept

    # 2. relaunched; process 1 dies again as soon as checkpoint 4's asynchronous write has started
    second = launch(same_clips, workdir, kill="1:save:4")
    assert second.returncode == 137, output(second)
    assert resumed_from(second) == set(kept[-1:]), output(second)
    assert committed(workdir) == [2], "checkpoint 4 must not be committed: one process never finished it"
    assert any(p.name.startswith("4.") for p in (workdir / "checkpoints").iterdir()), (
        "expected the killed write of checkpoint 4 to have left its temporary folder"
    )

    # 3. relaunched once more: resumes from 2 and finishes; every logged loss equals the unkilled run's
    third = launch(same_clips, workdir)
    assert third.returncode == 0, output(third)
    assert resumed_from(third) == {2}, output(third)
    assert committed(workdir) == [2, 4, 6]
    assert [r["step"] for r in read_metrics(workdir)] == list(range(1, STEPS + 1))
    for key in ("loss", "grad_norm"):
        assert losses(workdir, key) == losses(never_killed, key), key  # bit for bit


@pytest.mark.slow(seconds=86)
@pytest.mark.parametrize("devices, mesh", [(8, ["mesh.data=2", "mesh.seq=4"]), (2, ["mesh.data=2", "mesh.seq=1"])])
def test_a_two_process_checkpoint_resumes_on_one_process(same_clips, never_killed, tmp_path, devices, mesh):
    workdir = tmp_path / "run"
    shutil.copytree(never_killed, workdir, ignore=shutil.ignore_patterns("tensorboard"))
    for step in (4, 6):  # as if the 2 x 4 job stopped after step 2
        shutil.rmtree(workdir / "checkpoints" / str(step))
    rows = [r for r in read_metrics(workdir) if r["step"] <= 2]
    (workdir / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    proc = launch(same_clips, workdir, processes=1, devices=devices, sets=mesh)
    assert proc.returncode == 0, output(proc)
    assert resumed_from(proc) == {2}, output(proc)
    assert [r["step"] for r in read_metrics(workdir)] == list(range(1, STEPS + 1))
    for key, rtol in (("loss", 1e-5), ("grad_norm", 1e-4)):
        np.testing.assert_allclose(losses(workdir, key)[2:], losses(never_killed, key)[2:], rtol=rtol, err_msg=key)


def _bad_records_per_process(data, steps: int, processes: int, monkeypatch) -> list[list[int]]:
    """Each process's ``bad_records`` per step, from its own shard of the pipeline the run builds
    (``Run.dataset`` with the process index and count it would see)."""
    import jax

    from jaxdrive.config import load_config
    from jaxdrive.train.run import Run

    cfg = load_config(ROOT / "configs" / "tiny.py", [f"data.path={data}", *SETS, "data.skip_bad_records=true"])
    out = []
    for p in range(processes):
        with monkeypatch.context() as m:
            m.setattr(jax, "process_index", lambda: p)
            m.setattr(jax, "process_count", lambda: processes)
            it = iter(Run(cfg).dataset())
            out.append([int(next(it)["bad_records"]) for _ in range(steps)])
    return out


@pytest.mark.slow(seconds=89)
def test_sigterm_to_one_process_stops_both_at_one_step_and_bad_records_are_summed(tmp_path, monkeypatch):
    """A scheduler preempting one host sends SIGTERM to that process only. The processes agree on
    it after the step in flight, save one checkpoint together and stop (143); the relaunch resumes
    there. Two of the four clips sit in truncated shards (data.skip_bad_records): each process
    counts the ones it replaced, and metrics.jsonl holds the sum over both, step by step, across
    the resume."""
    data = write_same_clips(tmp_path / "data", seed=7, frames=5, copies=4, shard_bytes=1)  # a clip a shard
    for shard in shard_files(data)[1:3]:
        truncate(shard)
    per_process = _bad_records_per_process(data, STEPS, 2, monkeypatch)
    assert all(sum(c) > 0 for c in per_process), per_process  # both processes meet bad clips
    workdir = tmp_path / "run"
    first = launch(data, workdir, kill="1:term:3", sets=["data.skip_bad_records=true"])
    assert first.returncode == 143, output(first)  # "interrupted", not a hang or a kill
    saved = [line for line in first.stdout.splitlines() if "signal SIGTERM: saved checkpoint" in line]
    assert sorted(line[:3] for line in saved) == ["[0]", "[1]"], output(first)  # both processes, at step 3
    assert all(line.split("saved checkpoint ")[1].startswith(str(workdir / "checkpoints" / "3")) for line in saved)
    assert committed(workdir) == [2, 3]

    second = launch(data, workdir, sets=["data.skip_bad_records=true"])
    assert second.returncode == 0, output(second)
    assert resumed_from(second) == {3}, output(second)
    rows = read_metrics(workdir)
    assert [r["step"] for r in rows] == list(range(1, STEPS + 1))
    expected = np.cumsum(np.sum(per_process, axis=0)).tolist()
    assert [r["bad_records"] for r in rows] == expected, (expected, per_process)
