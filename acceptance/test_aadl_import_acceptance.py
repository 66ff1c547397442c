"""Acceptance: the AADL importer on the real third-party models of the shared design-model
folder (``$DESIGN_MODELS/aadl/``), against the expectations of that folder's README,
"What a correct import yields": the NTNU ship case (with and without the rpio/mbed
properties), OSATE's speed regulation (two mappings), PolyORB's ping, AADLib's Data_Model
types, and the navigation case (a non-standard dialect, rejected with located errors).

Every imported plan also converts back through msgspec (the model's own types), and the
model's own findings (:func:`rap_schemas.model.model_findings`) are located in the
design's files through ``Imported.locate``.
"""

from __future__ import annotations

from pathlib import Path

import msgspec
import pytest
from rap_cli.diagnostics import Diagnostic
from rap_cli.importers import Imported
from rap_cli.importers.aadl import import_aadl
from rap_schemas.maplek import Stage
from rap_schemas.model import model_findings
from rap_schemas.plan import DeploymentPlan

MAPLEK = {"m": "monitor", "a": "analysis", "p": "plan", "l": "legitimate", "e": "execute"}


def _import(design_models: Path, *folders: str, root: str | None = None) -> Imported:
    paths = [p for f in folders for p in sorted((design_models / "aadl" / f).glob("*.aadl"))]
    assert paths, folders
    imported = import_aadl(paths, root=root)
    if imported.plan is not None:
        data = msgspec.to_builtins(imported.plan)
        assert msgspec.convert(data, DeploymentPlan) == imported.plan
    return imported


def _plan(imported: Imported) -> DeploymentPlan:
    assert imported.plan is not None, [str(d) for d in imported.diagnostics]
    return imported.plan


def _at(diagnostics: list[Diagnostic], severity: str, text: str) -> list[tuple[str, int]]:
    """``(file name, line)`` of the diagnostics of ``severity`` whose message has ``text``."""
    return [
        (Path(d.file).name, d.line)
        for d in diagnostics
        if d.severity == severity and text in d.message
    ]


# ------------------------------------------------------------------ NTNU ship


@pytest.fixture(scope="module")
def ship(design_models: Path) -> Imported:
    return _import(design_models, "rpio-ntnu-ship")


def test_ship_messages_and_field_types(ship: Imported) -> None:
    messages = _plan(ship).messages
    fields = {name: {f: s.type for f, s in m.fields.items()} for name, m in messages.items()}
    assert fields["weatherConditions"] == {
        "windDirection": "float64",
        "windSpeed": "float64",
        "windSpeed2": "list[bytes]",  # the array 'Array' gives no Base_Type
    }
    pose = ["SurgeSpeed", "SwaySpeed", "YawRate", "RollAngle", "RollRate", "Heading", "x", "y"]
    assert fields["shipPose"] == dict.fromkeys(pose, "float64")
    assert fields["shipAction"] == {"RudderAngle": "float64", "rpm": "float32"}
    assert fields["predictedPath"] == {"Confidence": "float32", "waypoints": "str"}
    assert messages["shipPose"].origin == "aadl data messages::shipPose"


def test_ship_array_types_are_not_messages(ship: Imported) -> None:
    messages = _plan(ship).messages
    assert not {"ObjectArray", "FloatArray", "Array"} & set(messages)
    # the Boolean ports (pathAnomaly, isLegit) carry a wrapper of the base type
    assert {f: s.type for f, s in messages["Boolean"].fields.items()} == {"value": "bool"}


def test_ship_seven_processes(ship: Imported) -> None:
    components = _plan(ship).components
    assert set(components) == {*MAPLEK, "k", "controlSoftware"}
    for name, type_name in MAPLEK.items():
        comp = components[name]
        assert comp.origin == (
            f"aadl process LogicalArchitecture::{type_name}.impl at managingSystem.{name}"
        )
        assert comp.module is None
        assert comp.role is None
    assert [components[n].stage for n in "maple"] == [
        Stage.MONITOR,
        Stage.ANALYSE,
        Stage.PLAN,
        Stage.LEGITIMATE,
        Stage.EXECUTE,
    ]
    assert components["k"].role == "knowledge"
    assert (
        components["k"].origin == "aadl process LogicalArchitecture::knowledge at managingSystem.k"
    )
    assert components["controlSoftware"].role == "managed"
    monitor = components["m"].ports
    assert {n: (p.direction, p.kind, p.type) for n, p in monitor.items()} == {
        "weatherConditions": ("in", "event-data", "weatherConditions"),
        "shipPose": ("in", "event-data", "shipPose"),
        "shipAction": ("in", "event-data", "shipAction"),
        "pathEstimate": ("out", "event-data", "predictedPath"),
    }
    legit = components["l"].ports
    assert (legit["verifyPlan"].kind, legit["verifyPlan"].type) == ("event", None)


