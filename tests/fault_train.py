"""``jaxdrive train`` with a fault injected, for the multi-host kill tests (run under
``launch/local.py``): ``JAXDRIVE_TEST_KILL=PROCESS:WHEN`` makes process PROCESS kill itself with
SIGKILL, as a host lost without warning: ``WHEN`` is ``step:N`` (after step N, before its
checkpoint, if any, is saved) or ``save:N`` (as soon as checkpoint N's asynchronous write has
started, before it is committed). ``term:N`` sends that process alone SIGTERM after step N, as a
scheduler preempting one host (not the whole pod) would."""

import os
import signal
import sys


def _kill_here(process: int) -> None:
    import jax

    if jax.process_index() == process:
        print(f"fault: process {process} kills itself", flush=True)
        os.kill(os.getpid(), signal.SIGKILL)


def _terminate_here(process: int) -> None:
    import jax

    if jax.process_index() == process:
        print(f"fault: process {process} gets SIGTERM", flush=True)
        os.kill(os.getpid(), signal.SIGTERM)


def main() -> int:
    process, when, n = os.environ["JAXDRIVE_TEST_KILL"].split(":")
    process, n = int(process), int(n)
    from jaxdrive.train import run

    if when in ("step", "term"):
        train, fault = run.train, _kill_here if when == "step" else _terminate_here

        def killing_train(*args, **kwargs):
            return train(*args, **kwargs, on_step=lambda step, _: step == n and fault(process))

        run.train = killing_train
    elif when == "save":
        save = run.Checkpoints.save

        def killing_save(self, step, *args, **kwargs):
            save(self, step, *args, **kwargs)
            if step == n:
                _kill_here(process)

        run.Checkpoints.save = killing_save
    else:
        raise ValueError(f"JAXDRIVE_TEST_KILL: expected PROCESS:step:N, PROCESS:save:N or PROCESS:term:N, got {when!r}")
    from jaxdrive.cli import main as cli

    return cli(sys.argv[1:])


if __name__ == "__main__":
    sys.exit(main())
