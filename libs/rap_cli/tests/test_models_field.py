"""A component's ``models:`` (the model store's models it may read or write): ``rap
check`` refuses a bad name or access at its line; the access control grants each process
the keys of its components' models and nothing else; ``rap up`` hands the knowledge
service who may write what; AADL carries it as ``RAP::Models`` both ways."""

from __future__ import annotations

import json
from pathlib import Path

import msgspec
from rap_cli.acl import access_control, model_grants, process_grants
from rap_cli.app import app
from rap_cli.deploy import Paths, node_processes
from rap_cli.exporters.aadl import PROPERTY_SET, export_aadl
from rap_cli.importers.aadl import import_aadl
from rap_schemas import keys, load_plan, parse_plan
from rap_schemas.plan import plan_findings
from typer.testing import CliRunner

REPO = Path(__file__).resolve().parents[3]
LIDAR = REPO / "examples/lidar_occlusion/model.yaml"
runner = CliRunner()


def _lidar(tmp_path: Path, *, tls: bool = True) -> Path:
    """The lidar model with the analysis writing model ``occlusion`` and the monitor
    reading it (and ``detector/yolo``)."""
    text = LIDAR.read_text()
    for old, new in (
        ("    writes: [lidar_mask, handling_anomaly]\n", "    models: {occlusion: write}\n"),
        (
            "    writes: [laser_scan, odometry, obstacle_map]\n",
            "    models: {occlusion: read, detector/yolo: read}\n",
        ),
    ):
        assert text.count(old) == 1
        text = text.replace(old, old + new)
    if tls:
        text += "\nfabric:\n  tls: true\n  operators: [ops]\n"
    path = tmp_path / "model.yaml"
    path.write_text(text)
    return path


def test_rap_check_refuses_a_bad_model_name_or_access_at_its_line(tmp_path: Path) -> None:
    model = _lidar(tmp_path, tls=False)
    res = runner.invoke(app, ["check", str(model)])
    assert res.exit_code == 0, res.output
    text = model.read_text()
    bad = text.replace("models: {occlusion: write}", 'models: {"occ*lusion": write}')
    bad = bad.replace("occlusion: read,", "occlusion: rw,")
    model.write_text(bad)
    lines = bad.splitlines()
    name_line = next(i for i, line in enumerate(lines, 1) if "occ*lusion" in line)
    access_line = next(i for i, line in enumerate(lines, 1) if "occlusion: rw" in line)
    res = runner.invoke(app, ["check", str(model)])
    assert res.exit_code == 1
    out = res.output
    at_name = [line for line in out.splitlines() if f"model.yaml:{name_line}:" in line]
    at_access = [line for line in out.splitlines() if f"model.yaml:{access_line}:" in line]
    assert any("'occ*lusion'" in line for line in at_name), out
    assert any("'rw'" in line for line in at_access), out


def test_a_model_built_in_code_is_checked_too() -> None:
    text = (
        "system: demo\ncompute_nodes: {laptop: {}}\ncomponents:\n"
        "  m: {stage: monitor, node: laptop, models: {ok: read}}\n"
    )
    plan = parse_plan(text).plan
    comp = plan.components["m"]
    assert comp.models == {"ok": "read"}
    wrong = msgspec.structs.replace(comp, models={"a/": "read", "b": "all"})
    found = list(plan_findings(msgspec.structs.replace(plan, components={"m": wrong})))
    assert [(loc, key) for loc, _, key in found] == [
        (("components", "m", "models", "a/"), True),
        (("components", "m", "models", "b"), False),
    ]
    assert "is not a model name" in found[0][1]
    assert "write read" in found[1][1]
    assert "or write" in found[1][1]


def test_each_process_may_query_its_components_models_only(tmp_path: Path) -> None:
    plan = load_plan(_lidar(tmp_path)).plan
    grants = process_grants(plan)
    occlusion = keys.kb("demo", "_models/occlusion")
    yolo = keys.kb("demo", "_models/detector/yolo")
    # the edge's runner hosts the analysis (write), the robot's the monitor (read): both
    # a query on the model's key, nothing else on it
    assert occlusion in grants["edge.runner"].may["query"]
    assert yolo not in grants["edge.runner"].may["query"]
    assert {occlusion, yolo} <= set(grants["robot.runner"].may["query"])
    for g in grants.values():
        for message, exprs in g.may.items():
            if message != "query" and g.kind not in ("operator", "router", "knowledge"):
                assert occlusion not in exprs
                assert yolo not in exprs
    # the simulator, the manager: none
    for who in ("robot.robot", "edge.manager"):
        assert not any("_models" in e for e in grants[who].may.get("query", []))
    # operators: everything (the system's whole space)
    assert grants["ops"].may["query"] == [keys.system_pattern("demo")]
    # and the router's rules say so
    acl = access_control(plan)
    subject = next(s["id"] for s in acl["subjects"] if s["cert_common_names"] == ["robot.runner"])
    policy = next(p for p in acl["policies"] if p["subjects"] == [subject])
    rules = [r for r in acl["rules"] if r["id"] in policy["rules"] and "query" in r["messages"]]
    assert any(occlusion in r["key_exprs"] for r in rules)


def test_model_grants_say_who_may_write_and_knowledge_gets_them(tmp_path: Path) -> None:
    model = _lidar(tmp_path)
    doc = load_plan(model)
    assert model_grants(doc.plan) == {
        "edge.runner": {"occlusion": "write"},
        "robot.runner": {"occlusion": "read", "detector/yolo": "read"},
    }
    paths = Paths.local(model, tmp_path / "run", "edge", certs=tmp_path / "certs")
    kb = next(p for p in node_processes(doc, "edge", paths=paths) if p.name == "knowledge")
    argv = list(kb.argv)
    assert json.loads(argv[argv.index("--model-grants") + 1]) == model_grants(doc.plan)
    # without TLS nobody is checked: nothing to hand over
    doc = load_plan(_lidar(tmp_path, tls=False))
    kb = next(p for p in node_processes(doc, "edge", paths=paths) if p.name == "knowledge")
    assert "--model-grants" not in kb.argv


def test_aadl_carries_the_models_both_ways(tmp_path: Path) -> None:
    assert "  Models: list of aadlstring applies to (process);\n" in PROPERTY_SET
    plan = load_plan(_lidar(tmp_path, tls=False)).plan
    exported = export_aadl(plan)
    logical = next(t for n, t in exported.files.items() if n.endswith("_logical.aadl"))
    assert 'RAP::Models => ("occlusion:read", "detector/yolo:read")' in logical
    assert 'RAP::Models => ("occlusion:write")' in logical
    out = tmp_path / "aadl"
    out.mkdir()
    paths = []
    for name, text in exported.files.items():
        (out / name).write_text(text)
        paths.append(out / name)
    back = import_aadl(paths, root=exported.root).plan
    assert back is not None
    assert back.components["monitor"].models == {"occlusion": "read", "detector/yolo": "read"}
    assert back.components["analysis"].models == {"occlusion": "write"}
    assert back.components["planner"].models == {}
