"""Acceptance: RAP's RoboChart / RoboArch parser on real third-party designs.

The designs are not part of this repository: set ``DESIGN_MODELS`` to the folder that
holds them (its ``robochart/`` sub-folder is read) and run

    DESIGN_MODELS=<folder> python -m pytest -p no:cacheprovider \\
        acceptance/test_robochart_parse_acceptance.py -s

Every ``.rct`` and ``.rac`` file must parse with no error diagnostic; the York HelloWorld
MAPLE-K package must contain what its README lists. ``-s`` shows per-file counts.
"""

from __future__ import annotations

import os
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import pytest
from rap_cli.diagnostics import Diagnostic
from rap_cli.robochart import parse_robochart_files
from rap_cli.robochart import syntax as s


@pytest.fixture(scope="module")
def robochart_dir() -> Path:
    """``$DESIGN_MODELS/robochart``, or a failure that says how to provide it."""
    root = os.environ.get("DESIGN_MODELS")
    if not root:
        pytest.fail(
            "DESIGN_MODELS is not set - set it to the folder of shared design models "
            "(the one with a robochart/ sub-folder)",
            pytrace=False,
        )
    folder = Path(root) / "robochart"
    if not folder.is_dir():
        pytest.fail(
            f"{folder} does not exist - DESIGN_MODELS={root} must hold a robochart/ folder",
            pytrace=False,
        )
    return folder


@pytest.fixture(scope="module")
def parsed(robochart_dir: Path) -> tuple[list[s.RcFile | s.RacFile], list[Diagnostic]]:
    paths = sorted(p for p in robochart_dir.rglob("*") if p.suffix in (".rct", ".rac"))
    assert paths, f"no .rct or .rac file under {robochart_dir}"
    return parse_robochart_files(paths)


def _walk(nodes: tuple[s.Node, ...]) -> Iterator[s.Node]:
    stack = list(nodes)
    while stack:
        node = stack.pop()
        yield node
        if isinstance(node, s.State):
            stack.extend(node.nodes)


def _transitions(machine: s.StateMachine) -> int:
    nested = sum(len(n.transitions) for n in _walk(machine.nodes) if isinstance(n, s.State))
    return len(machine.transitions) + nested


def _machines(file: s.RcFile | s.RacFile) -> Iterator[s.StateMachine]:
    for d in file.declarations:
        if isinstance(d, s.StateMachine):
            yield d
        elif isinstance(d, s.Controller):
            yield from (m.definition for m in d.machines if m.definition)
            yield from (o.definition for o in d.operations if o.definition)


def _counts(file: s.RcFile | s.RacFile) -> str:
    kinds = Counter(type(d).__name__ for d in file.declarations)
    machines = list(_machines(file))
    states = sum(isinstance(n, s.State) for m in machines for n in _walk(m.nodes))
    connections = sum(
        len(d.connections) for d in file.declarations if isinstance(d, s.Controller | s.Module)
    )
    parts = [f"{k}={v}" for k, v in sorted(kinds.items())]
    parts += [
        f"stm={len(machines)}",
        f"states={states}",
        f"transitions={sum(_transitions(m) for m in machines)}",
    ]
    if isinstance(file, s.RacFile):
        parts += [f"layers={len(file.layers)}", f"connections={len(file.connections)}"]
    else:
        parts.append(f"connections={connections}")
    return " ".join(parts)


def test_every_shared_file_parses_without_error(
    robochart_dir: Path, parsed: tuple[list[s.RcFile | s.RacFile], list[Diagnostic]]
) -> None:
    files, diagnostics = parsed
    print()  # noqa: T201 - the per-file report is for the reviewer (-s)
    for f in files:
        name = Path(f.loc.file).relative_to(robochart_dir)
        print(f"{name}: {_counts(f)}")  # noqa: T201
    for d in diagnostics:
        print(d)  # noqa: T201
    errors = [str(d) for d in diagnostics if d.severity == "error"]
    assert errors == []
    expected = {p for p in robochart_dir.rglob("*") if p.suffix in (".rct", ".rac")}
    assert {Path(f.loc.file) for f in files} == expected


def _package(files: list[s.RcFile | s.RacFile], folder: str) -> list[s.RcFile]:
    return [f for f in files if isinstance(f, s.RcFile) and Path(f.loc.file).parent.name == folder]


def _find(files: list[s.RcFile], kind: type, name: str) -> object:
    found = [d for f in files for d in f.declarations if isinstance(d, kind) and d.name == name]
    assert len(found) == 1, f"{kind.__name__} {name}: found {len(found)}"
    return found[0]


