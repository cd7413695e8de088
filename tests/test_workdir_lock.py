"""The lock on a run's directory (``jaxdrive.train.workdir_lock``): a second process is refused
with the holder's pid and host, a dead process's lock is taken over with a warning, a lock of
another host or a damaged one is refused naming the file, the lock goes on the way out (an
exception's included), and ``train()`` holds it while it steps."""

import json
import logging
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from jaxdrive.train import workdir_lock as wl
from jaxdrive.train.workdir_lock import LOCK_FILE, WorkdirLocked, workdir_lock

from train_fixtures import MACHINERY, write_synthetic

ROOT = Path(__file__).resolve().parents[1]
HOST = socket.gethostname()

# A second process locking the workdir: the module loaded by its path (it needs no JAX, so the
# process starts in a tenth of a second); exit code 3 and the message when refused.
CHILD = """
import importlib.util, sys
spec = importlib.util.spec_from_file_location("workdir_lock", sys.argv[1])
wl = importlib.util.module_from_spec(spec)
spec.loader.exec_module(wl)
try:
    with wl.workdir_lock(sys.argv[2]):
        pass
except wl.WorkdirLocked as e:
    print(e)
    sys.exit(3)
"""


def lock_in_another_process(workdir) -> subprocess.CompletedProcess:
    module = ROOT / "jaxdrive" / "train" / "workdir_lock.py"
    return subprocess.run(
        [sys.executable, "-c", CHILD, str(module), str(workdir)], capture_output=True, text=True, timeout=60
    )


def dead_pid() -> int:
    """The id of a process of this host that has ended (and been reaped)."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait(timeout=60)
    with pytest.raises(ProcessLookupError):
        os.kill(proc.pid, 0)
    return proc.pid


def write_lock(workdir, text) -> Path:
    path = Path(workdir) / LOCK_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text if isinstance(text, str) else json.dumps(text))
    return path


def warnings(caplog) -> list[str]:
    """The lock's warnings (a run also logs others, e.g. a sharding fallback)."""
    return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING and r.name == wl.__name__]


def test_a_second_process_is_refused_with_the_holders_pid_and_host(tmp_path):
    workdir = tmp_path / "run"
    with workdir_lock(workdir) as path:
        assert path == workdir / LOCK_FILE
        holder = json.loads(path.read_text())
        assert (holder["pid"], holder["host"]) == (os.getpid(), HOST) and "started" in holder
        refused = lock_in_another_process(workdir)
        assert refused.returncode == 3, refused.stderr
        message = refused.stdout
        assert message.startswith("workdir: expected a directory no other run is using")
        assert f"locked by process {os.getpid()} on host {HOST}" in message and f"(lock file {path})" in message
        assert json.loads(path.read_text()) == holder  # the refused process left it alone
    assert not path.exists()
    taken = lock_in_another_process(workdir)  # released: the other process gets it, and releases it
    assert taken.returncode == 0, taken.stdout + taken.stderr
    assert list(workdir.iterdir()) == []


def test_a_dead_processs_lock_is_taken_over_with_a_warning(tmp_path, caplog):
    pid = dead_pid()
    path = write_lock(tmp_path, {"pid": pid, "host": HOST, "started": "2024-01-01T00:00:00+00:00"})
    with caplog.at_level(logging.WARNING, logger="jaxdrive.train.workdir_lock"), workdir_lock(tmp_path):
        assert json.loads(path.read_text())["pid"] == os.getpid()
    assert warnings(caplog) == [
        f"taking over the lock {path} of process {pid} on {HOST} (started 2024-01-01T00:00:00+00:00), "
        "which no longer runs"
    ]
    assert list(tmp_path.iterdir()) == []  # nothing moved aside is left behind


def test_a_lock_of_this_pid_that_no_context_holds_is_taken_over_one_that_is_held_is_refused(tmp_path, caplog):
    """An earlier process with this process's id left it: taken over. One of this process's live
    contexts holds it (also under another spelling of the path): refused."""
    path = write_lock(tmp_path, {"pid": os.getpid(), "host": HOST})
    with caplog.at_level(logging.WARNING, logger="jaxdrive.train.workdir_lock"), workdir_lock(tmp_path):
        with pytest.raises(WorkdirLocked, match=f"locked by process {os.getpid()} .*: this process, which is running"):
            with workdir_lock(tmp_path / "." / ".." / tmp_path.name):
                pass
        assert path.exists()  # the refused inner call did not release the outer one's lock
    assert not path.exists()
    assert len(warnings(caplog)) == 1 and f"of process {os.getpid()} on {HOST}" in warnings(caplog)[0]
    with workdir_lock(tmp_path), pytest.raises(RuntimeError, match="boom"):  # one after the other: fine
        raise RuntimeError("boom")
    assert not path.exists()  # released on the way out of an exception too


