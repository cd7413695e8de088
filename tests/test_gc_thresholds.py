"""jaxdrive.gc_thresholds: the collector's thresholds for a block, and the jaxdrive command runs in it."""

import argparse
import gc

import pytest

import jaxdrive.cli
from jaxdrive.gc_thresholds import THRESHOLDS, relaxed_gc


@pytest.fixture
def default_thresholds():
    """CPython's defaults for the test (the suite runs with THRESHOLDS: tests/conftest.py)."""
    before = gc.get_threshold()
    gc.set_threshold(700, 10, 10)
    yield (700, 10, 10)
    gc.set_threshold(*before)


def test_the_block_runs_with_the_thresholds_and_the_old_ones_come_back_after_an_error(default_thresholds):
    with relaxed_gc((1000, 3, 4)):
        assert gc.get_threshold() == (1000, 3, 4)
    assert gc.get_threshold() == default_thresholds
    with pytest.raises(RuntimeError, match="inside"), relaxed_gc():
        assert gc.get_threshold() == THRESHOLDS
        raise RuntimeError("inside")
    assert gc.get_threshold() == default_thresholds
    assert THRESHOLDS[0] > default_thresholds[0]


@pytest.mark.parametrize("bad", [(1000, 3), (0, 10, 10), (1000.0, 10, 10), (True, 10, 10), 700, [700, 10, 10]])
def test_bad_thresholds_are_refused(bad, default_thresholds):
    with pytest.raises(ValueError, match=r"thresholds: expected a tuple of three positive ints, got"), relaxed_gc(bad):
        pass
    assert gc.get_threshold() == default_thresholds


def test_a_command_runs_with_the_thresholds(monkeypatch, default_thresholds):
    seen = []

    def parser():
        p = argparse.ArgumentParser(prog="jaxdrive")
        p.add_argument("-q", "--quiet", action="store_true")
        sub = p.add_subparsers(dest="command")
        sub.add_parser("probe").set_defaults(run=lambda args, rest: seen.append(gc.get_threshold()) or 0)
        return p

    monkeypatch.setattr(jaxdrive.cli, "build_parser", parser)
    assert jaxdrive.cli.main(["probe"]) == 0
    assert seen == [THRESHOLDS]
    assert gc.get_threshold() == default_thresholds
