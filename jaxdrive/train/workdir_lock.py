"""A lock on a training run's directory, so that two runs never write one ``workdir``.

    with workdir_lock("runs/tiny") as path:   # runs/tiny/.lock, removed on the way out
        ...
    with job_workdir_lock("runs/tiny"):       # a JAX job: process 0 holds it for every process
        ...

:func:`jaxdrive.train.run.train` holds :func:`job_workdir_lock` from the moment its config is
checked to the end of its last checkpoint's write. The lock is the file ``WORKDIR/.lock``, made
with ``os.open(O_CREAT | O_EXCL)`` (one of two processes racing for it wins), holding JSON with the
holder's ``pid``, ``host`` and ``started`` (ISO 8601, UTC). A process that finds the file:

- held by a live process on this host (``os.kill(pid, 0)`` succeeds): refuses
  (:class:`WorkdirLocked`, naming the holder's process id and host and the lock file);
- held by a process of this host that is gone (``ProcessLookupError``: a SIGKILLed run, a lost
  host's relaunch): takes it over, logging a WARNING that names the dead pid;
- held by another host: refuses, since no process of this host can check it; the message says to
  delete the file if that run is gone;
- held by this very process (the pid is ours): refuses when a context of this process holds it
  now (a ``train()`` of the workdir inside another one's ``on_step``, or in a second thread), and
  otherwise takes it over with a WARNING: no context of ours holds it, so no run of ours writes the
  directory, and its writer was an earlier process whose pid ours reuses. So one process may train
  in one workdir any number of times one after the other (a resume test);
- not a lock (not JSON, no pid or host; e.g. empty, from a process killed between creating and
  writing it): refuses, naming the file and saying to delete it.

The lock is removed on the way out of the context, an exception's included, and only when it
still holds what this process wrote. A run stopped by SIGTERM / SIGINT in its loop returns
normally (:class:`jaxdrive.train.common.Stop`) and so removes it; a SIGKILL, or a SIGTERM before the
loop (while compiling: Python's default handler ends the process), leaves it behind, for the next
run of this host to take over. A pid reused by an unrelated live process makes a stale lock look
held: the refusal says to delete the file if the holder is not a run.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import logging
import os
import socket
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

logger = logging.getLogger(__name__)

LOCK_FILE = ".lock"
_TRIES = 3  # a lock taken over can be re-taken by a racing process before this one makes its own
_PARTIAL_WAIT = 1.0  # seconds an empty or partial lock gets to be written by the process that made it

# the lock files (real paths) that an active context of this process holds, with the text it wrote
_held: dict[str, str] = {}
_held_guard = threading.Lock()


class WorkdirLocked(ValueError):
    """The run's ``workdir`` is locked by another run, or holds a damaged lock. A ``ValueError``
    (its message begins ``workdir:``) rather than a ``RuntimeError``: the argument is what the
    caller changes (another directory, or the lock removed once its run is gone), and the command
    line reports a ``ValueError`` as one line naming ``--workdir`` (exit code 2), not a traceback."""


def _record() -> dict:
    started = datetime.datetime.now(datetime.UTC).isoformat(timespec="microseconds")
    return {"pid": os.getpid(), "host": socket.gethostname(), "started": started, "token": uuid.uuid4().hex}


def _create(path: Path) -> str:
    """Make ``path`` holding this process's record, or ``FileExistsError``; returns its text."""
    text = json.dumps(_record())
    fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
    except BaseException:
        path.unlink(missing_ok=True)
        raise
    return text


def _parse(text: str) -> dict | None:
    try:
        holder = json.loads(text)
    except json.JSONDecodeError:
        return None
    ok = isinstance(holder, dict) and isinstance(holder.get("pid"), int) and isinstance(holder.get("host"), str)
    return holder if ok else None


def _read(path: Path) -> tuple[str, dict] | None:
    """``(text, holder)`` of the lock at ``path``; None when it is gone. A lock that is not one
    after :data:`_PARTIAL_WAIT` seconds (its maker writes right after creating it) is refused."""
    deadline = time.monotonic() + _PARTIAL_WAIT
    while True:
        try:
            text = path.read_text()
        except FileNotFoundError:
            return None
        holder = _parse(text)
        if holder is not None:
            return text, holder
        if time.monotonic() > deadline:
            raise WorkdirLocked(
                f"workdir: expected {path} to be a jaxdrive lock (JSON with the holder's pid and host), got "
                f"{text[:80]!r}; if no run uses {path.parent}, delete {path} and run again"
            )
        time.sleep(0.05)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def _held_message(path: Path, holder: dict) -> str:
    pid, host, since = holder["pid"], holder["host"], holder.get("started", "?")
    return (
        f"workdir: expected a directory no other run is using, got {path.parent}, locked by process {pid} "
        f"on host {host} since {since} (lock file {path})"
    )