def test_ship_knowledge_ports_are_in_out(ship: Imported) -> None:
    ports = _plan(ship).components["k"].ports
    assert len(ports) == 7
    assert {p.direction for p in ports.values()} == {"in-out"}
    assert ports["isLegit"].type == "Boolean"


def test_ship_legitimate_threads_in_modes(ship: Imported) -> None:
    legit = _plan(ship).components["l"]
    assert legit.modes == ["Initialise", "WaitForSignal", "PerformVerification"]
    assert {n: t.in_modes for n, t in legit.threads.items()} == {
        "Initialise_impl": ["Initialise"],
        "WaitForSignal_impl": ["WaitForSignal"],
        "PerformVerification_impl": ["PerformVerification"],
    }
    steps = [(t.from_, t.to, t.triggers) for t in legit.mode_transitions]
    assert steps == [
        ("Initialise", "WaitForSignal", []),  # a thread's event: in the origin only
        ("WaitForSignal", "PerformVerification", ["verifyPlan"]),
        ("PerformVerification", "WaitForSignal", ["planAccepted"]),
        ("PerformVerification", "WaitForSignal", ["planRejected"]),
    ]
    assert "Initialise_impl.initialisationDone" in (legit.mode_transitions[0].origin or "")


def test_ship_bindings_and_idle_firmware(ship: Imported) -> None:
    plan = _plan(ship)
    assert set(plan.compute_nodes) == {
        "platform.controller.MissionProcessor1",
        "platform.robot.RPI",
        "platform.robot.firmware",
    }
    for name in "mapelk":
        assert plan.components[name].node == "platform.controller.MissionProcessor1"
    assert plan.components["controlSoftware"].node == "platform.robot.RPI"
    assert plan.components_on("platform.robot.firmware") == {}
    origin = plan.compute_nodes["platform.robot.RPI"].origin
    assert origin == "aadl processor platform.robot.RPI (HardwareParts::Cortex_A72.quadcore)"


def test_ship_connections_flattened(ship: Imported) -> None:
    plan = _plan(ship)
    pairs = {(c.name, c.from_, c.to) for c in plan.connections}
    assert ("L1", "k.plan", "l.plan") in pairs
    assert ("M4", "m.pathEstimate", "k.pathEstimate") in pairs
    assert not any("isLegit" in c.from_ and c.from_.startswith("l.") for c in plan.connections)
    where = ship.where[("connections", [c.name for c in plan.connections].index("L1"))]
    assert (Path(where.file).name, where.line) == ("system.aadl", 98)


def test_ship_three_design_diagnostics(ship: Imported) -> None:
    found = ship.diagnostics
    assert _at(found, "error", "package HardwareParts") == [("PhysicalArchitecture.aadl", 3)]
    isolated = _at(found, "error", "names l.isLegit")
    assert isolated == [("system.aadl", 99)]
    (message,) = [d.message for d in found if "names l.isLegit" in d.message]
    assert "plan, verifyPlan, planRejected, planAccepted" in message
    dead = _at(found, "warning", "port predictedPath of managedSystem")
    assert dead == [("system.aadl", 43)]
    (message,) = [d.message for d in found if "port predictedPath of managedSystem" in d.message]
    assert "goes nowhere" in message
    assert "controlSoftware.dataIn" in message
    # nothing else is an error: every classifier of the missing package is opaque, once
    errors = [str(d) for d in found if d.severity == "error"]
    assert len(errors) == 2, errors


def test_ship_model_findings_are_located_in_the_design(ship: Imported) -> None:
    plan = _plan(ship)
    located = []
    for finding in model_findings(plan):
        where = ship.locate(finding.loc)
        assert where is not None, finding
        located.append((Path(where.file).name, where.line, finding.message))
    # the managed system's input, fed by nothing (the connection died at its boundary)
    assert any(
        name == "LogicalArchitecture.aadl" and "input controlSoftware.dataIn" in message
        for name, _, message in located
    )


