"""The AADL importer on small models written for RAP: ``fixtures/aadl_import/`` (a lidar
loop: types with the Data_Model annex, a managing system, a device array, a machine with
an address, a bus) and inline designs, one per diagnostic, each checked with its line."""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import msgspec
import pytest
from rap_cli.aadl import parse_aadl
from rap_cli.designs import checked_import
from rap_cli.exporters.aadl import PROPERTY_SET
from rap_cli.importers import Imported
from rap_cli.importers.aadl import import_aadl
from rap_cli.importers.aadl_rap import BUILTIN_SOURCE, builtin_property_sets
from rap_schemas.maplek import Stage
from rap_schemas.model import model_findings
from rap_schemas.plan import DeploymentPlan, plan_findings

FIXTURES = Path(__file__).parent / "fixtures" / "aadl_import"
SCHEMA = Path(__file__).parents[3] / "schemas" / "json" / "rap.DeploymentPlan.schema.json"


def _plan(imported: Imported) -> DeploymentPlan:
    assert imported.plan is not None, [str(d) for d in imported.diagnostics]
    return imported.plan


@pytest.fixture(scope="module")
def loop() -> Imported:
    return import_aadl(sorted(FIXTURES.glob("*.aadl")))


def _write(tmp_path: Path, **files: str) -> list[Path]:
    paths = []
    for name, text in files.items():
        path = tmp_path / f"{name}.aadl"
        path.write_text(text, encoding="utf-8")
        paths.append(path)
    return paths


def _found(imported: Imported, severity: str) -> list[tuple[str, int, str]]:
    return [
        (Path(d.file).stem, d.line, d.message)
        for d in imported.diagnostics
        if d.severity == severity
    ]


# ------------------------------------------------------------------ the loop fixture


def test_loop_imports_without_diagnostics(loop: Imported) -> None:
    assert [str(d) for d in loop.diagnostics if d.severity != "note"] == []
    plan = _plan(loop)
    assert plan.system == "robot"
    assert plan_findings(plan) is not None
    assert list(plan_findings(plan)) == []


def test_loop_plan_converts_and_validates_against_the_json_schema(loop: Imported) -> None:
    plan = _plan(loop)
    data = msgspec.to_builtins(plan)
    assert msgspec.convert(data, DeploymentPlan) == plan
    schema = json.loads(SCHEMA.read_text(encoding="utf-8"))
    jsonschema.validate(json.loads(msgspec.json.encode(plan)), schema)


def test_messages_from_the_data_model_annex(loop: Imported) -> None:
    messages = _plan(loop).messages
    assert set(messages) == {"Scan", "Mask", "Verdict"}  # Ranges is an array: a type
    scan = {f: s.type for f, s in messages["Scan"].fields.items()}
    assert scan == {"stamp": "uint64", "ranges": "list[float32, 360]"}
    # Mask and Mask.impl are one message, with the implementation's fields
    assert {f: s.type for f, s in messages["Mask"].fields.items()} == {
        "values": "bool",
        "verdict": "Verdict",
    }
    assert messages["Verdict"].enum == ["accept", "reject"]
    where = loop.where[("messages", "Scan", "fields", "ranges")]
    assert (Path(where.file).name, where.line) == ("types.aadl", 15)


def test_components_stages_ports_and_origin(loop: Imported) -> None:
    components = _plan(loop).components
    assert set(components) == {"sensors_1", "sensors_2", "m", "l"}
    m = components["m"]
    assert m.stage is Stage.MONITOR
    assert m.origin == "aadl process Loop::monitor.impl at managingSys.m"
    assert {n: (p.direction, p.kind, p.type) for n, p in m.ports.items()} == {
        "scan": ("in", "event-data", "Scan"),
        "mask": ("out", "event-data", "Mask"),
    }
    assert components["l"].stage is Stage.LEGITIMATE
    assert components["l"].ports["start"].type is None
    where = loop.where[("components", "m", "ports", "scan")]
    assert (Path(where.file).name, where.line) == ("loop.aadl", 7)


def test_devices_are_external_and_arrays_are_numbered(loop: Imported) -> None:
    components = _plan(loop).components
    for name in ("sensors_1", "sensors_2"):
        device = components[name]
        assert (device.role, device.external, device.node) == ("device", True, "edge")
        assert device.origin == f"aadl device Loop::lidar at {name}"


