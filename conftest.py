"""Shared pytest configuration.

- Every async test runs on asyncio through anyio.
- The collection guard: when the whole suite runs (``make test``, CI: no paths given),
  every ``test_*.py`` file under the configured test paths must be collected, and each
  collected module must be the file it was collected from. Two test files whose module
  names collide (two ``tests`` packages with a ``test_cli.py`` each, say) would otherwise
  make pytest run one file's tests twice and the other's never, silently.
"""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture
def anyio_backend() -> str:
    return "asyncio"


def _test_files(config: pytest.Config) -> set[Path]:
    root = config.rootpath
    files: set[Path] = set()
    for entry in config.getini("testpaths"):
        files.update(p.resolve() for p in (root / entry).rglob("test_*.py"))
    return files


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(
    session: pytest.Session, config: pytest.Config, items: list[pytest.Item]
) -> None:
    """Runs before ``-k``/``-m`` deselect anything: ``items`` is all that was collected."""
    if config.args_source is not pytest.Config.ArgsSource.TESTPATHS or session.testsfailed:
        return  # a chosen subset, or collection errors that fail the run already
    problems: list[str] = []
    collected: set[Path] = set()
    for item in items:
        module = item.getparent(pytest.Module)
        if module is None:
            continue
        path = module.path.resolve()
        collected.add(path)
        loaded = Path(getattr(module.obj, "__file__", "") or "").resolve()
        if loaded != path:
            problems.append(
                f"{path.relative_to(config.rootpath)} was collected as the module of "
                f"{loaded}: two test modules share a name; remove the __init__.py that "
                "makes them packages of the same name, or rename one"
            )
    problems.extend(
        f"{path.relative_to(config.rootpath)} was not collected (it has no tests, or "
        "they are all deselected by a collection hook); fix it or remove it"
        for path in sorted(_test_files(config) - collected)
    )
    if problems:
        unique = sorted(set(problems))
        raise pytest.UsageError("test collection guard:\n  " + "\n  ".join(unique))