# ------------------------------------------------------------------ NTNU ship with properties


@pytest.fixture(scope="module")
def ship_docs(design_models: Path) -> Imported:
    return _import(design_models, "rpio-ntnu-ship-docs", "rpio-property-sets")


def test_ship_docs_compute_nodes(ship_docs: Imported) -> None:
    nodes = _plan(ship_docs).compute_nodes
    assert set(nodes) == {"companion", "shipCompute"}
    assert nodes["companion"].address == "192.168.0.115"
    assert nodes["shipCompute"].address == "192.168.0.10"
    assert nodes["companion"].properties["mbed::Clock_Frequency"] == "2.0 GHz"
    assert "companion.cpu" in (nodes["companion"].origin or "")


def test_ship_docs_bindings(ship_docs: Imported) -> None:
    plan = _plan(ship_docs)
    assert {n: c.node for n, c in plan.components.items()} == {
        **dict.fromkeys("mapelk", "companion"),
        "controlSoftware": "shipCompute",
    }


def test_ship_docs_knowledge_backend(ship_docs: Imported) -> None:
    plan = _plan(ship_docs)
    kb = plan.knowledge
    assert (kb.backend, kb.node, kb.url) == ("redis", "companion", "redis://192.168.0.115:6379/0")
    props = plan.compute_nodes["companion"].properties
    assert props["rpio_backend.rpio::MQTT_port"] == "1883"
    assert props["rpio_backend.rpio::Redis_port"] == "6379"


def test_ship_docs_topics_and_dispatch(ship_docs: Imported) -> None:
    knowledge = _plan(ship_docs).components["k"]
    ports = knowledge.ports
    assert ports["weatherConditions"].topic == "/weather_condition"
    assert ports["shipPose"].topic == "/ship_status"
    assert ports["pathEstimate"].topic == "/new_model"
    assert ports["shipAction"].topic is None  # Port_MQTT_Override_Topic => false
    weather = ports["weatherConditions"].properties
    assert weather["rpio::Port_Dispatch_Protocol"] == "Periodic"
    assert weather["rpio::Port_Frequency"] == "10.0 Hz"
    assert ports["pathEstimate"].properties["rpio::Port_Dispatch_Protocol"] == "Sporadic"
    assert knowledge.dispatch is not None
    assert (knowledge.dispatch.kind, knowledge.dispatch.rate_hz) == ("periodic", 10.0)


def test_ship_docs_undefined_unit(ship_docs: Imported) -> None:
    lines = _at(ship_docs.diagnostics, "error", "the unit Mbps")
    assert lines == [("PhysicalArchitecture.aadl", n) for n in (69, 76, 81)]
    (first, *_) = [d.message for d in ship_docs.diagnostics if "the unit Mbps" in d.message]
    assert "MBytesps" in first  # the units mbed::BandWidthCapacity accepts


# ------------------------------------------------------------------ OSATE speed regulation


@pytest.fixture(scope="module")
def speed1(design_models: Path) -> Imported:
    return _import(design_models, "osate-speed-regulation", root="integration.implementation1")


def _processes(plan: DeploymentPlan) -> dict[str, str | None]:
    return {
        n: c.node for n, c in plan.components.items() if (c.origin or "").startswith("aadl process")
    }


def test_osate_ten_processes_five_per_ecu(speed1: Imported) -> None:
    plan = _plan(speed1)
    processes = _processes(plan)
    assert len(processes) == 10
    assert sorted(n for n, node in processes.items() if node == "ecu1") == [
        "image_acquisition",
        "obstacle_detection",
        "position_voter",
        "radar_acquisition",
        "speed_estimate",
    ]
    assert sum(node == "ecu2" for node in processes.values()) == 5
    assert plan.buses["can"].nodes == ["ecu1", "ecu2"]
    bound = {c.name: c.bus for c in plan.connections if c.bus}
    assert set(bound) == {"c080", "c120", "c130", "c140", "c150", "c180", "c190"}
    assert set(bound.values()) == {"can"}
    devices = [n for n, c in plan.components.items() if c.role == "device"]
    assert len(devices) == 9
    assert all(plan.components[d].external for d in devices)
    thread = plan.components["image_acquisition"].threads["thr_acq"]
    assert thread.dispatch is not None
    assert thread.dispatch.rate_hz == pytest.approx(20.0)


