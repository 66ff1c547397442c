"""The public surface of sim_world: every module declares ``__all__``, the surface is the
one written here, and what other packages of the repository import from sim_world is
part of it."""

from __future__ import annotations

import ast
import importlib
import pkgutil
from pathlib import Path

import pytest
import sim_world

SURFACE: dict[str, set[str]] = {
    "sim_world": set(),
    "sim_world.__main__": {"cli", "main"},
    "sim_world.config": {"MAX_DURATION", "MAX_REALTIME_FACTOR", "SimConfig", "SimConfigError"},
    "sim_world.executor": {"PlanExecutor"},
    "sim_world.geometry": {"Scene", "cast_rays", "scene_of"},
    "sim_world.kinematics": {"DiffDrive", "Pose2", "wrap"},
    "sim_world.navigation": {
        "CANDIDATES",
        "LOOKAHEAD",
        "MARGIN",
        "MEMORY_RANGE",
        "REACHED",
        "STOP",
        "Navigator",
        "fold_points",
        "near_returns",
    },
    "sim_world.occlusion": {"GLOBAL_WINDOW", "active_arcs", "occlusion_mask"},
    "sim_world.physics": {"STATIC", "pymunk_ray", "static_space"},
    "sim_world.schema": {"SCHEMA_PATH", "cli", "main", "render"},
    "sim_world.service": {"NODE", "RobotSummary", "RunSummary", "SimService", "open_service"},
    "sim_world.sim": {"Robot", "ScanEvent", "Simulation"},
    "sim_world.viz": {"RerunFileError", "RerunLog"},
    "sim_world.world": {
        "MAX_ROOM",
        "MAX_SPEED",
        "REACHED",
        "Arc",
        "Box",
        "Circle",
        "Lidar",
        "Occlusion",
        "Point",
        "Pose",
        "RobotSpec",
        "Room",
        "WorldError",
        "WorldSpec",
        "check_world",
        "default_world_path",
        "find_world",
        "load_world",
        "parse_world",
        "shipped_worlds",
    },
}

REPO = Path(__file__).resolve().parents[3]
OWN = REPO / "services" / "sim_world"


def modules() -> list[str]:
    found = ["sim_world"]
    found += [m.name for m in pkgutil.walk_packages(sim_world.__path__, "sim_world.")]
    return sorted(found)


def test_every_module_is_listed_here() -> None:
    assert modules() == sorted(SURFACE), "a module was added or removed: update SURFACE"


@pytest.mark.parametrize("name", sorted(SURFACE))
def test_each_module_declares_its_public_names(name: str) -> None:
    module = importlib.import_module(name)
    declared = getattr(module, "__all__", None)
    assert declared is not None, f"{name} has no __all__"
    assert len(declared) == len(set(declared)), f"{name}.__all__ repeats a name"
    assert set(declared) == SURFACE[name]
    for attr in declared:
        assert hasattr(module, attr), f"{name}.__all__ names {attr!r}, which it lacks"


def imports_from_sim_world() -> list[tuple[str, str, str]]:
    """(file, module, name) of every ``from sim_world... import name`` outside sim_world."""
    found = []
    for top in ("bench", "examples", "libs", "schemas", "services", "tests"):
        for path in sorted((REPO / top).rglob("*.py")):
            if OWN in path.parents or any(p.startswith(".") for p in path.relative_to(REPO).parts):
                continue
            tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
            for node in ast.walk(tree):
                if (
                    isinstance(node, ast.ImportFrom)
                    and node.module is not None
                    and node.module.split(".")[0] == "sim_world"
                ):
                    rel = str(path.relative_to(REPO))
                    found += [(rel, node.module, a.name) for a in node.names]
    return found


def test_what_other_packages_import_is_public() -> None:
    found = imports_from_sim_world()
    assert len(found) >= 10, found  # examples, bench and tests do use sim_world
    private = [
        f"{where}: from {module} import {name}"
        for where, module, name in found
        if name not in SURFACE.get(module, set())
        and f"{module}.{name}" not in SURFACE  # importing a submodule
    ]
    assert not private, "not in the module's __all__:\n" + "\n".join(private)
