"""The RoboChart importer on designs written for these tests
(``fixtures/robochart_import/``): each mapping to the system model, and each diagnostic
with the line it points at."""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import msgspec
import pytest
from rap_cli.diagnostics import Diagnostic
from rap_cli.importers import Imported
from rap_cli.importers.robochart import import_robochart
from rap_schemas.model import model_findings
from rap_schemas.plan import DeploymentPlan

FIXTURES = Path(__file__).parent / "fixtures" / "robochart_import"
SCHEMA = Path(__file__).parents[3] / "schemas" / "json" / "rap.DeploymentPlan.schema.json"


def _import(*names: str) -> tuple[Imported, DeploymentPlan]:
    imported = import_robochart([FIXTURES / n for n in names])
    assert imported.readable
    assert imported.plan is not None
    return imported, imported.plan


def _line(name: str, needle: str) -> int:
    text = (FIXTURES / name).read_text().splitlines()
    return next(i for i, line in enumerate(text, 1) if needle in line)


def _one(imported: Imported, text: str) -> Diagnostic:
    (found,) = [d for d in imported.diagnostics if text in d.message]
    return found


def test_records_and_field_types() -> None:
    _, plan = _import("types.rct", "loop.rct")
    scan = {f: (s.type, s.ge) for f, s in plan.messages["Scan"].fields.items()}
    assert scan == {
        "ranges": ("list[float]", None),
        "count": ("int", 0),
        "ok": ("bool", None),
        "label": ("str", None),
        "ticks": ("int", None),
    }
    goal = plan.messages["Goal"].fields
    assert goal["targets"].type == "list[Scan]"
    assert goal["targets"].doc == "a set in RoboChart"
    assert goal["where"].type == "Tuple_Float_Float"
    pair = plan.messages["Tuple_Float_Float"].fields
    assert {f: s.type for f, s in pair.items()} == {"item1": "float", "item2": "float"}
    assert plan.messages["Scan"].origin == "robochart datatype rover::types::Scan"


def test_enumerations_and_primitive_types() -> None:
    imported, plan = _import("types.rct", "loop.rct")
    assert plan.messages["Mode"].enum == ["IDLE", "MOVING"]
    assert plan.messages["Opaque"].fields == {}
    assert "no structure" in plan.messages["Opaque"].doc
    assert imported.where[("messages", "Mode")].line == _line("types.rct", "enumeration Mode")


def test_machines_are_components_with_stage_and_behaviour() -> None:
    imported, plan = _import("types.rct", "loop.rct")
    monitor = plan.components["Monitor"]
    assert (monitor.stage, monitor.origin) == ("monitor", "robochart stm rover::loop::Monitor")
    assert monitor.module is None
    assert not monitor.external
    assert monitor.properties["states"] == "i0 (initial), Watch"
    assert monitor.properties["transitions"] == "t0: i0 -> Watch trigger scan ? last"
    assert monitor.properties["consts"] == "window: nat"
    assert monitor.properties["variables"] == "last: Scan"
    assert monitor.properties["interfaces"] == "uses Sensing"
    assert plan.components["Planner"].stage == "plan"
    assert imported.where[("components", "Monitor")].line == _line("loop.rct", "stm Monitor")


def test_controller_and_platform_are_external_components() -> None:
    _, plan = _import("types.rct", "loop.rct")
    brain = plan.components["Brain"]
    assert (brain.role, brain.external) == ("controller", True)
    assert brain.properties["machines"] == "mon = Monitor, pl = Planner"
    body = plan.components["Body"]
    assert (body.role, body.external) == ("platform", True)
    assert plan.system == "Rover"  # the one module


def test_connection_ends_become_ports() -> None:
    imported, plan = _import("types.rct", "loop.rct")
    ports = {
        (c, p): (spec.direction, spec.kind, spec.type)
        for c, comp in plan.components.items()
        for p, spec in comp.ports.items()
    }
    assert ports == {
        ("Brain", "scan"): ("in-out", "event-data", "Scan"),  # fed by the module, passed on
        ("Brain", "mode"): ("in", "event-data", "Mode"),
        ("Monitor", "scan"): ("in", "event-data", "Scan"),
        ("Monitor", "report"): ("out", "event-data", "Scan"),
        ("Monitor", "level"): ("in-out", "event-data", "FloatValue"),  # _bidirec
        ("Planner", "report"): ("in", "event-data", "Scan"),
        ("Planner", "goal"): ("out", "event-data", "Mode"),
        ("Planner", "ping"): ("in-out", "event", None),
        ("Body", "scan"): ("out", "event-data", "Scan"),
    }
    # the port is where its event is declared (interface Sensing), its type there too
    assert imported.where[("components", "Monitor", "ports", "scan")].line == _line(
        "types.rct", "event scan"
    )


def test_primitive_event_types_get_a_wrapper_message() -> None:
    _, plan = _import("types.rct", "loop.rct")
    wrapper = plan.messages["FloatValue"]
    assert {f: s.type for f, s in wrapper.fields.items()} == {"value": "float"}
    assert wrapper.origin == "robochart type real"