def test_osate_second_mapping(design_models: Path) -> None:
    imported = _import(design_models, "osate-speed-regulation", root="integration.implementation2")
    plan = _plan(imported)
    processes = _processes(plan)
    first = _plan(
        _import(design_models, "osate-speed-regulation", root="integration.implementation1")
    )
    assert set(processes) == set(_processes(first))  # the same software, mapped again
    assert processes["position_voter"] == "ecu2"
    assert sum(node == "ecu3" for node in processes.values()) == 5
    assert {n: b.nodes for n, b in plan.buses.items()} == {
        "bus1": ["ecu1", "ecu3"],
        "bus2": ["ecu2", "ecu3"],
    }


def test_osate_root_choice(design_models: Path) -> None:
    imported = _import(design_models, "osate-speed-regulation")
    notes = [d.message for d in imported.diagnostics if "root systems" in d.message]
    assert len(notes) == 1
    assert "--root" in notes[0]
    bad = _import(design_models, "osate-speed-regulation", root="integration.nope")
    assert bad.plan is None
    (message,) = [d.message for d in bad.diagnostics if d.severity == "error"]
    assert "integration.implementation1" in message
    assert "integration.implementation2" in message


# ------------------------------------------------------------------ PolyORB ping


def test_polyorb_two_nodes_one_connection_over_a_bus(design_models: Path) -> None:
    imported = _import(design_models, "polyorb-ping")
    plan = _plan(imported)
    assert set(plan.compute_nodes) == {"CPU_A", "CPU_B"}
    assert plan.compute_nodes["CPU_A"].address == "127.0.0.1"
    assert {n: list(plan.components_on(n)) for n in plan.compute_nodes} == {
        "CPU_A": ["Node_A"],
        "CPU_B": ["Node_B"],
    }
    (conn,) = plan.connections
    assert (conn.from_, conn.to, conn.bus) == ("Node_A.Out_Port", "Node_B.In_Port", "the_bus")
    port = plan.components["Node_A"].ports["Out_Port"]
    assert (port.kind, port.type) == ("event-data", "Simple_Type")
    assert plan.buses["the_bus"].nodes == ["CPU_A", "CPU_B"]
    dispatch = plan.components["Node_A"].dispatch
    assert dispatch is not None
    assert (dispatch.kind, dispatch.rate_hz) == ("periodic", 0.5)
    assert [d for d in imported.diagnostics if d.severity == "error"] == []


# ------------------------------------------------------------------ AADLib Data_Model


def test_aadlib_data_model_types(design_models: Path) -> None:
    plan = _plan(_import(design_models, "aadlib-data-model"))
    msgs = plan.messages

    def types(name: str) -> dict[str, str]:
        return {f: s.type for f, s in msgs[name].fields.items()}

    assert types("One_Dimension_Array") == {"value": "list[int, 42]"}
    assert types("Two_Dimensions_Array") == {"value": "list[list[int, 75], 74]"}
    assert types("A_Struct1") == {"f1": "float", "c2": "str"}
    assert types("A_Struct2") == {"f1": "float", "c2": "str"}
    assert types("A_Union1") == {"f1": "optional[float]", "f2": "optional[str]"}
    assert types("A_Union2") == {"f1": "optional[float]", "c2": "optional[str]"}
    assert msgs["An_Enum"].enum == ["foo", "bar"]
    assert types("A_Kanji") == {"value": "str"}
    assert msgs["C_Type"].fields == {}
    assert "opaque" in msgs["C_Type"].doc
    assert [f for f in model_findings(plan) if f.severity == "error"] == []


# ------------------------------------------------------------------ navigation case


def test_navigation_dialect_rejected_with_located_errors(design_models: Path) -> None:
    imported = _import(design_models, "navigation-case-study")
    assert imported.plan is None
    assert not imported.readable
    errors = [d for d in imported.diagnostics if d.severity == "error"]
    assert len(errors) == 30
    assert all(Path(d.file).name == "navigation.aadl" and d.line > 0 for d in errors)
    assert sum("'for' after an implementation name" in d.message for d in errors) == 29