def test_threads_modes_and_dispatch(loop: Imported) -> None:
    components = _plan(loop).components
    reader = components["m"].threads["reader"]
    assert reader.dispatch is not None
    assert (reader.dispatch.kind, reader.dispatch.rate_hz) == ("periodic", 10.0)
    assert components["m"].dispatch == reader.dispatch  # one thread: the process's
    legit = components["l"]
    assert legit.modes == ["Idle", "Busy"]
    assert {n: t.in_modes for n, t in legit.threads.items()} == {
        "idle": ["Idle"],
        "busy": ["Busy"],
    }
    first, second = legit.mode_transitions
    assert (first.from_, first.to, first.triggers) == ("Idle", "Busy", ["start"])
    assert (second.from_, second.to, second.triggers) == ("Busy", "Idle", [])
    assert "busy.done" in (second.origin or "")
    assert legit.dispatch is not None
    assert (legit.dispatch.kind, legit.dispatch.rate_hz) == ("sporadic", 50.0)


def test_compute_nodes_addresses_and_bindings(loop: Imported) -> None:
    plan = _plan(loop)
    # board.impl has an address and one processor: the machine keeps its name
    assert {n: c.address for n, c in plan.compute_nodes.items()} == {
        "edge": "10.0.0.2",
        "main": "10.0.0.1",
    }
    assert "edge.cpu0" in (plan.compute_nodes["edge"].origin or "")
    assert plan.components["m"].node == "main"
    assert plan.components["l"].node == "edge"
    assert plan.buses["eth"].nodes == ["edge", "main"]
    assert plan.buses["eth"].kind == "net"


def test_connections_flattened_across_the_system_boundary(loop: Imported) -> None:
    plan = _plan(loop)
    assert [(c.name, c.from_, c.to, c.bus) for c in plan.connections] == [
        ("c0/c1", "sensors_1.scan", "m.scan", "eth"),
        ("c0/c1_2", "sensors_2.scan", "m.scan", "eth"),
        ("c2", "m.mask", "l.mask", None),
    ]
    where = loop.where[("connections", 0)]
    assert (Path(where.file).name, where.line) == ("loop.aadl", 108)
    # the system feature's topic goes to the process port inside
    scan = plan.components["m"].ports["scan"]
    assert scan.topic == "scan"


def test_model_findings_are_located(loop: Imported) -> None:
    plan = _plan(loop)
    located = {f.message.split(" ")[1]: loop.locate(f.loc) for f in model_findings(plan)}
    start = located["l.start"]
    assert start is not None
    assert (Path(start.file).name, start.line) == ("loop.aadl", 33)


# ------------------------------------------------------------------ diagnostics

SYSTEM = """package S
public
  with T;
  process P
  features
    o: out event port;
    i: in event port;
  end P;
  process implementation P.impl
  end P.impl;
  processor cpu
  end cpu;
  system top
  end top;
  system implementation top.impl
  subcomponents
    a: process P.impl;
    b: process P.impl;
    c: processor cpu;
  connections
    k1: port a.o -> b.missing;
  properties
    Actual_Processor_Binding => (reference (nowhere)) applies to a;
  end top.impl;
end S;
"""


def test_missing_with_unknown_feature_and_bad_binding(tmp_path: Path) -> None:
    imported = import_aadl(_write(tmp_path, s=SYSTEM))
    errors = _found(imported, "error")
    warnings = _found(imported, "warning")
    assert [(f, n) for f, n, _ in warnings] == [("s", 3)]  # 'with T', used by nothing
    assert "remove it" in warnings[0][2]
    assert [(f, n) for f, n, _ in errors] == [("s", 21), ("s", 23)]
    assert "b (process S::P.impl) has no feature missing - its features are o, i" in errors[0][2]
    assert "has no subcomponent nowhere - use one of a, b, c" in errors[1][2]
    plan = _plan(imported)
    assert plan.components["a"].node is None


def test_used_missing_package_is_an_error_and_its_classifiers_are_opaque(tmp_path: Path) -> None:
    text = SYSTEM.replace("c: processor cpu;", "c: processor T::cpu;")
    text = text.replace("k1: port a.o -> b.missing;", "k1: port a.o -> b.i;")
    text = text.replace("(reference (nowhere))", "(reference (c))")
    imported = import_aadl(_write(tmp_path, s=text))
    errors = _found(imported, "error")
    assert [(f, n) for f, n, _ in errors] == [("s", 3)]
    assert "package T" in errors[0][2]
    plan = _plan(imported)
    assert plan.components["a"].node == "c"
    assert plan.compute_nodes["c"].origin == "aadl processor c (T::cpu)"


