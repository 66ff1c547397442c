"""Every package's public names are its modules' ``__all__``, and what one package (or a
benchmark, an example, a test elsewhere) imports from another is public there."""

from __future__ import annotations

import ast
import importlib
import pkgutil
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = {  # package -> its folder
    "rap_schemas": REPO / "schemas",
    "rap_sdk": REPO / "libs" / "rap_sdk",
    "rap_bridges": REPO / "libs" / "rap_bridges",
    "knowledge": REPO / "services" / "knowledge",
    "maplek_runner": REPO / "services" / "maplek_runner",
    "sim_world": REPO / "services" / "sim_world",
    "trust_checker": REPO / "services" / "trust_checker",
    "lidar_occlusion": REPO / "examples" / "lidar_occlusion",
}
SOURCES = ("schemas", "libs", "services", "examples", "bench", "tests")


def modules(package: str) -> list[str]:
    root = importlib.import_module(package)
    names = [package] + [m.name for m in pkgutil.walk_packages(root.__path__, f"{package}.")]
    return sorted(names)


ALL_MODULES = [m for p in PACKAGES for m in modules(p)]


@pytest.mark.parametrize("name", ALL_MODULES)
def test_each_module_declares_its_public_names(name: str) -> None:
    module = importlib.import_module(name)
    declared = getattr(module, "__all__", None)
    assert declared is not None, f"{name} has no __all__: declare its public names"
    assert len(declared) == len(set(declared)), f"{name}.__all__ names something twice"
    missing = [attr for attr in declared if not hasattr(module, attr)]
    assert not missing, f"{name}.__all__ names {missing}, which it does not define"


def cross_imports() -> list[tuple[str, int, str, str]]:
    """(file, line, module, name) of ``from <package>... import name`` written outside
    that package's own folder."""
    found = []
    for top in SOURCES:
        for path in sorted((REPO / top).rglob("*.py")):
            hidden = any(p.startswith(".") for p in path.relative_to(REPO).parts)  # .venv
            if hidden or "results" in path.parts:
                continue
            tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
            for node in ast.walk(tree):
                if not isinstance(node, ast.ImportFrom) or node.level or not node.module:
                    continue
                package = node.module.split(".")[0]
                home = PACKAGES.get(package)
                if home is None or home in path.parents:
                    continue
                found += [
                    (str(path.relative_to(REPO)), node.lineno, node.module, alias.name)
                    for alias in node.names
                ]
    return found


def test_what_other_packages_import_is_public() -> None:
    wrong = []
    for file, line, module, name in cross_imports():
        mod = importlib.import_module(module)
        public = set(getattr(mod, "__all__", ()))
        is_module = (
            importlib.util.find_spec(f"{module}.{name}") is not None
            if hasattr(mod, "__path__")
            else False
        )
        private = any(part.startswith("_") and part != "__main__" for part in module.split("."))
        if private or (name not in public and not is_module):
            wrong.append(f"{file}:{line}: from {module} import {name}")
    assert not wrong, "imports of names that are not public:\n" + "\n".join(wrong)
