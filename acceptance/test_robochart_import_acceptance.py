"""Acceptance: the RoboChart importer on real third-party designs.

The designs are not part of this repository (``DESIGN_MODELS``, see ``conftest.py``).
One test per expectation of the models' README ("What a correct import yields", York
HelloWorld RoboChart), and the navigation case study (RoboChart with its RoboArch)
imported in full with every diagnostic located.
"""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import msgspec
import pytest
from rap_cli.importers import Imported
from rap_cli.importers.robochart import import_robochart
from rap_cli.robochart import parse_robochart_files
from rap_cli.robochart import syntax as s
from rap_schemas.model import connections, model_findings
from rap_schemas.plan import DeploymentPlan

SCHEMA = Path(__file__).parents[1] / "schemas" / "json" / "rap.DeploymentPlan.schema.json"
MACHINES = ["Monitor", "Analyse", "Plan", "Legitimate", "Execute", "Knowledge"]


@pytest.fixture(scope="module")
def york_dir(design_models: Path) -> Path:
    folder = design_models / "robochart" / "york-helloworld"
    assert folder.is_dir(), f"{folder} is missing from DESIGN_MODELS"
    return folder


@pytest.fixture(scope="module")
def york(york_dir: Path) -> Imported:
    return import_robochart([york_dir])


@pytest.fixture(scope="module")
def york_plan(york: Imported) -> DeploymentPlan:
    assert york.readable
    assert york.plan is not None
    return york.plan


@pytest.fixture(scope="module")
def navigation(design_models: Path) -> Imported:
    folder = design_models / "robochart" / "navigation-case-study"
    assert (folder / "turtlebot.rac").is_file(), f"{folder} lacks turtlebot.rac"
    return import_robochart([folder])


def _valid(plan: DeploymentPlan) -> None:
    builtins = msgspec.to_builtins(plan)
    assert msgspec.convert(builtins, DeploymentPlan) == plan
    jsonschema.validate(builtins, json.loads(SCHEMA.read_text()))


def test_york_imports_without_errors_and_validates(
    york: Imported, york_plan: DeploymentPlan
) -> None:
    assert [d for d in york.diagnostics if d.severity == "error"] == []
    _valid(york_plan)


def test_york_records_and_their_field_types(york_plan: DeploymentPlan) -> None:
    def types(name: str) -> dict[str, str]:
        return {f: spec.type for f, spec in york_plan.messages[name].fields.items()}

    # The README says LidarRange has "7 reals" and the two sequences; the file
    # (MAPLE-K.rct) declares 7 reals plus ranges and intensities: 9 fields.
    lidar = types("LidarRange")
    assert len(lidar) == 9
    assert [f for f, t in lidar.items() if t == "float"] == [
        "angleMin",
        "angleMax",
        "angleIncrement",
        "timeIncrement",
        "rangeMin",
        "rangeMax",
        "scanTime",
    ]
    assert lidar["ranges"] == lidar["intensities"] == "list[float]"
    assert types("SpinConfig") == {"commands": "list[SpinCommand]", "period": "int"}
    assert types("SpinCommand") == {"angleVelocity": "float", "duration": "float"}
    assert types("BoolLidarMask") == {"values": "list[bool]", "baseAngle": "float"}
    assert types("ProbLidarMask") == {"values": "list[float]", "baseAngle": "float"}


def test_every_seq_field_becomes_a_list(york_dir: Path, york_plan: DeploymentPlan) -> None:
    files, _ = parse_robochart_files([york_dir])
    seq_fields = [
        (d.name, f.name)
        for file in files
        for d in file.declarations
        if isinstance(d, s.Record)
        for f in d.fields
        if isinstance(f.type, s.SeqType)
    ]
    assert len(seq_fields) == 5  # ranges, intensities, commands and two values
    for record, field in seq_fields:
        assert york_plan.messages[record].fields[field].type.startswith("list[")


def test_enumeration_component_with_its_literals(york_plan: DeploymentPlan) -> None:
    component = york_plan.messages["Component"]
    assert component.enum == ["MONITOR", "ANALYSE", "PLAN", "LEGITIMATE", "EXECUTE"]
    assert component.fields == {}


