"""Acceptance: the AADL-IL importer on RPIO's real ``design.json`` (York HelloWorld).

The design is not part of this repository (``DESIGN_MODELS``, see ``conftest.py``). One
test per expectation of the models' README ("What a correct import yields", York
HelloWorld). Lines are found in the file's text, never written down here, so that the
assertions say *which* construct a diagnostic points at.
"""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import msgspec
import pytest
from rap_cli.diagnostics import Loc
from rap_cli.importers import Imported
from rap_cli.importers.aadl_il import import_aadl_il
from rap_schemas.model import ModelFinding, model_findings
from rap_schemas.plan import DeploymentPlan, plan_findings

SCHEMA = Path(__file__).parents[1] / "schemas" / "json" / "rap.DeploymentPlan.schema.json"


@pytest.fixture(scope="module")
def design(design_models: Path) -> Path:
    path = design_models / "aadl-il" / "york-helloworld" / "design.json"
    assert path.is_file(), f"{path} is missing from DESIGN_MODELS"
    return path


@pytest.fixture(scope="module")
def imported(design: Path) -> Imported:
    return import_aadl_il(design)


@pytest.fixture(scope="module")
def plan(imported: Imported) -> DeploymentPlan:
    assert imported.readable
    assert imported.plan is not None
    return imported.plan


@pytest.fixture(scope="module")
def findings(plan: DeploymentPlan) -> list[ModelFinding]:
    return model_findings(plan)


def _line(design: Path, needle: str, nth: int = 0) -> int:
    """The line of the ``nth`` occurrence of ``needle`` in the design's text."""
    lines = [i for i, text in enumerate(design.read_text().splitlines(), 1) if needle in text]
    assert len(lines) > nth, f"{needle!r} occurs {len(lines)} times in {design}"
    return lines[nth]


def _line_after(design: Path, needle: str, after: int) -> int:
    """The first line after line ``after`` that holds ``needle``."""
    for i, text in enumerate(design.read_text().splitlines(), 1):
        if i > after and needle in text:
            return i
    raise AssertionError(f"{needle!r} does not occur after line {after}")


def _where(imported: Imported, finding: ModelFinding) -> Loc:
    loc = imported.locate(finding.loc)
    assert loc is not None, f"{finding.message} has no place in the design"
    return loc


def test_the_imported_plan_converts_and_validates(plan: DeploymentPlan) -> None:
    builtins = msgspec.to_builtins(plan)
    assert msgspec.convert(builtins, DeploymentPlan) == plan
    jsonschema.validate(builtins, json.loads(SCHEMA.read_text()))


def test_processes_are_the_components_and_legitimate_has_no_ports(plan: DeploymentPlan) -> None:
    assert list(plan.components) == ["Monitor", "Analysis", "Plan", "Legitimate", "Execute"]
    stages = {name: c.stage for name, c in plan.components.items()}
    assert stages == {
        "Monitor": "monitor",
        "Analysis": "analyse",
        "Plan": "plan",
        "Legitimate": "legitimate",
        "Execute": "execute",
    }
    assert plan.components["Legitimate"].ports == {}
    assert set(plan.components["Execute"].ports) == {
        "new_plan",
        "isLegit",
        "directions",
        "spin_config",
    }
    assert plan.components["Execute"].ports["spin_config"].topic == "/spin_config"


def test_compute_nodes_with_their_addresses(
    plan: DeploymentPlan, imported: Imported, design: Path
) -> None:
    assert {n: c.address for n, c in plan.compute_nodes.items()} == {
        "xeon1": "192.168.0.172",
        "lattepandaD3": "192.168.0.161",
    }
    assert plan.compute_nodes["xeon1"].properties["rap_backbone"] == "true"
    assert imported.where[("compute_nodes", "xeon1")].line == _line(design, '"_name": "xeon1"')


def test_bindings_and_legitimate_bound_to_nothing(
    plan: DeploymentPlan, imported: Imported, design: Path
) -> None:
    assert {n: c.node for n, c in plan.components.items()} == {
        "Monitor": "lattepandaD3",
        "Analysis": "lattepandaD3",
        "Plan": "xeon1",
        "Execute": "xeon1",
        "Legitimate": None,
    }
    unbound = [
        (imported.locate(loc), problem)
        for loc, problem, _ in plan_findings(plan)
        if "bound to no compute node" in problem
    ]
    assert len(unbound) == 1
    where, problem = unbound[0]
    assert "'Legitimate'" in problem
    assert where is not None
    assert where.line == _line(design, '"_name": "Legitimate"')


def test_messages_include_those_only_ports_use_with_an_error_at_the_port(
    plan: DeploymentPlan, imported: Imported, design: Path
) -> None:
    assert set(plan.messages) == {
        "LaserScan",
        "Direction",
        "AnomalyMessage",
        "NewPlanMessage",
        "NewData",
        "LegitimateMessage",
    }
    assert plan.messages["LaserScan"].fields["ranges"].type == "list[float64]"
    assert plan.messages["Direction"].fields["omega"].type == "float64"
    for message, port in (("NewData", "new_data"), ("LegitimateMessage", "isLegit")):
        assert "message lists" in plan.messages[message].doc
        (error,) = [
            d
            for d in imported.diagnostics
            if d.severity == "error" and f"uses message {message!r}" in d.message
        ]
        assert "which the design does not declare" in error.message
        assert error.line == _line(design, f'"_name": "{port}"')


def test_nothing_produces_execute_islegit_or_directions(
    findings: list[ModelFinding], imported: Imported, design: Path
) -> None:
    for port in ("isLegit", "directions"):
        (finding,) = [
            f
            for f in findings
            if f.severity == "error"
            and f"input Execute.{port} is connected to nothing" in f.message
        ]
        where = _where(imported, finding)
        assert where.file == str(design)
        assert where.line == _line(design, f'"_name": "{port}"')


def test_execute_new_plan_is_direction_while_plan_sends_new_plan_message(
    findings: list[ModelFinding], imported: Imported, design: Path
) -> None:
    (finding,) = [
        f
        for f in findings
        if "sends NewPlanMessage but Execute.new_plan takes Direction" in f.message
    ]
    where = _where(imported, finding)
    # Execute's own new_plan port is the third "new_plan" (after Plan's port and thread);
    # the finding points at the message it names, Direction, a few lines below it
    port = _line(design, '"_name": "new_plan"', 2)
    assert port < _line(design, '"_name": "Execute"') + 10
    direction = _line_after(design, '"_name": "Direction"', port)
    assert (where.file, where.line) == (str(design), direction)