def _shape(t: s.TypeExpr) -> str:
    if isinstance(t, s.SeqType):
        return f"Seq({_shape(t.elem)})"
    if isinstance(t, s.TypeName):
        return t.name
    return type(t).__name__


def test_york_helloworld_package_has_what_the_readme_lists(
    parsed: tuple[list[s.RcFile | s.RacFile], list[Diagnostic]],
) -> None:
    files = _package(parsed[0], "york-helloworld")
    assert len(files) == 7
    records = {
        "LidarRange": [
            ("angleMin", "real"),
            ("angleMax", "real"),
            ("angleIncrement", "real"),
            ("timeIncrement", "real"),
            ("rangeMin", "real"),
            ("rangeMax", "real"),
            ("scanTime", "real"),
            ("ranges", "Seq(real)"),
            ("intensities", "Seq(real)"),
        ],
        "SpinConfig": [("commands", "Seq(SpinCommand)"), ("period", "int")],
        "SpinCommand": [("angleVelocity", "real"), ("duration", "real")],
        "BoolLidarMask": [("values", "Seq(boolean)"), ("baseAngle", "real")],
        "ProbLidarMask": [("values", "Seq(real)"), ("baseAngle", "real")],
    }
    print()  # noqa: T201
    for name, fields in records.items():
        record = _find(files, s.Record, name)
        assert isinstance(record, s.Record)
        got = [(f.name, _shape(f.type)) for f in record.fields]
        print(f"record {name}: {len(got)} fields {got}")  # noqa: T201
        assert got == fields
    component = _find(files, s.Enumeration, "Component")
    assert isinstance(component, s.Enumeration)
    literals = [lit.name for lit in component.literals]
    print(f"enumeration Component: {len(literals)} literals {literals}")  # noqa: T201
    assert literals == ["MONITOR", "ANALYSE", "PLAN", "LEGITIMATE", "EXECUTE"]
    adaptation = _find(files, s.Controller, "Adaptation")
    assert isinstance(adaptation, s.Controller)
    targets = [m.target for m in adaptation.machines]
    print(  # noqa: T201
        f"controller Adaptation: {len(targets)} machines {targets}, "
        f"{len(adaptation.connections)} connections"
    )
    assert targets == ["Monitor", "Analyse", "Plan", "Legitimate", "Execute", "Knowledge"]
    assert len(adaptation.connections) == 33
    for target in targets:  # every referenced machine is defined in the package
        assert isinstance(_find(files, s.StateMachine, str(target)), s.StateMachine)
    nodes = {m.name for m in adaptation.machines} | {adaptation.name}
    for c in adaptation.connections:  # every endpoint names a machine or the controller
        assert {c.from_node, c.to_node} <= nodes, c


def test_navigation_case_controller_module_and_architecture(
    parsed: tuple[list[s.RcFile | s.RacFile], list[Diagnostic]],
) -> None:
    files = _package(parsed[0], "navigation-case-study")
    adaptation = _find(files, s.Controller, "Adaptation")
    assert isinstance(adaptation, s.Controller)
    assert sorted(str(m.target) for m in adaptation.machines) == [
        "Adaptation_Analyse",
        "Adaptation_Execute",
        "Adaptation_Knowledge",
        "Adaptation_Legitimate",
        "Adaptation_Monitor",
        "Adaptation_Plan",
    ]
    nodes = {m.name for m in adaptation.machines} | {adaptation.name}
    for c in adaptation.connections:
        assert {c.from_node, c.to_node} <= nodes, c
    turtlebot = _find(files, s.Module, "Turtlebot")
    assert isinstance(turtlebot, s.Module)
    assert turtlebot.platform is not None
    assert turtlebot.platform.definition is not None
    assert [c.target for c in turtlebot.controllers] == ["Adaptation", "Control"]
    assert all(c.asynchronous for c in turtlebot.connections)
    (arch,) = [f for f in parsed[0] if isinstance(f, s.RacFile)]
    assert arch.system == "Turtlebot"
    assert [(layer.name, layer.pattern) for layer in arch.layers] == [
        ("Adaptation", "MAPLE-K"),
        ("Control", None),
    ]
    assert [b.name for b in arch.layers[0].stages] == [
        "monitor",
        "analyse",
        "plan",
        "legitimate",
        "execute",
    ]
    assert len(arch.connections) == 3
