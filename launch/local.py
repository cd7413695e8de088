#!/usr/bin/env python3
"""Run one command as N JAX processes on this machine (a local multi-host rehearsal).

    python launch/local.py --processes 2 [--cpu-devices 4] -- jaxdrive train --config configs/tiny.py ...

Every process gets ``JAXDRIVE_COORDINATOR=localhost:PORT``, ``JAXDRIVE_NUM_PROCESSES`` and
``JAXDRIVE_PROCESS_ID``, which ``jaxdrive.parallel.initialize_distributed`` reads. With
``--cpu-devices N`` each process runs on N fake CPU devices with gloo collectives
(``JAXDRIVE_CPU_DEVICES``), which is how the tests check multi-host training on one machine.
Output lines are prefixed with the process id. When one process fails or is killed (a lost host),
the launcher stops the others as a pod scheduler would: SIGTERM, then SIGKILL after ``--grace``
seconds (a survivor is usually blocked in a collective with the dead process and cannot act on
SIGTERM). It exits with the first failure's code (128 + N for a process killed by signal N).
Checkpoints are committed only when every process has written its part, so relaunching the same
command resumes from the last complete one.
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import subprocess
import sys
import threading
import time


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _pump(proc, pid):
    for line in proc.stdout:
        sys.stdout.write(f"[{pid}] {line}")
        sys.stdout.flush()


def _exit_code(rc: int) -> int:
    """A Popen return code as a shell would report it (-N, killed by signal N: 128 + N)."""
    return 128 - rc if rc < 0 else rc


def _wait(procs, grace: float) -> int:
    """Wait for all processes; after the first failure stop the rest. Returns the first failure's code."""
    code = 0
    while [p.poll() for p in procs].count(None):  # poll every one: any() would stop at the first alive
        failed = [(i, p.returncode) for i, p in enumerate(procs) if p.returncode]
        if failed and not code:
            i, rc = failed[0]
            code = _exit_code(rc)
            how = f"was killed by {signal.Signals(-rc).name}" if rc < 0 else f"exited with code {rc}"
            print(f"[launcher] process {i} {how}; stopping the others", flush=True)
            _stop([p for p in procs if p.poll() is None], grace)
        time.sleep(0.1)
    if not code:
        code = next((_exit_code(p.returncode) for p in procs if p.returncode), 0)
    return code


def _stop(procs, grace: float) -> None:
    for p in procs:
        p.terminate()
    deadline = time.monotonic() + grace
    for p in procs:
        try:
            p.wait(timeout=max(deadline - time.monotonic(), 0))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--cpu-devices", type=int, default=0, help="fake CPU devices per process (0: real devices)")
    parser.add_argument("--port", type=int, default=0, help="coordinator port (0: a free one)")
    parser.add_argument(
        "--grace",
        type=float,
        default=30.0,
        help="seconds the other processes get after SIGTERM, once one has failed, before SIGKILL",
    )
    parser.add_argument("command", nargs=argparse.REMAINDER, help="-- then the command every process runs")
    args = parser.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("command: expected '-- COMMAND ...' after the options")
    if args.processes < 1:
        parser.error(f"--processes: expected an integer >= 1, got {args.processes}")
    if not args.grace >= 0:
        parser.error(f"--grace: expected seconds >= 0, got {args.grace}")
    port = args.port or _free_port()
    procs = []
    for pid in range(args.processes):
        env = dict(
            os.environ,
            JAXDRIVE_COORDINATOR=f"localhost:{port}",
            JAXDRIVE_NUM_PROCESSES=str(args.processes),
            JAXDRIVE_PROCESS_ID=str(pid),
        )
        if args.cpu_devices:
            env.update(JAXDRIVE_CPU_DEVICES=str(args.cpu_devices), JAX_PLATFORMS="cpu")
        procs.append(subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True))
    pumps = [threading.Thread(target=_pump, args=(p, i), daemon=True) for i, p in enumerate(procs)]
    for t in pumps:
        t.start()
    code = _wait(procs, args.grace)
    for t in pumps:
        t.join(timeout=5)
    return code


if __name__ == "__main__":
    sys.exit(main())