def test_unresolved_classifier(tmp_path: Path) -> None:
    text = SYSTEM.replace("b: process P.impl;", "b: process Q.impl;")
    imported = import_aadl(_write(tmp_path, s=text))
    errors = _found(imported, "error")
    assert ("s", 18) in [(f, n) for f, n, _ in errors]
    (message,) = [m for _, n, m in errors if n == 18]
    assert "Q.impl is not declared in package S" in message


BOUNDARY = """package B
public
  process P
  features
    o: out event data port;
    i: in event data port;
  end P;
  system inner
  features
    x: in event data port;
    y: out event data port;
  end inner;
  system implementation inner.impl
  subcomponents
    q: process P;
  end inner.impl;
  system top
  end top;
  system implementation top.impl
  subcomponents
    p: process P;
    s: system inner.impl;
  connections
    c1: port p.o -> s.x;
    c2: port s.y -> p.i;
  end top.impl;
end B;
"""


def test_system_port_connected_to_nothing_inside(tmp_path: Path) -> None:
    imported = import_aadl(_write(tmp_path, b=BOUNDARY))
    warnings = _found(imported, "warning")
    assert [(f, n) for f, n, _ in warnings] == [("b", 10), ("b", 11)]
    assert "goes nowhere" in warnings[0][2]
    assert "q.i" in warnings[0][2]  # the port inside it could go to
    assert "starts from nothing" in warnings[1][2]
    assert _plan(imported).connections == []


UNITS = """property set U is
  Speed: aadlreal units (mps, kmph => mps * 3) applies to (system);
end U;
"""


def test_undefined_unit(tmp_path: Path) -> None:
    text = SYSTEM.replace("  with T;\n", "  with U;\n").replace(
        "  end top;", "  properties\n    U::Speed => 3.0 mph;\n  end top;"
    )
    text = text.replace("b.missing", "b.i").replace("(reference (nowhere))", "(reference (c))")
    imported = import_aadl(_write(tmp_path, s=text, u=UNITS))
    errors = _found(imported, "error")
    assert [(f, n) for f, n, _ in errors] == [("s", 15)]
    assert "the unit mph of U::Speed" in errors[0][2]
    assert "use one of mps, kmph" in errors[0][2]


TWO_CPUS = """package D
public
  processor cpu
  end cpu;
  process P
  end P;
  system box
  end box;
  system implementation box.impl
  subcomponents
    c1: processor cpu;
    c2: processor cpu;
  end box.impl;
  system top
  end top;
  system implementation top.impl
  subcomponents
    p: process P;
    b: system box.impl;
  properties
    Actual_Processor_Binding => (reference (b)) applies to p;
  end top.impl;
end D;
"""


def test_binding_to_a_system_with_two_processors(tmp_path: Path) -> None:
    imported = import_aadl(_write(tmp_path, d=TWO_CPUS))
    errors = _found(imported, "error")
    assert [(f, n) for f, n, _ in errors] == [("d", 21)]
    assert "holds 2 processors (b.c1, b.c2) - name one of them" in errors[0][2]
    one = import_aadl(_write(tmp_path, d=TWO_CPUS.replace("    c2: processor cpu;\n", "")))
    assert _plan(one).components["p"].node == "b.c1"


def test_root_choice_and_bad_root(tmp_path: Path) -> None:
    text = TWO_CPUS.replace(
        "end D;",
        "  system other\n  end other;\n"
        "  system implementation other.impl\n  end other.impl;\nend D;",
    )
    paths = _write(tmp_path, d=text)
    imported = import_aadl(paths)
    assert _plan(imported).system == "top"
    notes = [m for _, _, m in _found(imported, "note") if "root systems" in m]
    assert len(notes) == 1
    assert "D::other.impl" in notes[0]
    assert _plan(import_aadl(paths, root="other.impl")).components == {}
    bad = import_aadl(paths, root="nothing.impl")
    assert bad.plan is None
    (error,) = [m for _, _, m in _found(bad, "error")]
    assert "D::top.impl, D::other.impl" in error


def test_syntax_errors_reject_the_design(tmp_path: Path) -> None:
    imported = import_aadl(_write(tmp_path, x="package X\npublic\n  system s\nend X;\n"))
    assert imported.plan is None
    assert not imported.readable
    assert imported.diagnostics[0].severity == "error"
    assert imported.diagnostics[0].line > 0


def test_data_types_only(tmp_path: Path) -> None:
    imported = import_aadl([FIXTURES / "types.aadl"])
    plan = _plan(imported)
    assert {f: s.type for f, s in plan.messages["Ranges"].fields.items()} == {
        "value": "list[float32, 360]"
    }
    assert plan.compute_nodes == {}


