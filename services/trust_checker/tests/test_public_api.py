"""The public surface is what ``__all__`` says: the package's own, every module's, and
anything the rest of the repository (bench, tests, examples, other packages) imports
from the checker is in it."""

from __future__ import annotations

import ast
import importlib
import importlib.util
import pkgutil
from pathlib import Path

import pytest
import trust_checker

ROOT = Path(__file__).resolve().parents[3]

PACKAGE = {
    "EvalError",
    "Explainer",
    "Fired",
    "InputError",
    "Output",
    "Problem",
    "SpecError",
    "SpecRunner",
    "TextFileError",
    "TrustError",
    "load_spec",
}
SERVICE = {"TrustService", "open_service"}
CONFIG = {
    "ChannelMap",
    "DdsConfig",
    "DdsTopic",
    "FabricConfig",
    "FabricInput",
    "MqttConfig",
    "RedisConfig",
    "ServiceConfig",
    "TopicMap",
    "decode_map",
}

MODULES = sorted(
    m.name for m in pkgutil.walk_packages(trust_checker.__path__, prefix="trust_checker.")
)


def test_the_package_exports_the_core() -> None:
    assert set(trust_checker.__all__) == PACKAGE
    for name in PACKAGE:
        assert getattr(trust_checker, name) is not None


@pytest.mark.parametrize(
    ("module", "expected"), [("trust_checker.service", SERVICE), ("trust_checker.config", CONFIG)]
)
def test_the_service_surface(module: str, expected: set[str]) -> None:
    assert set(importlib.import_module(module).__all__) == expected


def test_every_module_is_listed() -> None:
    """A new module gets an ``__all__`` (the next test), and a place in this list."""
    assert MODULES == [
        "trust_checker.__main__",
        "trust_checker.config",
        "trust_checker.console",
        "trust_checker.engine",
        "trust_checker.engine.compiler",
        "trust_checker.engine.dynamic",
        "trust_checker.engine.lifted",
        "trust_checker.engine.nodes",
        "trust_checker.engine.plan",
        "trust_checker.engine.runner",
        "trust_checker.engine.stateful",
        "trust_checker.errors",
        "trust_checker.explain",
        "trust_checker.io",
        "trust_checker.io.auth",
        "trust_checker.io.codec",
        "trust_checker.io.credentials",
        "trust_checker.io.dds",
        "trust_checker.io.fabric",
        "trust_checker.io.mqtt",
        "trust_checker.io.ports",
        "trust_checker.io.redis",
        "trust_checker.io.session",
        "trust_checker.io.specs",
        "trust_checker.io.ticks",
        "trust_checker.lang",
        "trust_checker.lang.ast",
        "trust_checker.lang.check",
        "trust_checker.lang.lexer",
        "trust_checker.lang.parser",
        "trust_checker.operators",
        "trust_checker.service",
        "trust_checker.specs",
        "trust_checker.tracefile",
        "trust_checker.values",
    ]


@pytest.mark.parametrize("module", MODULES)
def test_every_module_has_an_all_of_names_it_defines(module: str) -> None:
    mod = importlib.import_module(module)
    names = getattr(mod, "__all__", None)
    assert names is not None, f"{module} has no __all__"
    assert len(set(names)) == len(names), f"{module}.__all__ repeats a name"
    for name in names:
        assert hasattr(mod, name), f"{module}.__all__ names missing {name}"


def _imports_from_the_checker() -> dict[tuple[str, str], list[str]]:
    """(module, name) -> the files outside the package's source that import it."""
    found: dict[tuple[str, str], list[str]] = {}
    src = ROOT / "services" / "trust_checker" / "src"
    for top in ("bench", "tests", "examples", "libs", "services"):
        for path in sorted((ROOT / top).rglob("*.py")):
            if src in path.parents or any(p.startswith(".") for p in path.relative_to(ROOT).parts):
                continue
            tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
            for node in ast.walk(tree):
                if isinstance(node, ast.ImportFrom) and node.module:
                    if node.module.split(".")[0] == "trust_checker":
                        for alias in node.names:
                            where = str(path.relative_to(ROOT))
                            found.setdefault((node.module, alias.name), []).append(where)
    return found


def test_what_the_repository_imports_from_the_checker_is_public() -> None:
    found = _imports_from_the_checker()
    assert ("trust_checker.service", "open_service") in found  # the scan sees imports
    private = []
    for (module, name), files in sorted(found.items()):
        mod = importlib.import_module(module)
        submodule = hasattr(mod, "__path__") and (
            importlib.util.find_spec(f"{module}.{name}") is not None
        )
        if name not in getattr(mod, "__all__", ()) and not submodule:
            private.append(f"{module}.{name} (imported by {', '.join(files)})")
    assert not private, "not in __all__: " + "; ".join(private)


def test_no_name_of_the_checker_shadows_the_sdks_or_the_schemas() -> None:
    """One home per name: a class the checker defines is not named like one of rap_sdk
    or rap_schemas (where it is the same concept, the checker uses theirs)."""
    import rap_schemas
    import rap_sdk

    theirs: set[str] = set()
    for package in (rap_sdk, rap_schemas):
        theirs |= set(package.__all__)
        for info in pkgutil.walk_packages(package.__path__, prefix=f"{package.__name__}."):
            theirs |= set(getattr(importlib.import_module(info.name), "__all__", ()))
    assert {"Clock", "ConfigError", "Node", "Token", "Verdict"} <= theirs
    clashes = []
    for module in MODULES:
        mod = importlib.import_module(module)
        for name in mod.__all__:
            obj = getattr(mod, name)
            if isinstance(obj, type) and obj.__module__ == module and name in theirs:
                clashes.append(f"{module}.{name}")
    assert not clashes