def test_another_hosts_lock_is_refused_saying_how_to_remove_it(tmp_path):
    holder = {"pid": 1234, "host": "elsewhere", "started": "then"}
    path = write_lock(tmp_path, holder)
    with pytest.raises(WorkdirLocked) as e:
        with workdir_lock(tmp_path):
            pass
    message = str(e.value)
    assert f"locked by process 1234 on host elsewhere since then (lock file {path})" in message
    assert f"this host ({HOST}) cannot check" in message and f"if it is gone, delete {path}" in message
    assert json.loads(path.read_text()) == holder


def test_a_live_process_of_this_host_is_refused(tmp_path):
    """The parent of this process (pytest's launcher, or a shell) certainly runs."""
    path = write_lock(tmp_path, {"pid": os.getppid(), "host": HOST})
    with pytest.raises(WorkdirLocked, match=f"locked by process {os.getppid()} on host {HOST} .*wait for it to end"):
        with workdir_lock(tmp_path):
            pass
    assert path.exists()


@pytest.mark.parametrize("text", ["", "not json", "[1, 2]", '{"pid": "12", "host": "h"}', '{"host": "h"}'])
def test_a_damaged_lock_is_refused_naming_the_file(tmp_path, monkeypatch, text):
    monkeypatch.setattr(wl, "_PARTIAL_WAIT", 0.0)  # no maker is writing it
    path = write_lock(tmp_path, text)
    with pytest.raises(WorkdirLocked, match="workdir: expected .* to be a jaxdrive lock") as e:
        with workdir_lock(tmp_path):
            pass
    assert str(path) in str(e.value) and f"delete {path}" in str(e.value) and repr(text) in str(e.value)
    assert path.read_text() == text


@pytest.mark.parametrize("how", ["removed", "replaced"])
def test_a_lock_changed_under_its_holder_is_left_with_a_warning(tmp_path, caplog, how):
    other = {"pid": 99, "host": "elsewhere"}
    with caplog.at_level(logging.WARNING, logger="jaxdrive.train.workdir_lock"), workdir_lock(tmp_path) as path:
        path.unlink() if how == "removed" else path.write_text(json.dumps(other))
    said = {"removed": "removed", "replaced": "replaced by another process's"}[how]
    assert warnings(caplog) == [f"the lock {path} was {said} while this process held it; left as it is"]
    assert (json.loads(path.read_text()) == other) if how == "replaced" else not path.exists()


@pytest.mark.slow(seconds=11)
def test_train_holds_the_lock_while_it_steps_and_takes_over_a_killed_runs(tmp_path, caplog):
    from jaxdrive.config import load_config
    from jaxdrive.train.run import train

    data = write_synthetic(tmp_path / "data", train=2, frames=5)
    sets = ["data.views=2", "data.frames=5", "data.batch_size=2", "model.depth=1", "mesh.data=2", "mesh.seq=4"]
    sets += [f"data.path={data}", "train.steps=1", "train.checkpoint_every=0", *MACHINERY]
    cfg = load_config(ROOT / "configs" / "tiny.py", sets)
    workdir = tmp_path / "run"
    path = write_lock(workdir, {"pid": dead_pid(), "host": HOST})  # a SIGKILLed run's
    seen = []

    def on_step(step, metrics):
        seen.append(json.loads(path.read_text())["pid"])

    with caplog.at_level(logging.WARNING, logger="jaxdrive.train.workdir_lock"):
        out = train(cfg, workdir, progress=False, on_step=on_step)
    assert out["status"] == "done" and seen == [os.getpid()] and not path.exists()
    assert len(warnings(caplog)) == 1 and warnings(caplog)[0].startswith(f"taking over the lock {path}")
    with workdir_lock(workdir), pytest.raises(WorkdirLocked, match="this process, which is running in it"):
        train(cfg, workdir, progress=False)  # refused before anything compiles
