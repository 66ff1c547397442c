"""The AADL-IL importer on small designs written for these tests (JSON built inline, so
each test shows the construct it maps and the line its diagnostic points at)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import jsonschema
import msgspec
import pytest
from rap_cli.importers import Imported
from rap_cli.importers.aadl_il import import_aadl_il, stage_or_role
from rap_cli.importers.aadl_il_json import json_positions
from rap_schemas.model import model_findings
from rap_schemas.plan import DeploymentPlan

SCHEMA = Path(__file__).parents[3] / "schemas" / "json" / "rap.DeploymentPlan.schema.json"


def _msg(name: str, **fields: str) -> dict[str, Any]:
    return {
        "_name": name,
        "_featureList": [
            {"_name": f, "_featureType": "feature", "_dataType": t} for f, t in fields.items()
        ],
    }


def _port(name: str, direction: str, kind: str, message: dict[str, Any] | None) -> dict[str, Any]:
    return {"_name": name, "_featureType": direction, "_type": kind, "_message": message}


SCAN = _msg("Scan", ranges="Array", stamp="Float_64", count="Natural")
VERDICT = _msg("Verdict", ok="Boolean")


def _design(**changes: Any) -> dict[str, Any]:
    monitor = {
        "_name": "Monitor",
        "_description": "reads the scans",
        "_featureList": [_port("scan", "outport", "data", SCAN)],
        "_threadList": [{"_name": "t", "_eventTrigger": "/scan"}],
        "_formalism": "python",
        "_containerization": True,
    }
    execute = {
        "_name": "Execute",
        "_featureList": [
            _port("scan", "inport", "data", SCAN),
            _port("verdict", "inport", "event data", VERDICT),
            _port("/cmd", "outport", "data event", None),
        ],
        "_threadList": [{"_name": "run", "_eventTrigger": None}],
    }
    cpu = {
        "_name": "cpu",
        "_IP": "10.0.0.2",
        "rap_backbone": True,
        "_propertyList": [{"_name": "MIPSCapacity", "_value": 500.0, "_dataType": "MIPS"}],
        "_bindingList": [{"_name": "Monitor"}, {"_name": "Execute"}],
    }
    design = {
        "_name": "demo system",
        "_systemList": [
            {
                "_name": "managing",
                "_processList": [monitor, execute],
                "_processorList": [cpu],
                "_messageList": [],
            }
        ],
        "_messageList": [SCAN],
    }
    design.update(changes)
    return design


def _import(tmp_path: Path, design: Any) -> tuple[Imported, list[str]]:
    path = tmp_path / "design.json"
    text = json.dumps(design, indent=2)
    path.write_text(text)
    return import_aadl_il(path), text.splitlines()


def _line(lines: list[str], needle: str, nth: int = 0) -> int:
    return [i for i, line in enumerate(lines, 1) if needle in line][nth]


def test_processes_ports_threads_nodes_and_bindings(tmp_path: Path) -> None:
    imported, lines = _import(tmp_path, _design())
    plan = imported.plan
    assert plan is not None
    assert plan.system == "demo_system"
    monitor = plan.components["Monitor"]
    assert (monitor.stage, monitor.node, monitor.doc) == ("monitor", "cpu", "reads the scans")
    assert monitor.properties == {"formalism": "python", "containerization": "true"}
    scan = monitor.ports["scan"]
    assert (scan.direction, scan.kind, scan.type, scan.topic) == ("out", "data", "Scan", "scan")
    assert monitor.threads["t"].dispatch is not None
    assert monitor.threads["t"].dispatch.kind == "sporadic"
    assert monitor.threads["t"].properties == {"event_trigger": "/scan"}
    execute = plan.components["Execute"]
    assert execute.threads["run"].dispatch is None
    assert execute.ports["verdict"].kind == "event-data"
    cmd = execute.ports["cmd"]
    assert (cmd.kind, cmd.type, cmd.topic) == ("event-data", None, "/cmd")
    node = plan.compute_nodes["cpu"]
    assert node.address == "10.0.0.2"
    assert node.properties == {"rap_backbone": "true", "MIPSCapacity": "500.0 MIPS"}
    assert imported.where[("components", "Monitor")].line == _line(lines, '"_name": "Monitor"')
    assert imported.where[("compute_nodes", "cpu", "address")].line == _line(lines, '"_IP"')
    assert imported.where[("components", "Execute", "node")].line == _line(
        lines, '"_name": "Execute"', 1
    )


def test_message_fields_and_data_types(tmp_path: Path) -> None:
    imported, lines = _import(tmp_path, _design())
    assert imported.plan is not None
    fields = imported.plan.messages["Scan"].fields
    assert {f: spec.type for f, spec in fields.items()} == {
        "ranges": "list[float64]",
        "stamp": "float64",
        "count": "int",
    }
    assert fields["count"].ge == 0
    (note,) = [d for d in imported.diagnostics if "Array" in d.message]
    assert note.severity == "note"
    assert note.line == _line(lines, '"_name": "ranges"', 2)  # the declaration, last copy


def test_a_message_the_lists_omit_is_created_with_an_error_at_the_port(tmp_path: Path) -> None:
    imported, lines = _import(tmp_path, _design())
    assert imported.plan is not None
    verdict = imported.plan.messages["Verdict"]
    assert verdict.fields["ok"].type == "bool"
    assert "message lists" in verdict.doc
    (error,) = [d for d in imported.diagnostics if d.severity == "error"]
    assert "uses message 'Verdict', which the design does not declare" in error.message
    assert error.line == _line(lines, '"_name": "verdict"')


def test_a_port_copy_that_differs_from_the_declaration_warns(tmp_path: Path) -> None:
    design = _design()
    process = design["_systemList"][0]["_processList"][0]
    process["_featureList"][0]["_message"] = _msg("Scan", ranges="Float_32")
    imported, lines = _import(tmp_path, design)
    (warning,) = [d for d in imported.diagnostics if d.severity == "warning"]
    assert "differs from its declaration" in warning.message
    assert warning.line == _line(lines, '"_name": "Scan"')


def test_unbound_process_and_model_findings_are_located(tmp_path: Path) -> None:
    design = _design()
    design["_systemList"][0]["_processorList"][0]["_bindingList"] = [{"_name": "Monitor"}]
    imported, lines = _import(tmp_path, design)
    assert imported.plan is not None
    assert imported.plan.components["Execute"].node is None
    (unfed,) = [f for f in model_findings(imported.plan) if "input Execute.verdict" in f.message]
    where = imported.locate(unfed.loc)
    assert where is not None
    assert where.line == _line(lines, '"_name": "verdict"')


def test_binding_errors(tmp_path: Path) -> None:
    design = _design()
    bindings = design["_systemList"][0]["_processorList"][0]["_bindingList"]
    bindings += [{"_name": "Ghost"}, {"_name": "Monitor"}]
    imported, lines = _import(tmp_path, design)
    errors = {
        d.message.split(" - ")[0]: d.line for d in imported.diagnostics if d.severity == "error"
    }
    assert errors["processor 'cpu' binds process 'Ghost', which the design does not declare"] == (
        _line(lines, '"_name": "Ghost"')
    )
    second = [m for m in errors if "bound a second time" in m]
    assert second
    assert errors[second[0]] == _line(lines, '"_name": "Monitor"', 2)


def test_system_features_and_invalid_port_names_are_notes(tmp_path: Path) -> None:
    design = _design()
    design["_systemList"].append(
        {"_name": "managed", "_featureList": [_port("scan", "outport", "event data", SCAN)]}
    )
    imported, lines = _import(tmp_path, design)
    notes = [d for d in imported.diagnostics if d.severity == "note"]
    (system,) = [d for d in notes if "system 'managed'" in d.message]
    assert system.line == _line(lines, '"_name": "managed"')
    assert "no component" in system.message
    (renamed,) = [d for d in notes if "'/cmd' is named 'cmd'" in d.message]
    assert renamed.line == _line(lines, '"_name": "/cmd"')


@pytest.mark.parametrize(
    ("change", "needle", "message"),
    [
        ({"_featureType": "sideport"}, '"sideport"', "use inport, outport or inoutport"),
        ({"_type": "stream"}, '"stream"', "use event, data or event data"),
    ],
)
def test_bad_feature_and_port_types(
    tmp_path: Path, change: dict[str, str], needle: str, message: str
) -> None:
    design = _design()
    design["_systemList"][0]["_processList"][1]["_featureList"][0].update(change)
    imported, lines = _import(tmp_path, design)
    (error,) = [d for d in imported.diagnostics if message in d.message]
    assert error.severity == "error"
    assert abs(error.line - _line(lines, needle)) <= 3


def test_bad_json_is_unreadable_with_its_location(tmp_path: Path) -> None:
    path = tmp_path / "design.json"
    path.write_text('{\n  "_name": "x",\n  "_systemList": [\n    {"_name": }\n  ]\n}\n')
    imported = import_aadl_il(path)
    assert not imported.readable
    assert imported.plan is None
    (error,) = imported.diagnostics
    assert (error.line, error.severity) == (4, "error")
    assert "not valid JSON" in error.message


@pytest.mark.parametrize("content", [b"\xff\xfe", None, b"[1, 2]"])
def test_unreadable_files(tmp_path: Path, content: bytes | None) -> None:
    path = tmp_path / "design.json"
    if content is not None:
        path.write_bytes(content)
    imported = import_aadl_il(path)
    assert not imported.readable
    assert [d.severity for d in imported.diagnostics] == ["error"]


def test_wrong_json_types_are_errors_not_crashes(tmp_path: Path) -> None:
    imported, _ = _import(tmp_path, {"_name": "x", "_systemList": {"a": 1}, "_messageList": [3]})
    assert imported.readable
    assert imported.plan is not None
    assert len([d for d in imported.diagnostics if d.severity == "error"]) == 2


def test_plan_converts_and_validates(tmp_path: Path) -> None:
    imported, _ = _import(tmp_path, _design())
    assert imported.plan is not None
    builtins = msgspec.to_builtins(imported.plan)
    assert msgspec.convert(builtins, DeploymentPlan) == imported.plan
    jsonschema.validate(builtins, json.loads(SCHEMA.read_text()))


def test_json_positions_of_keys_and_items() -> None:
    text = '{\n "a": [1, {"b": "x"}],\n "c": {}\n}'
    assert json_positions(text) == {
        (): (1, 1),
        ("a",): (2, 2),
        ("a", 0): (2, 8),
        ("a", 1): (2, 11),
        ("a", 1, "b"): (2, 12),
        ("c",): (3, 2),
    }


@pytest.mark.parametrize(
    ("name", "stage", "role"),
    [
        ("Monitor", "monitor", None),
        ("Analysis", "analyse", None),
        ("Adaptation_Plan", "plan", None),
        ("Legitimate", "legitimate", None),
        ("execute", "execute", None),
        ("Knowledge", None, "knowledge"),
        ("Driver", None, None),
    ],
)
def test_stage_or_role_from_the_name(name: str, stage: str | None, role: str | None) -> None:
    assert stage_or_role(name) == (stage, role)
