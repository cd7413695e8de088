#!/usr/bin/env python3
"""Run one command as N JAX processes on this machine (a local multi-host rehearsal).

    python launch/local.py --processes 2 [--cpu-devices 4] -- jaxdrive train --config configs/tiny.py ...

Every process gets ``JAXDRIVE_COORDINATOR=localhost:PORT``, ``JAXDRIVE_NUM_PROCESSES`` and
``JAXDRIVE_PROCESS_ID``, which ``jaxdrive.parallel.initialize_distributed`` reads. With
``--cpu-devices N`` each process runs on N fake CPU devices with gloo collectives
(``JAXDRIVE_CPU_DEVICES``), which is how the tests check multi-host training on one machine.
Output lines are prefixed with the process id; the launcher exits with the first non-zero code
and stops the other processes.
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import threading


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _pump(proc, pid):
    for line in proc.stdout:
        sys.stdout.write(f"[{pid}] {line}")
        sys.stdout.flush()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--cpu-devices", type=int, default=0, help="fake CPU devices per process (0: real devices)")
    parser.add_argument("--port", type=int, default=0, help="coordinator port (0: a free one)")
    parser.add_argument("command", nargs=argparse.REMAINDER, help="-- then the command every process runs")
    args = parser.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("command: expected '-- COMMAND ...' after the options")
    if args.processes < 1:
        parser.error(f"--processes: expected an integer >= 1, got {args.processes}")
    port = args.port or _free_port()
    procs = []
    for pid in range(args.processes):
        env = dict(os.environ, JAXDRIVE_COORDINATOR=f"localhost:{port}",
                   JAXDRIVE_NUM_PROCESSES=str(args.processes), JAXDRIVE_PROCESS_ID=str(pid))
        if args.cpu_devices:
            env.update(JAXDRIVE_CPU_DEVICES=str(args.cpu_devices), JAX_PLATFORMS="cpu")
        procs.append(subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                      text=True))
    pumps = [threading.Thread(target=_pump, args=(p, i), daemon=True) for i, p in enumerate(procs)]
    for t in pumps:
        t.start()
    code = 0
    for p in procs:
        rc = p.wait()
        if rc and not code:
            code = rc
            for other in procs:
                if other.poll() is None:
                    other.terminate()
    for t in pumps:
        t.join(timeout=5)
    return code


if __name__ == "__main__":
    sys.exit(main())