def test_controller_adaptation_has_six_machines_as_components(york_plan: DeploymentPlan) -> None:
    comps = york_plan.components
    for name in MACHINES:
        assert comps[name].origin is not None
        assert comps[name].origin.startswith("robochart stm ")
    assert [comps[n].stage for n in MACHINES[:5]] == [
        "monitor",
        "analyse",
        "plan",
        "legitimate",
        "execute",
    ]
    assert comps["Knowledge"].role == "knowledge"
    assert comps["Adaptation"].role == "controller"
    assert comps["Adaptation"].external
    assert comps["Adaptation"].properties["machines"].split(", ")[0] == "stm_ref0 = Monitor"


def test_33_connections_each_resolving(york_plan: DeploymentPlan, york: Imported) -> None:
    assert len(york_plan.connections) == 33
    explicit = [c for c in connections(york_plan) if c.index is not None]
    assert len(explicit) == 33
    first = york.where[("connections", 0)]
    assert (Path(first.file).name, first.line) == ("MAPLE-K.rct", 82)


def test_every_connection_endpoint_is_a_port(york_dir: Path, york_plan: DeploymentPlan) -> None:
    files, _ = parse_robochart_files([york_dir])
    (controller,) = [d for f in files for d in f.declarations if isinstance(d, s.Controller)]
    refs = {m.name: m.target for m in controller.machines} | {"Adaptation": "Adaptation"}
    ends = {(refs[c.from_node], c.from_event) for c in controller.connections} | {
        (refs[c.to_node], c.to_event) for c in controller.connections
    }
    for comp, event in ends:
        assert event in york_plan.components[comp].ports, f"{comp}.{event}"
    total = sum(len(c.ports) for c in york_plan.components.values())
    assert total == len(ends)
    port = york_plan.components["Monitor"].ports["lidarData"]
    assert (port.direction, port.kind, port.type) == ("in", "event-data", "LidarRange")
    scans = york_plan.components["Knowledge"].ports["lidarScans"]
    assert (scans.direction, scans.type) == ("out", "LidarRangeList")
    assert york_plan.messages["LidarRangeList"].fields["value"].type == "list[LidarRange]"


def test_york_model_findings_are_located(york: Imported, york_plan: DeploymentPlan) -> None:
    types = [f for f in model_findings(york_plan) if "sends" in f.message]
    assert types == []  # both ends of every connection carry the same message
    for finding in model_findings(york_plan):
        assert york.locate(finding.loc) is not None, finding.message


def test_navigation_case_imports_fully_with_located_diagnostics(navigation: Imported) -> None:
    assert navigation.readable
    assert navigation.plan is not None
    plan = navigation.plan
    _valid(plan)
    assert [d for d in navigation.diagnostics if d.severity == "error"] == []
    for d in navigation.diagnostics:
        assert d.line > 0, str(d)
    assert plan.system == "Turtlebot"
    stages = {c.stage for c in plan.components.values() if c.stage}
    assert stages == {"monitor", "analyse", "plan", "legitimate", "execute"}
    assert plan.components["Adaptation_Knowledge"].role == "knowledge"
    assert plan.components["Turtlebot"].role == "platform"
    assert plan.components["Adaptation"].properties["roboarch.pattern"] == "MAPLE-K"
    assert "roboarch.recorded_data" in plan.components["Adaptation_Monitor"].properties
    # 38 connections in controller Adaptation, 3 in module Turtlebot; RoboArch's 3 repeat
    # the module's and are notes
    assert len(plan.connections) == 41
    repeats = [d for d in navigation.diagnostics if "repeats the one at" in d.message]
    assert [Path(d.file).name for d in repeats] == ["turtlebot.rac"] * 3
    library = [d for d in navigation.diagnostics if "RoboChart's own library" in d.message]
    assert {Path(d.file).name for d in library} >= {"Adaptation_Plan.rct"}
    assert plan.components["Adaptation"].ports["laserScan"].direction == "in-out"
    for finding in model_findings(plan):
        assert navigation.locate(finding.loc) is not None, finding.message