def test_connections_with_flags_and_places() -> None:
    imported, plan = _import("types.rct", "loop.rct")
    ends = [(c.from_, c.to, c.bidirectional) for c in plan.connections]
    assert ends == [
        ("Brain.scan", "Monitor.scan", False),
        ("Monitor.report", "Planner.report", False),
        ("Planner.goal", "Brain.mode", False),
        ("Monitor.level", "Planner.ping", True),
        ("Body.scan", "Brain.scan", False),
    ]
    assert plan.connections[1].origin is not None
    assert plan.connections[1].origin.endswith("(_async)")
    assert imported.where[("connections", 3)].line == _line("loop.rct", "on level to pl")


def test_notes_for_what_has_no_place() -> None:
    imported, _ = _import("types.rct", "loop.rct")
    const = _one(imported, "MAX_SPEED")
    assert (const.severity, const.line) == ("note", _line("types.rct", "const MAX_SPEED"))
    unused = _one(imported, "interface rover::types::Unused")
    assert (unused.severity, unused.line) == ("note", _line("types.rct", "interface Unused"))
    assert [d for d in imported.diagnostics if d.severity != "note"] == []


@pytest.mark.parametrize(
    ("text", "needle", "severity"),
    [
        ("none of the given files declares package rover::missing", "rover::missing", "error"),
        ("RoboChart's own library", "sequence_toolkit", "note"),
        ("no interface 'Nowhere'", "uses Nowhere", "error"),
        ("no state machine 'Ghost'", "sref a = Ghost", "error"),
        ("'c' is none of the parts of controller Faulty", "to c on y", "error"),
        ("Lonely has no event 'nope'", "on nope", "error"),
        ("function rover::broken::twice", "function twice", "note"),
        ("state machine rover::broken::Orphan is in no controller", "stm Orphan", "note"),
        ("operation rover::broken::Helper", "operation Helper", "note"),
    ],
)
def test_design_diagnostics_with_their_lines(text: str, needle: str, severity: str) -> None:
    imported, _ = _import("types.rct", "broken.rct")
    found = _one(imported, text)
    assert (found.severity, found.line) == (severity, _line("broken.rct", needle))


def test_a_name_used_without_its_import_warns(tmp_path: Path) -> None:
    (tmp_path / "a.rct").write_text("package a\ndatatype R {\n\tx : real\n}\n")
    (tmp_path / "b.rct").write_text("package b\ndatatype S {\n\tr : R\n}\n")
    imported = import_robochart([tmp_path])
    assert imported.plan is not None
    assert imported.plan.messages["S"].fields["r"].type == "R"
    warning = _one(imported, "'R' is declared in package a, which this file does not import")
    assert (Path(warning.file).name, warning.line, warning.severity) == ("b.rct", 3, "warning")


def test_roboarch_layers_join_controllers_or_become_components() -> None:
    imported, plan = _import("types.rct", "loop.rct", "arch.rac")
    brain = plan.components["Brain"]
    assert brain.properties["roboarch.pattern"] == "MAPLE-K"
    assert brain.properties["roboarch.execute.outputs"] == "mode"
    assert plan.components["Monitor"].properties["roboarch.recorded_data"] == "scans: Seq(Scan)"
    drive = plan.components["Drive"]
    assert drive.role == "layer"
    assert {p: (s.direction, s.type) for p, s in drive.ports.items()} == {
        "path": ("in", "Path"),
        "speed": ("out", "FloatValue"),
    }
    stage = plan.components["Drive.plan"]
    assert (stage.stage, stage.properties) == ("plan", {"roboarch.plan_data": "route: Path"})
    assert _one(imported, "Scan repeats the RoboChart type").line == _line(
        "arch.rac", "datatype Scan"
    )
    assert _one(imported, "layer Brain is the RoboChart controller").line == _line(
        "arch.rac", "layer Brain"
    )
    repeat = _one(imported, "repeats the one at")
    assert repeat.line == _line("arch.rac", "Body on scan to Brain")
    assert plan.messages["Path"].origin == "roboarch datatype Path"


def test_model_findings_point_into_the_design() -> None:
    imported, plan = _import("types.rct", "loop.rct", "arch.rac")
    (mismatch,) = [
        f for f in model_findings(plan) if "sends Mode but Drive.path takes Path" in f.message
    ]
    where = imported.locate(mismatch.loc)
    assert where is not None
    assert (Path(where.file).name, where.line) == ("arch.rac", _line("arch.rac", "Brain on mode"))


def test_roboarch_alone() -> None:
    imported, plan = _import("arch.rac")
    assert plan.system == "Rover"
    assert plan.components["Brain"].role == "layer"
    assert plan.components["Brain.monitor"].stage == "monitor"
    missing = _one(imported, "'Body' is none of the parts")
    assert missing.line == _line("arch.rac", "Body on scan")


def test_plans_convert_and_validate() -> None:
    schema = json.loads(SCHEMA.read_text())
    for names in (("types.rct", "loop.rct", "arch.rac"), ("types.rct", "broken.rct")):
        _, plan = _import(*names)
        builtins = msgspec.to_builtins(plan)
        assert msgspec.convert(builtins, DeploymentPlan) == plan
        jsonschema.validate(builtins, schema)


def test_unreadable_input_is_not_readable(tmp_path: Path) -> None:
    bad = tmp_path / "bad.rct"
    bad.write_text("package p\nstm {\n")
    imported = import_robochart([bad])
    assert not imported.readable
    assert imported.plan is None
    assert [d.severity for d in imported.diagnostics] == ["error"]
    assert imported.diagnostics[0].line == 2