def _check(path: Path, holder: dict) -> str:
    """Raise :class:`WorkdirLocked` unless the holder of ``path`` is a gone process of this host;
    returns why it is gone."""
    pid, host = holder["pid"], holder["host"]
    if host != socket.gethostname():
        raise WorkdirLocked(
            f"{_held_message(path, holder)}; this host ({socket.gethostname()}) cannot check whether that "
            f"process still runs: if it is gone, delete {path} and run again"
        )
    if pid == os.getpid():
        if os.path.realpath(path) in _held:
            raise WorkdirLocked(f"{_held_message(path, holder)}: this process, which is running in it already")
        return "no longer runs (its id is this process's, in which no run holds the lock)"
    if _alive(pid):
        raise WorkdirLocked(
            f"{_held_message(path, holder)}; wait for it to end, or stop it; if process {pid} is not a run "
            f"(its id reused), delete {path} and run again"
        )
    return "no longer runs"


def _take_over(path: Path, text: str, holder: dict, gone: str) -> None:
    """Remove the stale lock ``path`` if it still holds ``text``: moved aside first (a rename is
    atomic), so of two processes taking it over one moves it, and one that moved a fresh lock
    instead (the other's, made in between) puts it back."""
    aside = path.with_name(f"{path.name}.stale-{uuid.uuid4().hex}")
    try:
        os.rename(path, aside)
    except FileNotFoundError:  # the other one moved it first
        return
    if aside.read_text() != text:
        with contextlib.suppress(FileExistsError):  # a third one locked it meanwhile: that one holds it
            os.link(aside, path)
        aside.unlink()
        return
    aside.unlink()
    logger.warning(
        "taking over the lock %s of process %d on %s (started %s), which %s",
        path,
        holder["pid"],
        holder["host"],
        holder.get("started", "?"),
        gone,
    )


def _acquire(path: Path) -> str:
    """Lock ``path`` (see the module docstring); returns the text written."""
    for _ in range(_TRIES):
        try:
            return _create(path)
        except FileExistsError:
            pass
        found = _read(path)
        if found is not None:
            _take_over(path, *found, _check(path, found[1]))
    raise WorkdirLocked(
        f"workdir: expected to lock {path}, got it taken by other processes {_TRIES} times in a row; run again"
    )


def _release(path: Path, key: str) -> None:
    """Remove ``path`` if it holds what this process wrote; a warning if it does not."""
    written = _held.pop(key)
    try:
        if path.read_text() == written:
            path.unlink()
            return
        how = "replaced by another process's"
    except FileNotFoundError:
        how = "removed"
    except OSError as e:  # not raised: it would hide the exception that ends the run, if any
        how = f"made unreadable ({e})"
    logger.warning("the lock %s was %s while this process held it; left as it is", path, how)


@contextlib.contextmanager
def workdir_lock(workdir) -> Iterator[Path]:
    """Hold ``WORKDIR/.lock`` (made, with ``workdir``, when absent) for the context; yields its
    path. :class:`WorkdirLocked` when another run holds it (see the module docstring)."""
    path = Path(workdir) / LOCK_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    key = os.path.realpath(path)
    with _held_guard:
        _held[key] = _acquire(path)
    try:
        yield path
    finally:
        with _held_guard:
            _release(path, key)


@contextlib.contextmanager
def job_workdir_lock(workdir) -> Iterator[Path | None]:
    """:func:`workdir_lock` for a JAX job: process 0 holds it (yields its path, the others None)
    and the other processes do not touch it. Every process learns whether process 0 got it (one
    host all-gather; none with one process), so a refused lock stops them all at once rather than
    after a collective's timeout."""
    from jaxdrive.parallel import Processes  # here: the lock alone needs no JAX (a checking process starts fast)

    procs = Processes()
    with contextlib.ExitStack() as stack:
        path, error = None, None
        if procs.index == 0:
            try:
                path = stack.enter_context(workdir_lock(workdir))
            except Exception as e:  # WorkdirLocked, or an OSError (a read-only file system)
                error = e
        if procs.gather(int(error is not None))[0]:
            raise error or WorkdirLocked(
                f"workdir: expected process 0 to lock {Path(workdir) / LOCK_FILE} for this job, got a refusal "
                "(process 0's error says why)"
            )
        yield path
