"""The collection guard of the root conftest: a test file on disk that the whole-suite run
does not collect, or collects as another file's module, fails the run."""

from __future__ import annotations

from pathlib import Path

import pytest

pytest_plugins = ["pytester"]

GUARD = (Path(__file__).resolve().parents[1] / "conftest.py").read_text(encoding="utf-8")
INI = """
[pytest]
testpaths = a/tests b/tests
addopts = --import-mode=importlib -p no:cacheprovider
"""


def _project(pytester: pytest.Pytester, *, packages: bool) -> None:
    pytester.makeconftest(GUARD)
    pytester.makefile(".ini", pytest=INI)
    for pkg in ("a", "b"):
        tests = pytester.path / pkg / "tests"
        tests.mkdir(parents=True)
        if packages:
            (tests / "__init__.py").write_text("")
        (tests / "test_cli.py").write_text(f"def test_{pkg}():\n    assert True\n")


def test_colliding_module_names_fail_the_run(pytester: pytest.Pytester) -> None:
    _project(pytester, packages=True)
    result = pytester.runpytest()
    assert result.ret == pytest.ExitCode.USAGE_ERROR
    result.stderr.fnmatch_lines(["*test collection guard*", "*two test modules share a name*"])


def test_unique_module_names_pass(pytester: pytest.Pytester) -> None:
    _project(pytester, packages=False)
    result = pytester.runpytest()
    result.assert_outcomes(passed=2)


def test_a_file_without_tests_fails_the_run(pytester: pytest.Pytester) -> None:
    _project(pytester, packages=False)
    (pytester.path / "a/tests/test_helpers.py").write_text("VALUE = 1\n")
    result = pytester.runpytest()
    assert result.ret == pytest.ExitCode.USAGE_ERROR
    result.stderr.fnmatch_lines(["*a/tests/test_helpers.py was not collected*"])


def test_a_chosen_subset_is_not_guarded(pytester: pytest.Pytester) -> None:
    _project(pytester, packages=True)
    result = pytester.runpytest("a/tests/test_cli.py")
    result.assert_outcomes(passed=1)
