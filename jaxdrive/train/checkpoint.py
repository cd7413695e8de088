"""Checkpoints of a run: orbax, asynchronous, keep-N, with the data iterator's state alongside.

``Checkpoints(workdir)`` manages ``workdir/checkpoints/<step>/`` with three items: ``state`` (the
:class:`jaxdrive.train.state.TrainState`), ``data`` (the grain iterator state, JSON) and ``meta``
(step, config, time). Orbax writes each checkpoint into a temporary directory and commits it
by rename, so a crash mid-save leaves the previous checkpoints intact.

On a CPU backend each array is written from one replica: orbax's replica-parallel save (its
default off GPUs) slices a replicated array into one piece per device, which on fake CPU devices
sharing one host's memory saves nothing and compiles one slice program per parameter shape (232
of the 308 programs of the MiLA recipe's test, and most of its checkpoint time). The files are
the same format either way; either restores the other.

Restoring takes an abstract state whose leaves carry the target shardings, so a run can resume
on a different mesh shape. When the newest checkpoint cannot be read (a partial copy, a damaged
file), :meth:`Checkpoints.restore_latest` logs a warning that says which one and why, and falls
back to the one before it.
"""

from __future__ import annotations

import logging
from pathlib import Path

import orbax.checkpoint as ocp

logger = logging.getLogger(__name__)


