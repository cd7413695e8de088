"""Where a run reports: ``DIR/metrics.jsonl`` (one JSON object per logged step, at least ``step``
and ``loss``), TensorBoard event files under ``DIR/tensorboard`` and the progress, with step/s,
loss, tokens/s and the ETA: a tqdm bar when stderr is a terminal, else one line per logged step
(``step 50/600  loss 0.05217  0.823 step/s  ETA 11:09``, :mod:`jaxdrive.progress`). Only process 0
writes."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import jax

from jaxdrive.progress import Progress


def _summary_writer(logdir: Path):
    """tensorboardX's ``SummaryWriter``, imported without PyTorch. tensorboardX imports ``torch``
    whenever it is installed, only to accept torch tensors where it takes NumPy arrays (1.1 s of
    a run's start on 2 CPU cores, with a CPU build; a CUDA build loads more); the writer here logs
    Python floats. A ``None`` entry in ``sys.modules`` makes ``import torch`` fail for the length
    of the import; a torch already imported is left as it is."""
    import sys

    if "tensorboardX" not in sys.modules and "torch" not in sys.modules:
        sys.modules["torch"] = None  # type: ignore[assignment]
        try:
            import tensorboardX  # noqa: F401
        finally:
            del sys.modules["torch"]
    from tensorboardX import SummaryWriter

    return SummaryWriter(str(logdir))


class MetricsWriter:
    """A run's reports (module docstring) in ``workdir``: :meth:`write` once per logged step.
    ``progress``: show the progress (on ``progress_stream``, default ``sys.stderr``: the tqdm bar
    when it is a terminal, one ``jaxdrive.progress`` log line per :meth:`write` otherwise)."""

    def __init__(
        self,
        workdir,
        *,
        total_steps: int,
        start_step: int = 0,
        tokens_per_step: int = 0,
        progress: bool = True,
        progress_stream=None,
    ):
        self.enabled = jax.process_index() == 0
        self.workdir = Path(workdir)
        self.tokens_per_step = tokens_per_step
        self._last = (time.perf_counter(), start_step)
        self._bar = self._tb = self._jsonl = None
        if not self.enabled:
            return
        self.workdir.mkdir(parents=True, exist_ok=True)
        self._jsonl = open(self.workdir / "metrics.jsonl", "a", buffering=1)
        self._tb = _summary_writer(self.workdir / "tensorboard")
        if progress:
            self._bar = Progress(
                total_steps, initial=start_step, unit="step", stream=progress_stream, dynamic_ncols=True
            )

    def write(self, step: int, metrics: dict, tokens: int | None = None) -> dict:
        """Log ``metrics`` (scalars) at ``step``; adds ``steps_per_s`` and ``tokens_per_s`` since the
        last call (``tokens``: the tokens trained since then, when steps differ in size; default
        ``tokens_per_step`` per step). Returns the row written."""
        now = time.perf_counter()
        elapsed, steps = now - self._last[0], step - self._last[1]
        self._last = (now, step)
        row = {"step": int(step), **{k: _scalar(v) for k, v in metrics.items()}}
        if steps > 0 and elapsed > 0:
            row["steps_per_s"] = steps / elapsed
            row["tokens_per_s"] = (steps * self.tokens_per_step if tokens is None else tokens) / elapsed
        if not self.enabled:
            return row
        self._jsonl.write(json.dumps(row) + "\n")
        for key, value in row.items():
            if key != "step" and isinstance(value, float) and math.isfinite(value):
                self._tb.add_scalar(key, value, step)
        if self._bar is not None:
            self._bar.update_to(step, _shown(row, terminal=self._bar.terminal))
        return row

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
        if self._tb is not None:
            self._tb.close()
        if self._jsonl is not None:
            self._jsonl.close()


def _shown(row: dict, *, terminal: bool) -> dict:
    """What the progress shows of ``row``: on the bar loss, steps_per_s and tokens_per_s, as
    before; a plain line has its own step/s (:class:`jaxdrive.progress.Progress`), so it shows
    the loss and, when tokens are counted, ``tokens/s``."""
    if terminal:
        return {k: f"{row[k]:.4g}" for k in ("loss", "steps_per_s", "tokens_per_s") if k in row}
    shown = {"loss": row["loss"]} if "loss" in row else {}
    if row.get("tokens_per_s"):
        shown["tokens/s"] = row["tokens_per_s"]
    return shown


def _scalar(value):
    value = jax.device_get(value)
    try:
        return float(value)
    except TypeError:
        return value


def read_metrics(workdir) -> list[dict]:
    """The rows of ``workdir/metrics.jsonl`` (the last row per step when a resumed run re-logged)."""
    rows = {}
    path = Path(workdir) / "metrics.jsonl"
    if path.exists():
        for line in path.read_text().splitlines():
            if line.strip():
                row = json.loads(line)
                rows[row["step"]] = row
    return [rows[k] for k in sorted(rows)]
