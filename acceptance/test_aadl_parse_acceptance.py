"""Acceptance: the AADL parser on the real third-party models of the shared design-model
folder, ``$DESIGN_MODELS/aadl/`` (RPIO's ship case, OSATE's speed regulation, PolyORB's
ping, AADLib's Data_Model types, the navigation case, the rpio/mbed property sets).

Run with ``DESIGN_MODELS=<folder> pytest acceptance/test_aadl_parse_acceptance.py -s``:
``-s`` shows, per file, the counts of component types, implementations and connections
and every diagnostic, for a reviewer to check against the files.

Every standard file parses with no error. The navigation case comes from a generator that
writes ``implementation T.impl for T`` (not AADL v2) and names a subcomponent ``data`` (a
reserved word); it is rejected with one located error for each of these, and nothing else.
The checks on content are what the parser must keep for the importer (see the folder's
README): the parser resolves nothing, so they are about what was written, where.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest
from rap_cli.aadl import parse_aadl
from rap_cli.aadl import syntax as s
from rap_cli.diagnostics import Diagnostic

NON_STANDARD = "navigation-case-study/navigation.aadl"
EXPECTED_FILES = {
    "aadlib-data-model/base_types-example_types.aadl",
    "navigation-case-study/messages.aadl",
    NON_STANDARD,
    "osate-speed-regulation/devices.aadl",
    "osate-speed-regulation/error.aadl",
    "osate-speed-regulation/icd.aadl",
    "osate-speed-regulation/integration.aadl",
    "osate-speed-regulation/platform.aadl",
    "osate-speed-regulation/software.aadl",
    "polyorb-ping/ping.aadl",
    "polyorb-ping/software.aadl",
    "rpio-ntnu-ship-docs/LogicalArchitecture.aadl",
    "rpio-ntnu-ship-docs/NTNU_CASE.aadl",
    "rpio-ntnu-ship-docs/PhysicalArchitecture.aadl",
    "rpio-ntnu-ship-docs/messages.aadl",
    "rpio-ntnu-ship/LogicalArchitecture.aadl",
    "rpio-ntnu-ship/PhysicalArchitecture.aadl",
    "rpio-ntnu-ship/messages.aadl",
    "rpio-ntnu-ship/system.aadl",
    "rpio-property-sets/mbed.aadl",
    "rpio-property-sets/rpio.aadl",
}

Parsed = dict[str, tuple[s.AadlFile | None, list[Diagnostic], str]]


def _report(line: str) -> None:
    print(line)  # noqa: T201 - the acceptance report is read by a reviewer (pytest -s)


@pytest.fixture(scope="module")
def aadl_root() -> Path:
    value = os.environ.get("DESIGN_MODELS")
    if not value:
        pytest.fail(
            "DESIGN_MODELS is not set - set it to the shared design-model folder "
            "(the one holding aadl/, aadl-il/ and robochart/)"
        )
    root = Path(value) / "aadl"
    if not root.is_dir():
        pytest.fail(
            f"{root} is not a folder - DESIGN_MODELS={value} must name the shared "
            "design-model folder, which has an aadl/ subfolder"
        )
    return root


@pytest.fixture(scope="module")
def parsed(aadl_root: Path) -> Parsed:
    results: Parsed = {}
    for path in sorted(aadl_root.rglob("*.aadl")):
        name = path.relative_to(aadl_root).as_posix()
        text = path.read_text(encoding="utf-8")
        aadl_file, diagnostics = parse_aadl(text, name)
        results[name] = (aadl_file, diagnostics, text)
    return results


def _file(parsed: Parsed, name: str) -> s.AadlFile:
    aadl_file, diagnostics, _ = parsed[name]
    assert [d for d in diagnostics if d.severity == "error"] == []
    assert aadl_file is not None
    return aadl_file


def _decl(parsed: Parsed, name: str, classifier: str) -> s.Declaration:
    (package,) = _file(parsed, name).packages
    found = package.find(classifier)
    assert found is not None, classifier
    return found


def _impl(parsed: Parsed, name: str, classifier: str) -> s.ComponentImpl:
    found = _decl(parsed, name, classifier)
    assert isinstance(found, s.ComponentImpl)
    return found


def _type(parsed: Parsed, name: str, classifier: str) -> s.ComponentType:
    found = _decl(parsed, name, classifier)
    assert isinstance(found, s.ComponentType)
    return found


def test_report_counts_per_file(parsed: Parsed) -> None:
    assert EXPECTED_FILES <= set(parsed)
    _report("")
    for name, (aadl_file, diagnostics, _) in parsed.items():
        if aadl_file is None:
            counts = "not parsed"
        else:
            declarations = [d for p in aadl_file.packages for d in p.declarations]
            types = [d for d in declarations if isinstance(d, s.ComponentType)]
            impls = [d for d in declarations if isinstance(d, s.ComponentImpl)]
            connections = sum(len(i.connections) for i in impls)
            counts = (
                f"{len(aadl_file.packages)} package(s), {len(aadl_file.property_sets)} "
                f"property set(s), {len(types)} component types, {len(impls)} "
                f"implementations, {connections} connections, {len(aadl_file.notes)} notes"
            )
        _report(f"{name}: {counts}")
        for diagnostic in diagnostics:
            _report(f"    {diagnostic}")


def test_every_standard_model_parses_without_error(parsed: Parsed) -> None:
    for name, (aadl_file, diagnostics, _) in parsed.items():
        if name == NON_STANDARD:
            continue
        assert [str(d) for d in diagnostics if d.severity == "error"] == [], name
        assert aadl_file is not None, name


def test_navigation_dialect_is_rejected_with_one_located_error_per_construct(
    parsed: Parsed,
) -> None:
    aadl_file, diagnostics, text = parsed[NON_STANDARD]
    assert aadl_file is None
    expected = []
    for number, line in enumerate(text.splitlines(), start=1):
        found = re.search(r"\bimplementation\s+\S+\s+(for)\s+(\w+)", line)
        if found:
            message = f"'for' after an implementation name is not AADL v2 - remove 'for {found[2]}'"
            expected.append((number, found.start(1) + 1, message))
        reserved = re.match(r"\s*(data)\s*:", line)
        if reserved:
            message = "'data' is a reserved word of AADL and cannot be used as a name"
            expected.append((number, reserved.start(1) + 1, message))
    assert len(expected) == 30  # 29 'for' clauses, one subcomponent named 'data'
    actual = [(d.line, d.column, d.message) for d in diagnostics]
    assert [(line, column) for line, column, _ in actual] == [(n, c) for n, c, _ in expected]
    for (_, _, message), (_, _, start) in zip(actual, expected, strict=True):
        assert message.startswith(start)
    assert all(d.severity == "error" and d.file == NON_STANDARD for d in diagnostics)


def test_navigation_messages_are_standard(parsed: Parsed) -> None:
    (package,) = _file(parsed, "navigation-case-study/messages.aadl").packages
    assert [d.name for d in package.declarations] == [
        "Direction",
        "SpinConfig",
        "LaserScan",
        "BoolLidarMask",
        "ProbLidarMask",
        "int",
    ]


# ------------------------------------------------------------------ RPIO ship case


def test_ship_processes_ports_and_modes(parsed: Parsed) -> None:
    name = "rpio-ntnu-ship/LogicalArchitecture.aadl"
    for process in ("monitor", "analysis", "plan", "legitimate", "execute", "knowledge"):
        assert _type(parsed, name, process).category == "process"
    knowledge = _type(parsed, name, "knowledge")
    assert {f.direction for f in knowledge.features} == {"in out"}
    assert {f.kind for f in knowledge.features} == {"event data port"}
    legitimate = _type(parsed, name, "legitimate")
    assert [(f.name, f.kind, f.classifier) for f in legitimate.features][1] == (
        "verifyPlan",
        "event port",
        None,
    )
    impl = _impl(parsed, name, "legitimate.impl")
    assert [(c.name, c.category, c.classifier, c.in_modes) for c in impl.subcomponents] == [
        ("Initialise_impl", "thread", "initialise.impl", ("Initialise",)),
        ("WaitForSignal_impl", "thread", "waitingForSignal.impl", ("WaitForSignal",)),
        (
            "PerformVerification_impl",
            "thread",
            "performVerification.impl",
            ("PerformVerification",),
        ),
    ]
    assert [(m.name, m.initial) for m in impl.modes] == [
        ("Initialise", True),
        ("WaitForSignal", False),
        ("PerformVerification", False),
    ]
    first = impl.mode_transitions[0]
    assert (first.sources, first.triggers, first.destination) == (
        ("Initialise",),
        ("Initialise_impl.initialisationDone",),
        "WaitForSignal",
    )


def test_ship_messages_are_data_with_access_features(parsed: Parsed) -> None:
    name = "rpio-ntnu-ship/messages.aadl"
    pose = _type(parsed, name, "shipPose")
    assert [f.name for f in pose.features] == [
        "SurgeSpeed",
        "SwaySpeed",
        "YawRate",
        "RollAngle",
        "RollRate",
        "Heading",
        "x",
        "y",
    ]
    assert {(f.kind, f.access, f.classifier) for f in pose.features} == {
        ("data access", "provides", "Base_Types::Float_64")
    }
    array = _type(parsed, name, "ObjectArray")
    assert [(p.name, type(p.value).__name__) for p in array.properties] == [
        ("Data_Model::Data_Representation", "EnumValue"),
        ("Data_Model::Base_Type", "ListValue"),
    ]


def test_ship_bindings_and_connections_as_written(parsed: Parsed) -> None:
    name = "rpio-ntnu-ship/system.aadl"
    system = _impl(parsed, name, "adaptiveSystem.impl")
    bindings = [
        (p.name, p.value, p.applies_to)
        for p in system.properties
        if s.norm(p.name) == "actual_processor_binding"
    ]
    targets = {}
    for _, value, applies_to in bindings:
        assert isinstance(value, s.ListValue)
        (reference,) = value.items
        assert isinstance(reference, s.ReferenceValue)
        (target,) = applies_to
        targets[target] = reference.path
    assert targets == {
        **{f"managingSystem.{p}": "platform.controller.MissionProcessor1" for p in "mapelk"},
        "managedSystem.controlSoftware": "platform.robot.RPI",
    }
    managing = _impl(parsed, name, "managingSystem.impl")
    (legit,) = [c for c in managing.connections if c.name == "L2"]
    assert (legit.source, legit.dest, legit.loc.line) == ("l.isLegit", "k.isLegit", 99)
    (physical,) = _file(parsed, "rpio-ntnu-ship/PhysicalArchitecture.aadl").packages
    assert physical.withs == ("HardwareParts",)
    robot = physical.find("turtlebot.impl1")
    assert isinstance(robot, s.ComponentImpl)
    assert [(c.kind, c.bidirectional) for c in robot.connections] == [("bus access", True)] * 2


def test_ship_docs_properties_and_undeclared_units(parsed: Parsed) -> None:
    managing = _type(parsed, "rpio-ntnu-ship-docs/NTNU_CASE.aadl", "managingSystem")
    weather = managing.features[0]
    values = {p.name: p.value for p in weather.properties}
    assert values["rpio::Port_MQTT_Topic"] == s.StringValue(
        s.Loc("rpio-ntnu-ship-docs/NTNU_CASE.aadl", 73, 42), "/weather_condition"
    )
    frequency = values["rpio::Port_Frequency"]
    assert isinstance(frequency, s.RealValue)
    assert (frequency.value, frequency.unit) == (10.0, "Hz")
    backend = _type(parsed, "rpio-ntnu-ship-docs/NTNU_CASE.aadl", "robosapiensio_backend")
    assert {p.name: getattr(p.value, "value", None) for p in backend.properties}[
        "rpio::Redis_port"
    ] == 6379

    physical = "rpio-ntnu-ship-docs/PhysicalArchitecture.aadl"
    bus = _type(parsed, physical, "Memory_Bus")
    (_, bandwidth) = bus.properties
    assert isinstance(bandwidth.value, s.RealValue)
    assert (bandwidth.value.value, bandwidth.value.unit) == (23.46, "Mbps")
    companion = _impl(parsed, physical, "LattePanda_Delta_3.impl")
    (address,) = companion.properties
    assert _plain_string(address.value) == "192.168.0.115"

    declared = {
        u.name
        for name in ("rpio-property-sets/rpio.aadl", "rpio-property-sets/mbed.aadl")
        for ps in _file(parsed, name).property_sets
        for u in ps.unit_literals()
    }
    assert declared == {"Hz", "kHz", "MHz", "GHz"}
    assert "Mbps" not in declared  # the importer must report it


def _plain_string(value: s.PropertyValue) -> str:
    assert isinstance(value, s.StringValue)
    return value.value


def test_rpio_property_sets(parsed: Parsed) -> None:
    (rpio,) = _file(parsed, "rpio-property-sets/rpio.aadl").property_sets
    by_name = {d.name: d for d in rpio.definitions}
    assert by_name["Port_MQTT_Topic"].type.kind == "aadlstring"
    assert by_name["Port_Frequency"].type.units_name == "rpio::Processor_Speed_Units"
    assert by_name["Port_Protocol"].applies_to == ("port",)
    enums = {t.name: t.type.enumerators for t in rpio.types if t.type.kind == "enumeration"}
    assert enums["Protocol"] == ("MQTT", "Redis", "WebSocket", "HTTP", "CoAP")
    (mbed,) = _file(parsed, "rpio-property-sets/mbed.aadl").property_sets
    assert mbed.withs == ("SEI",)
    width = {d.name: d for d in mbed.definitions}["Data_Width"]
    assert (width.type.kind, width.type.units_name) == ("aadlinteger", "Size_Units")
    assert width.applies_to[-1] == "access connection"


# ------------------------------------------------------------------ OSATE, PolyORB, AADLib


def test_osate_two_mappings_of_the_same_software(parsed: Parsed) -> None:
    name = "osate-speed-regulation/integration.aadl"
    generic = _impl(parsed, name, "integration.generic")
    assert sum(c.category == "process" for c in generic.subcomponents) == 10
    assert generic.flows_skipped == 23
    first = _impl(parsed, name, "integration.implementation1")
    assert first.extends == "integration.generic"
    bound = {}
    for p in first.properties:
        if p.name == "Actual_Processor_Binding":
            assert isinstance(p.value, s.ListValue)
            (reference,) = p.value.items
            assert isinstance(reference, s.ReferenceValue)
            bound[reference.path] = len(p.applies_to)
    assert bound == {"ecu1": 5, "ecu2": 5}
    assert _impl(parsed, name, "integration.implementation2").extends == "integration.generic"


def test_polyorb_two_nodes_and_a_bound_connection(parsed: Parsed) -> None:
    ping = _impl(parsed, "polyorb-ping/ping.aadl", "PING.Impl")
    assert [c.name for c in ping.subcomponents if c.category == "processor"] == ["CPU_A", "CPU_B"]
    (port,) = [c for c in ping.connections if c.kind == "port"]
    assert (port.name, port.source, port.dest) == (None, "Node_A.Out_Port", "Node_B.In_Port")
    (binding,) = port.properties
    assert binding.name == "Actual_Connection_Binding"
    processor = {p.applies_to: p.value for p in ping.properties}
    assert isinstance(processor[("Node_A",)], s.ReferenceValue)  # written without ( )
    thread = _impl(parsed, "polyorb-ping/software.aadl", "P.Impl")
    period = {p.name: p.value for p in thread.properties}["Period"]
    assert isinstance(period, s.IntValue)
    assert (period.value, period.unit) == (2000, "Ms")


def test_aadlib_data_model_types(parsed: Parsed) -> None:
    name = "aadlib-data-model/base_types-example_types.aadl"
    (package,) = _file(parsed, name).packages
    assert package.name == "Base_Types::Example_Types"

    def props(classifier: str) -> dict[str, s.PropertyValue]:
        return {p.simple_name: p.value for p in _type(parsed, name, classifier).properties}

    two = props("Two_Dimensions_Array")["Dimension"]
    assert isinstance(two, s.ListValue)
    assert [getattr(i, "value", None) for i in two.items] == [74, 75]
    kanji = _type(parsed, name, "A_Kanji")
    assert kanji.extends == "Base_types::Character"
    code_set = props("A_Kanji")["Code_Set"]
    assert isinstance(code_set, s.IntValue)
    assert code_set.value == 0x30001
    struct = _impl(parsed, name, "A_Struct2.impl")
    assert [(c.name, c.classifier) for c in struct.subcomponents] == [
        ("f1", "Base_Types::Float"),
        ("c2", "Base_Types::Character"),
    ]