class Checkpoints:
    """The checkpoints under ``workdir``; ``option`` is how the caller names ``workdir`` in errors
    (``train.init_from`` for a run it starts from, ``fine_workdir`` for a sampler's fine model)."""

    def __init__(self, workdir, *, keep: int = 3, asynchronous: bool = True, option: str = "workdir"):
        self.directory = Path(workdir).absolute() / "checkpoints"
        self.option = option
        options = ocp.CheckpointManagerOptions(max_to_keep=keep, create=True, enable_async_checkpointing=asynchronous)
        self.manager = ocp.CheckpointManager(
            self.directory,
            options=options,
            item_handlers={
                "state": _state_handler(),
                "data": ocp.JsonCheckpointHandler(),
                "meta": ocp.JsonCheckpointHandler(),
            },
        )
        self.skipped: list[str] = []  # why restore_latest's last call passed over each checkpoint it skipped

    def steps(self) -> list[int]:
        return sorted(self.manager.all_steps())

    def save(self, step: int, state, data_state: dict | None, meta: dict) -> None:
        """Start saving (asynchronously); a step saved already is left as it is."""
        if step in self.manager.all_steps():
            return
        self.manager.save(
            step,
            args=ocp.args.Composite(
                state=ocp.args.PyTreeSave(state),
                data=ocp.args.JsonSave(data_state or {}),
                meta=ocp.args.JsonSave(meta),
            ),
            force=True,
        )

    def wait(self) -> None:
        self.manager.wait_until_finished()

    def restore(self, step: int, abstract_state, *, fields: tuple[str, ...] | None = None):
        """``(state, data_state, meta)`` of checkpoint ``step``, placed as ``abstract_state`` says.
        ``fields``: read only these fields of the state (e.g. ``("ema",)``); the state is then a
        dict of them, and the other arrays are not read from disk."""
        if fields is not None:
            abstract_state = {name: getattr(abstract_state, name) for name in fields}
        out = self.manager.restore(
            step,
            args=ocp.args.Composite(
                state=ocp.args.PyTreeRestore(
                    abstract_state,
                    restore_args=ocp.checkpoint_utils.construct_restore_args(abstract_state),
                    partial_restore=fields is not None,
                ),
                data=ocp.args.JsonRestore(),
                meta=ocp.args.JsonRestore(),
            ),
        )
        return out["state"], out["data"], out["meta"]

    def parameter_differences(self, step: int, params) -> list[str]:
        """How the parameters saved at ``step`` differ from ``params`` (a tree of arrays or
        shape structs): one line per parameter missing, extra or of another shape; empty when they
        match. Raises whatever orbax raises when the checkpoint's metadata cannot be read."""
        import jax
        from etils import epath

        tree = ocp.StandardCheckpointHandler().metadata(epath.Path(self.directory / str(step) / "state"))
        saved = getattr(tree, "tree", tree)["params"]
        shapes = lambda t: {
            jax.tree_util.keystr(p, simple=True, separator="/"): tuple(x.shape)
            for p, x in jax.tree_util.tree_flatten_with_path(t)[0]
        }
        have, want = shapes(saved), shapes(params)
        lines = [
            f"{k}: expected shape {list(want[k])}, got {list(have[k])}"
            for k in sorted(want.keys() & have.keys())
            if want[k] != have[k]
        ]
        lines += [f"{k}: expected in the checkpoint, missing" for k in sorted(want.keys() - have.keys())]
        lines += [f"{k}: in the checkpoint, not in this model" for k in sorted(have.keys() - want.keys())]
        return lines

    def restore_latest(self, abstract_state, *, fields: tuple[str, ...] | None = None):
        """The newest readable checkpoint as ``(step, state, data_state, meta)``, or None when
        there is none. Unreadable newer ones (a truncated array file, a missing metadata file, an
        empty step folder) are skipped, each with a warning in the log and its message in
        ``skipped``. A readable checkpoint of another model (parameter names or shapes differ) is a
        ``ValueError`` saying what differs, not something to fall back past: the workdir belongs to
        another config. ``fields``: as :meth:`restore`."""
        self.skipped = []
        for step in reversed(self.steps()):
            try:
                differences = self.parameter_differences(step, abstract_state.params)
            except Exception as e:  # orbax raises many types for unreadable metadata
                self._damaged(step, e)
                continue
            if differences:
                raise ValueError(
                    f"{self.option}: expected checkpoints of this config's model in {self.directory}, got "
                    f"step {step} with other parameters ({len(differences)} differ: "
                    f"{'; '.join(differences[:4])}); use a new {self.option} or the config it was "
                    f"trained with"
                )
            try:
                return (step, *self.restore(step, abstract_state, fields=fields))
            except Exception as e:  # orbax raises many types for a damaged checkpoint
                self._damaged(step, e)
        return None

    def restore_latest_weights(self, abstract_state, *, ema: bool = True):
        """``(step, params)`` of the newest readable checkpoint (as :meth:`restore_latest`), or None:
        the EMA when ``ema`` and the state keeps one, else the parameters. Only that tree is read:
        a sampler, or a run that starts from these weights (``train.init_from``), needs neither
        the other copy nor the optimizer's moments, three quarters of an AdamW state with an EMA."""
        name = "ema" if ema and abstract_state.ema is not None else "params"
        restored = self.restore_latest(abstract_state, fields=(name,))
        return None if restored is None else (restored[0], restored[1][name])

    def _damaged(self, step: int, error: Exception) -> None:
        self.skipped.append(
            f"checkpoint {self.directory / str(step)} is incomplete or damaged "
            f"({type(error).__name__}: {str(error)[:200]}); using the one before it"
        )
        logger.warning("%s", self.skipped[-1])

    def close(self) -> None:
        self.manager.wait_until_finished()
        self.manager.close()


def _state_handler() -> ocp.PyTreeCheckpointHandler:
    """The train state's handler: orbax's defaults, except on a CPU backend, where arrays are
    written without replica-parallel slicing (module docstring)."""
    import jax
    import numpy as np

    if jax.default_backend() != "cpu":
        return ocp.PyTreeCheckpointHandler()
    th = ocp.type_handlers
    registry = th.create_type_handler_registry(
        (int, th.ScalarHandler()),
        (float, th.ScalarHandler()),
        (bytes, th.ScalarHandler()),
        (np.number, th.ScalarHandler()),
        (np.ndarray, th.NumpyHandler()),
        (jax.Array, th.ArrayHandler(use_replica_parallel=False)),
        (str, th.StringHandler()),
    )
    return ocp.PyTreeCheckpointHandler(type_handler_registry=registry)