def test_bidirectional_and_array_connection(tmp_path: Path) -> None:
    text = BOUNDARY.replace("c2: port s.y -> p.i;", "").replace(
        "c1: port p.o -> s.x;", "c1: port p.o <-> s.x;"
    )
    text = text.replace("q: process P;", "q: process P[2];").replace(
        "  end inner.impl;", "  connections\n    i1: port x <-> q.i;\n  end inner.impl;"
    )
    imported = import_aadl(_write(tmp_path, b=text))
    conns = _plan(imported).connections
    assert [(c.from_, c.to, c.bidirectional, c.name) for c in conns] == [
        ("p.o", "q_1.i", True, "c1/i1"),
        ("p.o", "q_2.i", True, "c1/i1_2"),
    ]


_RAP_DESIGN = """
package d
public
  with RAP;
  data W
  properties
    RAP::Wire_Type => "rap.LaserScan/2";
  end W;
  process monitor
  features
    scan: in data port W {RAP::Name => "scan-in"; Opaque_Prop => 3;};
  properties
    RAP::Role => "managed";
    RAP::Reads => ("laser_scan");
  end monitor;
  process implementation monitor.impl
  end monitor.impl;
  system top
  end top;
  system implementation top.impl
  subcomponents
    monitor: process monitor.impl {RAP::Name => "robot-1";};
  end top.impl;
end d;
"""


def test_rap_properties_decide_over_inference_and_stay_out_of_properties(
    tmp_path: Path,
) -> None:
    imported = import_aadl(_write(tmp_path, RAP=PROPERTY_SET, d=_RAP_DESIGN))
    plan = _plan(imported)
    comp = plan.components["robot-1"]
    assert comp.stage is None  # the name says monitor, but RAP::Role decides
    assert (comp.role, comp.reads, comp.properties) == ("managed", ["laser_scan"], {})
    port = comp.ports["scan-in"]
    assert (port.type, port.properties) == ("rap.LaserScan/2", {"Opaque_Prop": "3"})
    assert plan.messages == {}  # a wire type is no message


_STAGED = """
package s
public
  with RAP;
  process analysis
  features
    go: in event port {RAP::Topic => "new-data";};
  properties
    RAP::Writes => ("anomaly");
  end analysis;
  process implementation analysis.impl
  subcomponents
    fast: thread worker {Dispatch_Protocol => Periodic; Period => 100 ms;};
    slow: thread worker {Dispatch_Protocol => Periodic; Period => 500 ms;};
  end analysis.impl;
  process plan
  properties
    RAP::Stage => plan;
    RAP::Dispatch => sporadic;
    RAP::Rate_Hz => 2.0;
  end plan;
  process implementation plan.impl
  subcomponents
    tick: thread worker {Dispatch_Protocol => Periodic; Period => 100 ms;};
  end plan.impl;
  thread worker
  end worker;
  system top
  end top;
  system implementation top.impl
  subcomponents
    analysis: process analysis.impl;
    plan: process plan.impl;
  properties
    RAP::Knowledge_Backend => "memory";
  end top.impl;
end s;
"""


def test_rap_property_set_is_built_in(tmp_path: Path) -> None:
    # no RAP.aadl among the files: the importer knows the set `rap export aadl` writes
    imported = import_aadl(_write(tmp_path, d=_RAP_DESIGN))
    assert [str(d) for d in imported.diagnostics if d.severity != "note"] == []
    comp = _plan(imported).components["robot-1"]
    assert (comp.role, comp.reads) == ("managed", ["laser_scan"])
    # a RAP.aadl of the user's own is used instead, even one that differs
    own = PROPERTY_SET.replace("end RAP;", "  Extra: aadlstring applies to (all);\nend RAP;")
    imported = import_aadl(_write(tmp_path, RAP=own, d=_RAP_DESIGN))
    assert [str(d) for d in imported.diagnostics if d.severity != "note"] == []
    assert "robot-1" in _plan(imported).components
    # the built-in set is added only for a design that names RAP and does not declare it
    named, _ = parse_aadl(_RAP_DESIGN, "d.aadl")
    bare, _ = parse_aadl(_RAP_DESIGN.replace("with RAP;", ""), "d.aadl")
    given, _ = parse_aadl(PROPERTY_SET, "RAP.aadl")
    assert named is not None
    assert bare is not None
    assert given is not None
    assert [f.source for f in builtin_property_sets([named])] == [BUILTIN_SOURCE]
    assert builtin_property_sets([bare]) == []
    assert builtin_property_sets([named, given]) == []


