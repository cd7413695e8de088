"""Progress (jaxdrive.progress): tqdm's bar on a terminal, one plain log line per update in a log
file, nothing with ``progress=False``; the training writer's and ``jaxdrive train``'s into a pipe."""

import io
import logging
import types
from pathlib import Path

import pytest

import jaxdrive.progress as progress_module
import jaxdrive.train.metrics as metrics_module
from jaxdrive.cli import main as cli
from jaxdrive.progress import Progress, format_interval, is_terminal
from jaxdrive.train.metrics import MetricsWriter

from train_fixtures import MACHINERY, write_synthetic

PROGRESS = "jaxdrive.progress"
ROOT = Path(__file__).resolve().parents[1]


class FakeTerminal(io.StringIO):
    def isatty(self):
        return True


class Clock:
    """The time that jaxdrive.progress and jaxdrive.train.metrics read: ``now``, which the test moves."""

    def __init__(self):
        self.now = 1000.0


@pytest.fixture
def clock(monkeypatch):
    fake, module = Clock(), types.SimpleNamespace(perf_counter=lambda: fake.now)
    monkeypatch.setattr(progress_module, "time", module)
    monkeypatch.setattr(metrics_module, "time", module)  # the writer's steps_per_s, tokens_per_s
    return fake


def lines(caplog):
    return [r.getMessage() for r in caplog.records if r.name == PROGRESS]


def test_in_a_log_each_write_is_one_plain_line_with_step_loss_rate_and_eta(tmp_path, clock, caplog):
    stream = io.StringIO()  # not a terminal
    with caplog.at_level(logging.INFO, logger="jaxdrive"):
        writer = MetricsWriter(tmp_path, total_steps=600, tokens_per_step=0, progress_stream=stream)
        for step in (50, 100, 150):
            clock.now += 60.0  # 50 steps a minute: 0.833 step/s
            writer.write(step, {"loss": 0.0521749})
        writer.close()
    got = lines(caplog)
    assert got == [
        "step 50/600  loss 0.05217  0.833 step/s  ETA 11:00",
        "step 100/600  loss 0.05217  0.833 step/s  ETA 10:00",
        "step 150/600  loss 0.05217  0.833 step/s  ETA 09:00",
    ]
    assert not any("\r" in line for line in got)
    assert stream.getvalue() == ""  # no bar drawn


def test_a_plain_line_shows_tokens_per_second_when_they_are_counted(tmp_path, clock, caplog):
    with caplog.at_level(logging.INFO, logger="jaxdrive"):
        writer = MetricsWriter(
            tmp_path, total_steps=10, start_step=4, tokens_per_step=1000, progress_stream=io.StringIO()
        )
        clock.now += 2.0
        writer.write(6, {"loss": 1.5})
        writer.close()
    assert lines(caplog) == ["step 6/10  loss 1.5  tokens/s 1000  1 step/s  ETA 00:04"]


def test_on_a_terminal_the_writer_draws_tqdm_and_logs_no_lines(tmp_path, caplog):
    stream = FakeTerminal()
    with caplog.at_level(logging.INFO, logger="jaxdrive"):
        writer = MetricsWriter(tmp_path, total_steps=6, progress_stream=stream)
        for step in (2, 4, 6):
            writer.write(step, {"loss": 0.25})
        writer.close()
    assert lines(caplog) == []
    drawn = stream.getvalue()
    assert "\r" in drawn and "6/6" in drawn and "loss=0.25" in drawn and "step/s" in drawn


def test_without_progress_nothing_is_drawn_or_logged(tmp_path, caplog):
    for stream in (io.StringIO(), FakeTerminal()):
        with caplog.at_level(logging.DEBUG, logger="jaxdrive"):
            writer = MetricsWriter(tmp_path, total_steps=6, progress=False, progress_stream=stream)
            for step in (2, 4, 6):
                writer.write(step, {"loss": 0.25})
            writer.close()
        assert stream.getvalue() == "" and lines(caplog) == []
    with caplog.at_level(logging.DEBUG, logger="jaxdrive"), Progress(3, enabled=False, stream=io.StringIO()) as bar:
        assert list(bar.iterate("abc")) == ["a", "b", "c"] and not bar.terminal
    assert lines(caplog) == []


def test_every_spaces_the_lines_and_close_shows_the_rest(clock, caplog):
    with caplog.at_level(logging.INFO, logger="jaxdrive"):
        with Progress(10, unit="window", desc="encode", every=4, stream=io.StringIO()) as bar:
            for _ in range(5):
                clock.now += 1.0
                bar.update(2)
    assert lines(caplog) == [
        "encode window 4/10  2 window/s  ETA 00:03",
        "encode window 8/10  2 window/s  ETA 00:01",
        "encode window 10/10  2 window/s  ETA 00:00",
    ]


def test_iterate_logs_a_line_per_item_and_an_unknown_total_has_no_eta(clock, caplog):
    def items():
        for i in range(3):
            clock.now += 0.5
            yield i

    with caplog.at_level(logging.INFO, logger="jaxdrive"):
        with Progress(None, unit="window", stream=io.StringIO()) as bar:
            assert list(bar.iterate(items())) == [0, 1, 2]
    assert lines(caplog) == ["window 1  2 window/s", "window 2  2 window/s", "window 3  2 window/s"]


def test_the_terminal_check_and_the_interval_format():
    assert is_terminal(FakeTerminal()) and not is_terminal(io.StringIO()) and not is_terminal(object())
    closed = io.StringIO()
    closed.close()
    assert not is_terminal(closed)
    assert [format_interval(s) for s in (0, 59.6, 669, 3600, 3725)] == ["00:00", "01:00", "11:09", "1:00:00", "1:02:05"]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"total": -1}, "total: expected None or an int >= 0, got -1"),
        ({"every": 0}, "every: expected an int >= 1, got 0"),
    ],
)
def test_bad_arguments_are_named(kwargs, message):
    with pytest.raises(ValueError, match=message):
        Progress(**kwargs)


@pytest.mark.slow(seconds=8)
def test_jaxdrive_train_into_a_pipe_logs_one_line_per_logged_step(tmp_path, capsys):
    """The command's stderr handler shows the lines (``--no-progress`` is ``progress=False``: above)."""
    data = write_synthetic(tmp_path / "data", train=1, frames=5)
    sets = [f"data.path={data}", "data.views=2", "data.frames=5", "data.batch_size=2", "model.depth=1"]
    sets += ["optim.warmup_steps=2", "train.log_every=1", *MACHINERY]
    args = ["train", "--config", str(ROOT / "configs" / "tiny.py"), "--workdir", str(tmp_path / "run")]
    args += ["--mesh", "data=2,seq=4"]
    args += [a for s in sets for a in ("--set", s)]
    assert cli([*args, "--steps", "2"]) == 0
    err = capsys.readouterr().err
    shown = [line for line in err.splitlines() if line.startswith(f"INFO {PROGRESS}: ")]
    assert [line.split("  ")[0] for line in shown] == [f"INFO {PROGRESS}: step 1/2", f"INFO {PROGRESS}: step 2/2"]
    assert all(" loss " in line and " step/s" in line and "  ETA " in line for line in shown)
    assert "\r" not in err
