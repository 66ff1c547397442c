"""``rap check`` and ``rap model show`` on models written for these tests: every
planted defect is found at its line, several per run, with the exit codes the command
documents."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from rap_cli.app import app
from rap_cli.model_io import check_model_text
from rap_schemas.model import TypeSyntaxError, parse_type
from typer.testing import CliRunner

GOOD = """\
system: demo
compute_nodes:
  laptop: {address: 127.0.0.1}
messages:
  Mask:
    fields:
      occluded: {type: "list[bool, 360]"}
      mode: {type: Mode}
  Mode: {enum: [SPIN, WAIT]}
components:
  robot:
    role: managed
    external: true
    node: laptop
    ports:
      scan: {direction: out, kind: data, type: rap.LaserScan/2, topic: tb1/scan}
      spin: {direction: in, kind: data, type: rap.SpinPlan/1, topic: tb1/spin_config}
  monitor:
    stage: monitor
    node: laptop
    ports:
      scan: {direction: in, kind: data, type: rap.LaserScan/2, topic: tb1/scan}
      new_data: {direction: out, kind: event}
    writes: [laser_scan]
  analysis:
    stage: analyse
    node: laptop
    ports:
      new_data: {direction: in, kind: event}
      anomaly: {direction: out, type: Mask}
    reads: [laser_scan]
  planner:
    stage: plan
    node: laptop
    ports:
      anomaly: {direction: in, type: Mask}
      proposal: {direction: out, type: rap.PlanProposal/1}
  legitimate:
    stage: legitimate
    node: laptop
    ports:
      proposal: {direction: in, type: rap.PlanProposal/1}
      verdict: {direction: out, type: rap.Verdict/1}
  executor:
    stage: execute
    node: laptop
    ports:
      verdict: {direction: in, type: rap.Verdict/1}
      spin: {direction: out, kind: data, type: rap.SpinPlan/1, topic: tb1/spin_config}
connections:
  - {from: monitor.new_data, to: analysis.new_data}
  - {from: analysis.anomaly, to: planner.anomaly}
  - {from: planner.proposal, to: legitimate.proposal}
  - {from: legitimate.verdict, to: executor.verdict}
