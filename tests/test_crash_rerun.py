"""The suite's crash rerun (tests/crash_rerun.py): a test whose worker dies runs once more on a
fresh worker; a second crash fails it; a failed assertion is never rerun."""

from pathlib import Path

TESTS = Path(__file__).resolve().parent


def test_a_crashed_test_runs_once_more_and_a_second_crash_fails(pytester, monkeypatch):
    monkeypatch.setenv("PYTHONPATH", str(TESTS))
    pytester.makeconftest('pytest_plugins = ["crash_rerun"]')
    marker = pytester.path / "crashed_once"
    pytester.makepyfile(
        test_toy=f"""
        import os, pathlib

        def test_crashes_once():
            marker = pathlib.Path({str(marker)!r})
            if not marker.exists():
                marker.touch()
                os.abort()

        def test_always_crashes():
            os.abort()

        def test_fails():
            assert 1 == 2
        """
    )
    result = pytester.runpytest_subprocess("-n", "1", "-p", "no:cacheprovider")
    assert result.ret == 1
    assert result.parseoutcomes() == {"passed": 1, "failed": 2, "rerun": 2}
    for line in (
        "worker crashed in test_toy.py::test_crashes_once (1x); ran again",
        "worker crashed in test_toy.py::test_always_crashes (2x); failed: crashed again",
        "FAILED test_toy.py::test_always_crashes - worker 'gw*' crashed while running*",
        "FAILED test_toy.py::test_fails - assert 1 == 2",  # an assertion is not rerun
    ):
        result.stdout.fnmatch_lines([line])