def test_a_process_without_rap_stage_gets_its_stage_and_dispatch_inferred(
    tmp_path: Path,
) -> None:
    plan = _plan(import_aadl(_write(tmp_path, s=_STAGED)))
    analysis = plan.components["analysis"]
    assert analysis.stage == Stage.ANALYSE  # from its name: RAP::Writes says no stage
    assert analysis.writes == ["anomaly"]
    assert analysis.dispatch is not None
    assert (analysis.dispatch.kind, analysis.dispatch.rate_hz) == ("periodic", 10.0)
    threads = {
        n: (t.dispatch.kind, t.dispatch.rate_hz) for n, t in analysis.threads.items() if t.dispatch
    }
    assert threads == {"fast": ("periodic", 10.0), "slow": ("periodic", 2.0)}
    staged = plan.components["plan"]
    assert staged.stage == Stage.PLAN
    assert staged.dispatch is not None  # RAP::Dispatch and RAP::Rate_Hz win over the thread's
    assert (staged.dispatch.kind, staged.dispatch.rate_hz) == ("sporadic", 2.0)
    assert staged.threads["tick"].dispatch is not None
    # the root says the design says everything: nothing is inferred
    said = _STAGED.replace('RAP::Knowledge_Backend => "memory";', "RAP::Infer => false;")
    plan = _plan(import_aadl(_write(tmp_path, s=said)))
    analysis = plan.components["analysis"]
    assert (analysis.stage, analysis.dispatch) == (None, None)
    assert set(analysis.threads) == {"fast", "slow"}  # threads keep their own dispatch
    assert analysis.threads["fast"].dispatch is not None


_UNITS = """
package u
public
  with Base_Types, Data_Model, RAP;
  data Time
  properties
    Data_Model::Data_Representation => Float;
    Data_Model::Measurement_Unit => "s";
  end Time;
  data Fix
  end Fix;
  data implementation Fix.impl
  subcomponents
    t: data Time;
    x: data Base_Types::Float_64 {
      RAP::Doc => "North position."; Data_Model::Measurement_Unit => "m";};
    n: data Base_Types::Integer_64 {RAP::Constraints => "ge=1";};
    w: data Base_Types::Float_64 {RAP::Constraints => "ge=0.0; le=2.5";};
  end Fix.impl;
end u;
"""


def test_measurement_units_end_the_field_docs_and_constraints_keep_their_type(
    tmp_path: Path,
) -> None:
    plan = _plan(import_aadl(_write(tmp_path, u=_UNITS)))
    fields = plan.messages["Fix"].fields
    assert (fields["t"].doc, fields["x"].doc) == ("unit: s", "North position. (unit: m)")
    assert (fields["n"].ge, fields["w"].ge, fields["w"].le) == (1, 0.0, 2.5)
    assert (type(fields["n"].ge), type(fields["w"].ge)) == (int, float)


_BUS_REACH = """
package n
public
  process P
  features
    o: out data port;
    i: in data port;
  end P;
  bus Net
  end Net;
  processor CPU
  features
    link: requires bus access Net;
  end CPU;
  system top
  end top;
  system implementation top.impl
  subcomponents
    p: process P;
    q: process P;
    a: processor CPU;
    b: processor CPU;
    net: bus Net;
  connections
    c1: port p.o -> q.i;
    c2: port q.o -> p.i;
    b1: bus access net <-> a.link;
  properties
    Actual_Processor_Binding => (reference (a)) applies to p;
    Actual_Processor_Binding => (reference (b)) applies to q;
    Actual_Connection_Binding => (reference (net)) applies to c1;
  end top.impl;
end n;
"""


def test_check_reports_a_connection_bound_to_a_bus_that_misses_a_node(tmp_path: Path) -> None:
    imported = import_aadl(_write(tmp_path, n=_BUS_REACH))
    plan = _plan(imported)
    assert (plan.buses["net"].nodes, plan.connections[0].bus) == (["a"], "net")
    checked = checked_import(imported, str(tmp_path))
    found = [d for d in checked.diagnostics if "which the bus does not join" in d.message]
    assert len(found) == 1, [str(d) for d in checked.diagnostics]
    assert found[0].severity == "warning"
    assert "q.i runs on compute node 'b'" in found[0].message
    assert Path(found[0].file).name == "n.aadl"
    assert found[0].line > 0
    # joined to both nodes, the bus carries it without a word
    both = _BUS_REACH.replace(
        "b1: bus access net <-> a.link;",
        "b1: bus access net <-> a.link;\n    b2: bus access net <-> b.link;",
    )
    checked = checked_import(import_aadl(_write(tmp_path, n=both)), str(tmp_path))
    assert not [d for d in checked.diagnostics if "does not join" in d.message]