"""


def _lines(text: str, source: str = "m.yaml") -> list[str]:
    return [str(d) for d in check_model_text(text, source).diagnostics]


def _planted(old: str, new: str) -> list[str]:
    assert old in GOOD, old
    return _lines(GOOD.replace(old, new, 1))


def test_the_good_model_has_no_finding() -> None:
    checked = check_model_text(GOOD, "m.yaml")
    assert checked.diagnostics == []
    assert checked.ok


@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        (  # an input nobody produces
            "  - {from: monitor.new_data, to: analysis.new_data}\n",
            "",
            "m.yaml:29:7: error: input analysis.new_data is connected to nothing",
        ),
        (  # an output nobody consumes
            "  - {from: analysis.anomaly, to: planner.anomaly}\n",
            "",
            "m.yaml:30:7: warning: output analysis.anomaly is connected to nothing",
        ),
        (  # a type mismatch across a connection
            "anomaly: {direction: in, type: Mask}",
            "anomaly: {direction: in, type: Mode}",
            "m.yaml:52:5: error: analysis.anomaly sends Mask but planner.anomaly takes Mode",
        ),
        (  # a component bound to no node
            "    stage: plan\n    node: laptop\n",
            "    stage: plan\n",
            "m.yaml:32:3: error: component 'planner' is bound to no compute node",
        ),
        (  # a node that does not exist
            "    stage: legitimate\n    node: laptop\n",
            "    stage: legitimate\n    node: server\n",
            "m.yaml:40:11: error: component 'legitimate' is mapped to compute node 'server'",
        ),
        (  # a message that does not exist
            "anomaly: {direction: out, type: Mask}",
            "anomaly: {direction: out, type: Masq}",
            "m.yaml:30:39: error: port analysis.anomaly carries 'Masq', which is not a message",
        ),
        (  # a field type that does not exist
            'occluded: {type: "list[bool, 360]"}',
            'occluded: {type: "list[boolean, 360]"}',
            "m.yaml:7:24: error: field Mask.occluded: type 'boolean' is neither a scalar",
        ),
        (  # duplicate names (differing in case)
            "  Mode: {enum: [SPIN, WAIT]}\n",
            "  Mode: {enum: [SPIN, WAIT]}\n  mode: {enum: [X]}\n",
            "m.yaml:10:3: error: messages: 'mode' and 'Mode' differ only in case",
        ),
        (  # a knowledge key read but never written
            "reads: [laser_scan]",
            "reads: [laser_scan, lidar_mask]",
            "m.yaml:31:25: error: component 'analysis' reads knowledge key 'lidar_mask'",
        ),
        (  # execute reachable without the Legitimate gate
            "  - {from: legitimate.verdict, to: executor.verdict}\n",
            "  - {from: planner.proposal, to: executor.verdict}\n",
            "m.yaml:54:5: error: plan stage 'planner' reaches execute stage 'executor'",
        ),
    ],
)
def test_each_planted_defect_is_found_at_its_line(old: str, new: str, expected: str) -> None:
    found = _planted(old, new)
    assert any(line.startswith(expected) for line in found), "\n".join(found)
    assert all(" - " in line for line in found)  # each says how to fix it


def test_several_findings_in_one_run() -> None:
    text = GOOD.replace("reads: [laser_scan]", "reads: [laser_scan, x]").replace(
        "    stage: plan\n    node: laptop\n", "    stage: plan\n"
    )
    found = _lines(text)
    assert len(found) == 2
    assert found[0].startswith("m.yaml:31:")
    assert found[1].startswith("m.yaml:32:")


def test_every_schema_error_is_reported_with_its_path() -> None:
    text = GOOD.replace("kind: event}\n    writes", "kind: evnt}\n    writes").replace(
        "direction: in, kind: event}", "direction: inn, kind: event}"
    )
    found = _lines(text)
    assert len(found) == 2, found
    assert found[0].startswith("m.yaml:23:")
    assert "$.components.monitor.ports.new_data.kind: 'evnt' is not one of" in found[0]
    assert found[1].startswith("m.yaml:29:29:")
    assert "'inn' is not one of 'in', 'in-out', 'out'" in found[1]


def test_unknown_fields_point_at_the_key_and_list_the_known_ones() -> None:
    found = _lines(GOOD.replace("  laptop: {address: 127.0.0.1}", "  laptop: {adress: x}"))
    assert found == [
        "m.yaml:3:12: error: $.compute_nodes.laptop: unknown field 'adress' - the fields "
        "here are: address, architecture, connect, doc, listen, origin, properties, resources"
    ]


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("float", "float"),
        ("list[float]", "list[float]"),
        ("list[ list[int8] , 3 ]", "list[list[int8], 3]"),
        ("optional[Mask]", "optional[Mask]"),
    ],
)
def test_field_types_parse(text: str, expected: str) -> None:
    assert str(parse_type(text)) == expected


@pytest.mark.parametrize("text", ["", "list", "list[", "list[float, x]", "float]", "list[]"])
def test_bad_field_types_say_what_was_expected(text: str) -> None:
    with pytest.raises(TypeSyntaxError):
        parse_type(text)


def test_deep_field_types_are_refused_not_a_crash() -> None:
    with pytest.raises(TypeSyntaxError, match="nest"):
        parse_type("list[" * 100 + "int" + "]" * 100)


runner = CliRunner()


def _write(tmp_path: Path, text: str, name: str = "model.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_rap_check_exit_codes(tmp_path: Path) -> None:
    good = _write(tmp_path, GOOD)
    res = runner.invoke(app, ["check", str(good)])
    assert res.exit_code == 0, res.output
    assert "0 error(s), 0 warning(s)" in res.output

    bad = _write(tmp_path, GOOD.replace("reads: [laser_scan]", "reads: [nope]"), "bad.yaml")
    res = runner.invoke(app, ["check", str(bad)])
    assert res.exit_code == 1
    assert f"{bad}:31:" in res.output
    assert "Traceback" not in res.output

    broken = _write(tmp_path, "system: [\n", "broken.yaml")
    res = runner.invoke(app, ["check", str(broken)])
    assert res.exit_code == 2
    assert f"{broken}:" in res.output
    assert "not valid YAML" in res.output

    res = runner.invoke(app, ["check", str(tmp_path / "missing.yaml")])
    assert res.exit_code == 2
    assert "no such file" in res.output


def test_rap_check_takes_a_directory_with_a_model(tmp_path: Path) -> None:
    _write(tmp_path, GOOD)
    assert runner.invoke(app, ["check", str(tmp_path)]).exit_code == 0


def test_model_show_json_has_the_documented_shape(tmp_path: Path) -> None:
    path = _write(tmp_path, GOOD)
    res = runner.invoke(app, ["model", "show", str(path), "--json"])
    assert res.exit_code == 0, res.output
    view = json.loads(res.output)
    assert set(view) == {
        "components",
        "messages",
        "nodes",
        "bindings",
        "connections",
        "diagnostics",
    }
    names = [c["name"] for c in view["components"]]
    assert names == ["robot", "monitor", "analysis", "planner", "legitimate", "executor"]
    monitor = view["components"][1]
    assert monitor["kind"] == "component"
    assert monitor["origin"] == "rap"
    assert monitor["stage"] == "monitor"
    assert monitor["ports"][0] == {
        "name": "scan",
        "direction": "in",
        "kind": "data",
        "type": "rap.LaserScan/2",
    }
    assert view["messages"][0] == {
        "name": "Mask",
        "fields": [
            {"name": "occluded", "type": "list[bool, 360]"},
            {"name": "mode", "type": "Mode"},
        ],
    }
    assert view["nodes"] == [{"name": "laptop", "address": "127.0.0.1"}]
    assert view["bindings"]["executor"] == "laptop"
    # explicit connections first, then those the shared topics imply
    assert view["connections"][0] == {"from": "monitor.new_data", "to": "analysis.new_data"}
    assert {"from": "robot.scan", "to": "monitor.scan"} in view["connections"]
    assert {"from": "executor.spin", "to": "robot.spin"} in view["connections"]
    assert view["diagnostics"] == []


def test_model_show_json_still_prints_a_model_with_errors(tmp_path: Path) -> None:
    path = _write(tmp_path, GOOD.replace("reads: [laser_scan]", "reads: [nope]"))
    res = runner.invoke(app, ["model", "show", str(path), "--json"])
    assert res.exit_code == 1
    view = json.loads(res.output)
    assert len(view["components"]) == 6
    assert view["diagnostics"][0]["line"] == 31
    assert view["diagnostics"][0]["severity"] == "error"


def test_model_show_prints_a_table(tmp_path: Path) -> None:
    res = runner.invoke(app, ["model", "show", str(_write(tmp_path, GOOD))])
    assert res.exit_code == 0, res.output
    assert "components (6):" in res.output
    assert "monitor.new_data -> analysis.new_data" in res.output


REPO = Path(__file__).resolve().parents[3]


@pytest.mark.parametrize(
    "plan",
    sorted((REPO / "examples/lidar_occlusion/src/lidar_occlusion/plans").glob("*.yaml"))
    + sorted((REPO / "bench/loop/plans").glob("*.yaml")),
    ids=lambda p: p.name,
)
def test_every_shipped_deployment_plan_is_a_valid_model(plan: Path) -> None:
    res = runner.invoke(app, ["check", str(plan)])
    assert res.exit_code == 0, res.output


def test_the_lidar_model_is_complete_and_clean() -> None:
    """The model ``make demo`` runs: no finding at all, and its logical architecture
    closes the loop robot -> monitor -> ... -> legitimate -> executor -> robot."""
    model = REPO / "examples/lidar_occlusion/model.yaml"
    checked = check_model_text(model.read_text(), str(model))
    assert checked.diagnostics == []
    res = runner.invoke(app, ["model", "show", str(model), "--json"])
    assert res.exit_code == 0, res.output
    view = json.loads(res.output)
    links = {(c["from"], c["to"]) for c in view["connections"]}
    assert {
        ("robot.scan", "monitor.scan"),
        ("monitor.new_data", "analysis.new_data"),
        ("analysis.anomaly", "planner.anomaly"),
        ("planner.proposal", "legitimate.proposal"),
        ("legitimate.verdict", "executor.verdict"),
        ("executor.spin_config", "robot.spin_config"),
    } <= links
    assert set(view["bindings"].values()) == {"robot", "edge"}
