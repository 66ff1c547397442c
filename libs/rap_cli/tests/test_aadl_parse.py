"""The AADL v2 parser on models written for these tests (``fixtures/aadl/``, inline
snippets): every construct of the subset with its fields and lines, one test per kind of
syntax mistake with the located message a user reads, recovery to several errors per
file, and the guards against oversized, deeply nested and arbitrary input."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from rap_cli.aadl import (
    MAX_FILE_BYTES,
    MAX_NESTING,
    norm,
    parse_aadl,
    parse_aadl_files,
)
from rap_cli.aadl import syntax as s
from rap_cli.diagnostics import Diagnostic

FIXTURES = Path(__file__).parent / "fixtures" / "aadl"


def _parse_fixture(name: str) -> s.AadlFile:
    path = FIXTURES / name
    parsed, diagnostics = parse_aadl(path.read_text(encoding="utf-8"), name)
    assert diagnostics == []
    assert parsed is not None
    return parsed


@pytest.fixture(scope="module")
def rover() -> s.Package:
    (package,) = _parse_fixture("rover.aadl").packages
    return package


def _type(package: s.Package, name: str) -> s.ComponentType:
    found = package.find(name)
    assert isinstance(found, s.ComponentType)
    return found


def _impl(package: s.Package, name: str) -> s.ComponentImpl:
    found = package.find(name)
    assert isinstance(found, s.ComponentImpl)
    return found


def _plain(node: object) -> object:
    """``node`` without its locations, to compare values by content."""
    if dataclasses.is_dataclass(node) and not isinstance(node, type):
        fields = [f.name for f in dataclasses.fields(node) if f.name != "loc"]
        return (type(node).__name__, *(_plain(getattr(node, f)) for f in fields))
    if isinstance(node, tuple):
        return tuple(_plain(item) for item in node)
    return node


def _errors(text: str) -> list[Diagnostic]:
    parsed, diagnostics = parse_aadl(text, "bad.aadl")
    assert parsed is None
    assert diagnostics
    assert all(d.severity == "error" for d in diagnostics)
    return diagnostics


def _system(properties: str) -> str:
    return f"package P\npublic\n  system S\n    properties\n      {properties}\n  end S;\nend P;\n"


def _value(text: str) -> s.PropertyValue:
    parsed, diagnostics = parse_aadl(_system(f"X => {text};"), "v.aadl")
    assert diagnostics == [], text
    assert parsed is not None
    (association,) = _type(parsed.packages[0], "S").properties
    return association.value


# ------------------------------------------------------------------ packages


def test_package_header_withs_renames_and_sections(rover: s.Package) -> None:
    assert rover.name == "Rover::Logical"
    assert rover.loc == s.Loc("rover.aadl", 2, 1)
    assert rover.withs == ("Base_Types", "Rover_Props", "Data_Model", "Rover::Secret")
    assert [(r.alias, r.kind, r.target, r.loc.line) for r in rover.renames] == [
        ("Motors", "package", "Rover::Motors", 6),
        ("Drive", "thread", "Rover::Motors::Drive", 7),
        (None, "all", "Rover::Common", 8),
    ]
    assert [d.name for d in rover.public] == [
        "Pose",
        "Pose.impl",
        "Planner",
        "Planner.impl",
        "Worker",
        "Worker.impl",
        "Robot",
    ]
    assert [(d.category, d.name, d.loc.line) for d in rover.private] == [("bus", "Hidden", 105)]
    (vendor,) = rover.properties
    assert (vendor.name, vendor.value, vendor.loc.line) == (
        "Rover_Props::Vendor",
        s.StringValue(s.Loc("rover.aadl", 111, 26), "ACME"),
        111,
    )


def test_names_keep_their_case_and_compare_case_insensitively(rover: s.Package) -> None:
    assert rover.find("PLANNER.IMPL") is rover.find("planner.impl")
    assert rover.find("nothing") is None
    assert norm("Base_Types::Float") == norm("base_types::FLOAT") == "base_types::float"


def test_keywords_are_case_insensitive_and_comments_ignored() -> None:
    text = (
        "PACKAGE Mixed -- the package\nPUBLIC\n  SYSTEM Top\n  END Top;\n"
        "  System Implementation Top.Impl -- impl\n    SubComponents\n"
        "      Cpu: PROCESSOR;\n  End Top.Impl;\nEND Mixed;\n"
    )
    parsed, diagnostics = parse_aadl(text, "mixed.aadl")
    assert diagnostics == []
    assert parsed is not None
    impl = _impl(parsed.packages[0], "top.impl")
    assert (impl.name, impl.type_name, impl.impl_name, impl.loc.line) == (
        "Top.Impl",
        "Top",
        "Impl",
        5,
    )
    assert [(c.name, c.category) for c in impl.subcomponents] == [("Cpu", "processor")]


def test_several_packages_and_an_empty_file() -> None:
    text = "package A public end A;\npackage B::C end B::C;\n"
    parsed, diagnostics = parse_aadl(text, "two.aadl")
    assert diagnostics == []
    assert parsed is not None
    assert [(p.name, p.loc.line) for p in parsed.packages] == [("A", 1), ("B::C", 2)]
    assert parse_aadl("-- nothing but a comment\n", "empty.aadl") == (s.AadlFile("empty.aadl"), [])


# ------------------------------------------------------------------ component types


def test_component_type_with_every_kind_of_feature(rover: s.Package) -> None:
    planner = _type(rover, "Planner")
    assert (planner.category, planner.loc.line, planner.extends) == ("process", 22, None)
    rows = [
        (f.name, f.loc.line, f.direction, f.kind, f.access, f.classifier, f.dims, f.inverse)
        for f in planner.features
    ]
    assert rows == [
        ("scan", 24, "in", "event data port", None, "Pose.impl", (), False),
        ("plan", 25, "out", "data port", None, None, (), False),
        ("status", 26, "in out", "event port", None, None, (), False),
        ("go", 27, "in", "event port", None, None, (), False),
        ("pose", 28, None, "data access", "requires", "Pose", (), False),
        ("shared", 29, None, "data access", "provides", "Pose.impl", (), False),
        ("net", 30, None, "bus access", "requires", "Rover::Hw::Can", (), False),
        ("calc", 31, None, "subprogram access", "provides", None, (), False),
        ("lib", 32, None, "subprogram group access", "requires", None, (), False),
        ("group1", 33, None, "feature group", None, "Rover::Iface::Bundle", (), False),
        ("group2", 34, None, "feature group", None, "Rover::Iface::Bundle", (), True),
        ("anything", 35, "in", "feature", None, None, (), False),
        ("samples", 36, "in", "data port", None, "Base_Types::Float", ("4",), False),
    ]
    (topic,) = planner.features[0].properties
    assert (topic.name, topic.property_set, topic.simple_name) == (
        "Rover_Props::Topic",
        "Rover_Props",
        "Topic",
    )
    assert _plain(topic.value) == ("StringValue", "/scan")
    assert [(p.name, p.loc.line) for p in planner.properties] == [("Period", 45)]
    assert planner.flows_skipped == 1


def test_extends_on_types_and_data_model_properties() -> None:
    text = (
        "package D\npublic\n  data Kanji extends Base_Types::Character\n    properties\n"
        "      Data_Model::Data_Representation => Struct;\n"
        "      Data_Model::Base_Type => (classifier (Base_Types::Float));\n"
        "      Data_Model::Dimension => (360);\n"
        '      Data_Model::Element_Names => ("a", "b");\n'
        '      Data_Model::Enumerators => ("A", "B");\n'
        "  end Kanji;\nend D;\n"
    )
    parsed, diagnostics = parse_aadl(text, "d.aadl")
    assert diagnostics == []
    assert parsed is not None
    kanji = _type(parsed.packages[0], "Kanji")
    assert (kanji.category, kanji.extends) == ("data", "Base_Types::Character")
    assert [(p.name, _plain(p.value), p.loc.line) for p in kanji.properties] == [
        ("Data_Model::Data_Representation", ("EnumValue", "Struct"), 5),
        ("Data_Model::Base_Type", ("ListValue", (("ClassifierValue", "Base_Types::Float"),)), 6),
        ("Data_Model::Dimension", ("ListValue", (("IntValue", 360, None),)), 7),
        (
            "Data_Model::Element_Names",
            ("ListValue", (("StringValue", "a"), ("StringValue", "b"))),
            8,
        ),
        (
            "Data_Model::Enumerators",
            ("ListValue", (("StringValue", "A"), ("StringValue", "B"))),
            9,
        ),
    ]


def test_modes_and_mode_transitions(rover: s.Package) -> None:
    planner = _type(rover, "Planner")
    assert [(m.name, m.initial, m.loc.line) for m in planner.modes] == [
        ("Idle", True, 40),
        ("Busy", False, 41),
    ]
    assert [
        (t.name, t.sources, t.triggers, t.destination, t.loc.line) for t in planner.mode_transitions
    ] == [
        ("t1", ("Idle",), ("go",), "Busy", 42),
        (None, ("Busy", "Idle"), ("status", "go"), "Idle", 43),
    ]
    assert planner.requires_modes is False
    robot = _type(rover, "Robot")
    assert robot.requires_modes is True
    assert [(m.name, m.initial, m.loc.line) for m in robot.modes] == [("Off", True, 99)]
    impl = _impl(rover, "Planner.impl")
    (busy_period,) = impl.modes[1].properties
    assert (busy_period.name, _plain(busy_period.value)) == ("Period", ("IntValue", 5, "ms"))


def test_mode_transition_triggers_may_be_paths() -> None:
    text = (
        "package M\npublic\n  process P\n  end P;\n  process implementation P.i\n"
        "    subcomponents\n      a: thread T.i in modes (Init);\n    modes\n"
        "      Init: initial mode;\n      Run: mode;\n      Init -[a.done]-> Run;\n"
        "  end P.i;\nend M;\n"
    )
    parsed, diagnostics = parse_aadl(text, "m.aadl")
    assert diagnostics == []
    assert parsed is not None
    impl = _impl(parsed.packages[0], "P.i")
    (transition,) = impl.mode_transitions
    assert (transition.sources, transition.triggers, transition.destination) == (
        ("Init",),
        ("a.done",),
        "Run",
    )
    assert transition.loc.line == 11
    assert impl.subcomponents[0].in_modes == ("Init",)


# ------------------------------------------------------------------ implementations


def test_subcomponents_of_every_category(rover: s.Package) -> None:
    impl = _impl(rover, "Planner.impl")
    assert (impl.category, impl.type_name, impl.impl_name, impl.loc.line) == (
        "process",
        "Planner",
        "impl",
        49,
    )
    assert impl.extends == "Rover::Base::Planner.generic"
    rows = [
        (c.name, c.loc.line, c.category, c.classifier, c.dims, c.in_modes, c.refined)
        for c in impl.subcomponents
    ]
    assert rows == [
        ("worker", 53, "thread", "Worker.impl", (), ("Busy",), False),
        ("helpers", 54, "thread group", None, (), (), False),
        ("pool", 55, "thread", "Worker.impl", ("3",), (), False),
        ("vcpu", 56, "virtual processor", None, (), (), False),
        ("vbus", 57, "virtual bus", "Rover::Hw::Vbus", (), (), False),
        ("spg", 58, "subprogram group", "Rover::Lib", (), (), False),
        ("store", 59, "memory", None, (), (), False),
        ("sensor", 60, "device", "Rover::Hw::Lidar.impl", (), (), False),
        ("other", 61, "abstract", None, (), (), False),
        ("worker2", 62, "thread", "Worker.impl", (), (), True),
    ]
    (priority,) = impl.subcomponents[2].properties
    assert (priority.name, _plain(priority.value), priority.loc.line) == (
        "Priority",
        ("IntValue", 2, None),
        55,
    )
    pose = _impl(rover, "Pose.impl")
    assert [(c.name, c.category, c.classifier) for c in pose.subcomponents] == [
        ("x", "data", "Base_Types::Float"),
        ("y", "data", "Base_Types::Float"),
    ]


def test_connections_named_anonymous_and_of_every_kind(rover: s.Package) -> None:
    impl = _impl(rover, "Planner.impl")
    rows = [
        (c.name, c.loc.line, c.kind, c.source, c.dest, c.bidirectional, c.in_modes)
        for c in impl.connections
    ]
    assert rows == [
        ("c1", 66, "port", "scan", "worker.input", False, ()),
        ("c2", 67, "event data port", "worker.output", "plan", False, ("Busy",)),
        (None, 68, "port", "go", "worker.trigger", False, ()),
        ("c4", 69, "data access", "shared", "worker.state", True, ()),
        ("c5", 70, "bus access", "net", "sensor.link", False, ()),
        ("c6", 71, "parameter", "worker.value", "plan", False, ()),
        ("c7", 72, "feature group", "group1", "group2", False, ()),
        ("c8", 73, "feature", "anything", "worker.any", False, ()),
        ("c9", 74, "subprogram access", "calc", "worker.calc", False, ()),
        ("c10", 75, "data port", "worker.level", "plan", False, ()),
        ("c11", 76, "event port", "status", "worker.status", False, ()),
    ]
    (timing,) = impl.connections[1].properties
    assert (timing.name, _plain(timing.value), timing.loc.line) == (
        "Timing",
        ("EnumValue", "Immediate"),
        67,
    )


def test_aadl1_style_anonymous_connections_and_reference_without_parentheses() -> None:
    text = (
        "package Ping\npublic\n  system S\n  end S;\n  system implementation S.i\n"
        "    subcomponents\n      a: process A.i;\n      cpu: processor;\n      net: bus;\n"
        "    connections\n      bus access net -> a.link;\n"
        "      port a.out_port -> a.in_port\n"
        "        {Actual_Connection_Binding => (reference (net));};\n"
        "    properties\n      actual_processor_binding => reference cpu applies to a;\n"
        "  end S.i;\nend Ping;\n"
    )
    parsed, diagnostics = parse_aadl(text, "ping.aadl")
    assert diagnostics == []
    assert parsed is not None
    impl = _impl(parsed.packages[0], "S.i")
    assert [(c.name, c.kind, c.source, c.dest, c.loc.line) for c in impl.connections] == [
        (None, "bus access", "net", "a.link", 11),
        (None, "port", "a.out_port", "a.in_port", 12),
    ]
    (binding,) = impl.connections[1].properties
    assert _plain(binding.value) == ("ListValue", (("ReferenceValue", "net"),))
    (processor,) = impl.properties
    assert (_plain(processor.value), processor.applies_to) == (("ReferenceValue", "cpu"), ("a",))


# ------------------------------------------------------------------ property associations


def test_property_association_forms(rover: s.Package) -> None:
    impl = _impl(rover, "Planner.impl")
    rows = [
        (p.name, p.loc.line, p.applies_to, p.append, p.constant, p.in_modes, p.in_binding)
        for p in impl.properties
    ]
    assert rows == [
        ("Actual_Processor_Binding", 84, ("worker", "pool"), False, False, (), ()),
        ("Deadline", 85, (), True, False, (), ()),
        ("Priority", 86, (), False, True, (), ()),
        ("Period", 87, (), False, False, ("Busy",), ()),
        ("Actual_Memory_Binding", 88, ("worker",), False, False, (), ("Rover::Hw::Cpu",)),
    ]
    assert _plain(impl.properties[0].value) == ("ListValue", (("ReferenceValue", "cpu"),))
    assert _plain(impl.properties[4].value) == ("ReferenceValue", "store")


def test_applies_to_paths_of_a_binding() -> None:
    text = _system(
        "Actual_Processor_Binding => ( reference( platform.controller.Cpu1) ) "
        "applies to managing.m, managing.a;"
    )
    parsed, diagnostics = parse_aadl(text, "b.aadl")
    assert diagnostics == []
    assert parsed is not None
    (binding,) = _type(parsed.packages[0], "S").properties
    assert _plain(binding.value) == ("ListValue", (("ReferenceValue", "platform.controller.Cpu1"),))
    assert binding.applies_to == ("managing.m", "managing.a")


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("5", ("IntValue", 5, None)),
        ("-3", ("IntValue", -3, None)),
        ("1_000", ("IntValue", 1000, None)),
        ("1e3", ("IntValue", 1000, None)),
        ("16#FF#", ("IntValue", 255, None)),
        ("2#101#e2", ("IntValue", 20, None)),
        ("8 Bytes", ("IntValue", 8, "Bytes")),
        ("2000 Ms", ("IntValue", 2000, "Ms")),
        ("10ms", ("IntValue", 10, "ms")),
        ("10.0 Hz", ("RealValue", 10.0, "Hz")),
        ("23.46 Mbps", ("RealValue", 23.46, "Mbps")),
        ("1.35e-5", ("RealValue", 1.35e-5, None)),
        ("+2.5", ("RealValue", 2.5, None)),
        ('"/weather"', ("StringValue", "/weather")),
        ('"say ""hi"""', ("StringValue", 'say "hi"')),
        ("true", ("BoolValue", True)),
        ("FALSE", ("BoolValue", False)),
        ("Periodic", ("EnumValue", "Periodic")),
        ("rpio::Topic", ("NameValue", "rpio::Topic")),
        ("1 ms .. 2 ms", ("RangeValue", ("IntValue", 1, "ms"), ("IntValue", 2, "ms"), None)),
        (
            "0 .. 10 delta 2",
            ("RangeValue", ("IntValue", 0, None), ("IntValue", 10, None), ("IntValue", 2, None)),
        ),
        (
            "1.24 kipd .. 1.25 mipd",
            ("RangeValue", ("RealValue", 1.24, "kipd"), ("RealValue", 1.25, "mipd"), None),
        ),
        ("()", ("ListValue", ())),
        ("(360)", ("ListValue", (("IntValue", 360, None),))),
        ("(a, b)", ("ListValue", (("EnumValue", "a"), ("EnumValue", "b")))),
        (
            '[f => 1; g => "x";]',
            (
                "RecordValue",
                (
                    ("RecordField", "f", ("IntValue", 1, None)),
                    ("RecordField", "g", ("StringValue", "x")),
                ),
            ),
        ),
        (
            "([kind => Fixed; times => (1 ms, 2 ms);])",
            (
                "ListValue",
                (
                    (
                        "RecordValue",
                        (
                            ("RecordField", "kind", ("EnumValue", "Fixed")),
                            (
                                "RecordField",
                                "times",
                                ("ListValue", (("IntValue", 1, "ms"), ("IntValue", 2, "ms"))),
                            ),
                        ),
                    ),
                ),
            ),
        ),
        ("reference (a.b.c)", ("ReferenceValue", "a.b.c")),
        ("reference a.b", ("ReferenceValue", "a.b")),
        ("classifier (x::y)", ("ClassifierValue", "x::y")),
        ("classifier x::y.impl", ("ClassifierValue", "x::y.impl")),
        ("compute (Tools::Estimate)", ("ComputedValue", "Tools::Estimate")),
    ],
)
def test_property_values(text: str, expected: object) -> None:
    assert _plain(_value(text)) == expected


def test_value_locations_point_at_the_value() -> None:
    value = _value("(1 ms, reference (cpu))")
    assert isinstance(value, s.ListValue)
    assert value.loc == s.Loc("v.aadl", 5, 12)
    assert [item.loc.column for item in value.items] == [13, 19]


# ------------------------------------------------------------------ property sets


def test_property_set_definitions_types_and_constants() -> None:
    (props,) = _parse_fixture("rover_props.aadl").property_sets
    assert (props.name, props.withs, props.loc.line) == ("Rover_Props", ("Rover_Units",), 2)
    assert [(t.name, t.type.kind, t.loc.line) for t in props.types] == [
        ("Speed_Units", "units", 5),
        ("Mode_Kind", "enumeration", 6),
        ("Levels", "aadlinteger", 7),
    ]
    assert props.types[1].type.enumerators == ("Manual", "Auto", "Remote")
    assert [(u.name, u.base, u.factor) for u in props.types[0].type.units] == [
        ("mps", None, None),
        ("kmph", "mps", 3.6),
    ]
    levels = props.types[2].type
    assert (_plain(levels.low), _plain(levels.high)) == (
        ("IntValue", 0, None),
        ("IntValue", 10, None),
    )

    rows = [
        (d.name, d.loc.line, d.type.kind, d.list_depth, d.inherit, d.applies_to)
        for d in props.definitions
    ]
    assert rows == [
        ("Topic", 9, "aadlstring", 0, False, ("port", "event data port")),
        ("Max_Speed", 10, "aadlreal", 0, True, ("system", "device")),
        ("Bandwidth", 11, "aadlreal", 0, False, ("bus", "virtual bus", "access connection")),
        ("Kind", 12, "named", 0, False, ("all",)),
        ("Hosts", 13, "aadlstring", 1, False, ("processor",)),
        ("Matrix", 14, "aadlinteger", 2, False, ("data",)),
        ("Enabled", 15, "aadlboolean", 0, False, ("process", "thread group")),
        ("Window", 16, "range", 0, False, ("thread",)),
        ("Platform", 17, "classifier", 0, False, ("process",)),
        ("Peer", 18, "reference", 0, False, ("system",)),
        ("Contact", 19, "record", 0, False, ("system",)),
    ]
    by_name = {d.name: d for d in props.definitions}
    speed = by_name["Max_Speed"]
    assert (speed.type.units_name, _plain(speed.default)) == (
        "Rover_Props::Speed_Units",
        ("RealValue", 1.0, "mps"),
    )
    assert [u.name for u in by_name["Bandwidth"].type.units] == ["bps", "kbps"]
    assert (by_name["Kind"].type.name, _plain(by_name["Kind"].default)) == (
        "Rover_Props::Mode_Kind",
        ("EnumValue", "Auto"),
    )
    window = by_name["Window"].type.element
    assert window is not None
    assert window.kind == "aadlinteger"
    assert by_name["Platform"].type.owners == ("processor", "virtual processor")
    assert [(f.name, f.type.kind, f.list_depth) for f in by_name["Contact"].type.fields] == [
        ("name", "aadlstring", 0),
        ("ports", "aadlinteger", 1),
    ]
    assert [(c.name, c.type.kind, c.list_depth, _plain(c.value)) for c in props.constants] == [
        ("Max_Robots", "aadlinteger", 0, ("IntValue", 16, None)),
        (
            "Default_Hosts",
            "aadlstring",
            1,
            ("ListValue", (("StringValue", "a"), ("StringValue", "b"))),
        ),
    ]
    assert [u.name for u in props.unit_literals()] == ["mps", "kmph", "bps", "kbps"]


# ------------------------------------------------------------------ what is skipped


def test_annexes_flows_calls_and_prototypes_are_noted_with_their_place() -> None:
    parsed = _parse_fixture("rover.aadl")
    assert [(n.loc.line, n.message) for n in parsed.notes] == [
        (37, "1 flow declaration(s) of process type 'Planner' skipped: RAP does not model flows"),
        (46, "annex EMV2 of process type 'Planner' skipped: RAP does not read annexes"),
        (
            50,
            "1 prototype(s) of process implementation 'Planner.impl' skipped: "
            "RAP does not model prototypes",
        ),
        (
            63,
            "1 call sequence(s) of process implementation 'Planner.impl' skipped: "
            "RAP does not model calls",
        ),
        (
            77,
            "2 flow declaration(s) of process implementation 'Planner.impl' skipped: "
            "RAP does not model flows",
        ),
        (
            108,
            "annex library Behavior_Specification of package Rover::Logical skipped: "
            "RAP does not read annexes",
        ),
    ]
    (impl,) = [d for d in parsed.packages[0].public if d.name == "Planner.impl"]
    assert impl.flows_skipped == 2
    note = parsed.notes[1].diagnostic()
    assert str(note).startswith("rover.aadl:46:5: note: annex EMV2")


def test_empty_sections_crlf_and_tabs() -> None:
    text = (
        "package P\r\npublic\r\n\tsystem S\r\n\t\tfeatures none;\r\n\t\tflows none;\r\n"
        "\t\tmodes none;\r\n\t\tproperties none;\r\n\t\tannex EMV2 none;\r\n\tend S;\r\n"
        "\tsystem implementation S.i\r\n\t\tsubcomponents none;\r\n\t\tcalls none;\r\n"
        "\t\tconnections none;\r\n\tend S.i;\r\nprivate\r\nproperties\r\n  none;\r\n"
        "end P; -- no newline at the end"
    )
    parsed, diagnostics = parse_aadl(text, "none.aadl")
    assert diagnostics == []
    assert parsed is not None
    assert parsed.notes == ()  # nothing skipped: the sections are empty
    (package,) = parsed.packages
    assert [(d.name, d.loc.line, d.loc.column) for d in package.declarations] == [
        ("S", 3, 2),  # a tab is one column
        ("S.i", 10, 2),
    ]


def test_annex_text_may_hold_braces_and_aadl_keywords() -> None:
    text = (
        "package A\npublic\n  annex EMV2 {** error types X: type; end types; **};\n"
        "  device D\n    annex EMV2 {**\n      t: Op -[cmd {NoValue}]-> Failed; end component;\n"
        "    **};\n  end D;\nend A;\n"
    )
    parsed, diagnostics = parse_aadl(text, "a.aadl")
    assert diagnostics == []
    assert parsed is not None
    assert [n.loc.line for n in parsed.notes] == [3, 5]


# ------------------------------------------------------------------ syntax errors


def test_missing_semicolon_after_a_feature() -> None:
    text = (
        "package P\npublic\n  process monitor\n    features\n      a: in event port\n"
        "      b: out event data port T;\n  end monitor;\nend P;\n"
    )
    (error,) = _errors(text)
    assert (error.line, error.column) == (5, 23)
    assert error.message == (
        "expected ';' after the feature declaration in process type 'monitor' "
        "- add ';' at the end of this line"
    )
    assert str(error) == f"bad.aadl:5:23: error: {error.message}"


def test_missing_semicolon_after_a_with_clause() -> None:
    text = "package P\npublic\n  with A, B\n  system S\n  end S;\nend P;\n"
    (error,) = _errors(text)
    assert (error.line, error.column) == (3, 12)
    assert "expected ';' after the 'with' clause in package 'P'" in error.message


def test_missing_semicolon_in_the_middle_of_a_line() -> None:
    text = _system("Period => 5 ms Deadline => 4 ms;")
    (error,) = _errors(text)
    assert (error.line, error.column) == (5, 22)
    assert error.message.startswith(
        "expected ';' after the property association in system type 'S', found 'Deadline'"
    )


def test_unknown_category_keyword() -> None:
    text = (
        "package P\npublic\n  proces monitor\n  end monitor;\n  system S\n  end S;\n"
        "  system implementation S.i\n    subcomponents\n      m: thred monitor;\n"
        "  end S.i;\nend P;\n"
    )
    first, second = _errors(text)
    assert (first.line, first.column) == (3, 3)
    assert first.message.startswith(
        "unknown component category 'proces' - use one of abstract, bus,"
    )
    assert (second.line, second.column) == (9, 10)
    assert "unknown component category 'thred'" in second.message


def test_unterminated_annex() -> None:
    text = (
        "package P\npublic\n  system S\n    annex EMV2 {**\n      error types\n  end S;\nend P;\n"
    )
    (error,) = _errors(text)
    assert (error.line, error.column) == (4, 16)
    assert error.message == (
        "the annex text opened here with '{**' is never closed - end it with '**}' followed by ';'"
    )


def test_unterminated_string_and_stray_character() -> None:
    (string,) = _errors(_system('Source_Text => "abc;'))
    assert (string.line, string.column) == (5, 22)
    assert "string is not closed" in string.message
    (stray,) = _errors("package P\npublic\n  system S $\n  end S;\nend P;\n")
    assert (stray.line, stray.column) == (3, 12)
    assert stray.message.startswith("the character '$' cannot appear here")


def test_file_ending_inside_a_package() -> None:
    (error,) = _errors("package P\npublic\n  system S\n  end S;\n")
    assert error.line == 4
    assert error.message.startswith("the file ends inside package 'P' - complete it (expected")


def test_reserved_word_used_as_a_name() -> None:
    text = (
        "package P\npublic\n  process Q\n  end Q;\n  process implementation Q.i\n"
        "    subcomponents\n      data: data T;\n  end Q.i;\nend P;\n"
    )
    (error,) = _errors(text)
    assert (error.line, error.column) == (7, 7)
    assert error.message.startswith("'data' is a reserved word of AADL")


def test_unexpected_section_says_what_was_expected() -> None:
    text = (
        "package P\npublic\n  system S\n    connections\n      c: port a -> b;\n  end S;\nend P;\n"
    )
    (error,) = _errors(text)
    assert (error.line, error.column) == (4, 5)
    assert error.message.startswith(
        "unexpected 'connections' in the declaration of system type 'S' - expected 'annex', 'end'"
    )


def test_for_clause_of_a_non_standard_generator() -> None:
    text = (
        "package P\npublic\n  thread T\n  end T;\n  thread implementation T.impl for T\n"
        "  end T.impl;\nend P;\n"
    )
    (error,) = _errors(text)
    assert (error.line, error.column) == (5, 32)
    assert error.message.startswith(
        "'for' after an implementation name is not AADL v2 - remove 'for T'"
    )


def test_end_name_must_match() -> None:
    end_package, end_system = _errors("package P\npublic\n  system S\n  end T;\nend Q;\n")
    assert (end_package.line, end_package.message) == (
        5,
        "'end Q;' does not close package 'P' - write 'end P;'",
    )
    assert (end_system.line, end_system.column) == (4, 7)
    assert end_system.message == "'end T;' does not close the system type 'S' - write 'end S;'"


def test_recovery_reports_one_error_per_broken_declaration() -> None:
    text = (
        "package P\npublic\n"
        "  process A\n    features\n      x: in evnt port;\n      y: out event port;\n  end A;\n"
        "  process B\n    features\n      z: in event port\n  end B;\n"
        "  process C\n    properties\n      Period => => 5 ms;\n  end C;\n"
        "  process D\n  end D;\nend P;\n"
    )
    errors = _errors(text)
    assert [(e.line, e.message.split(" - ")[0]) for e in errors] == [
        (5, "unexpected 'evnt' in the feature declaration in process type 'A'"),
        (10, "expected ';' after the feature declaration in process type 'B'"),
        (14, "unexpected '=>' in the property association in process type 'C'"),
    ]


def test_section_out_of_order_is_a_warning_and_the_file_is_kept() -> None:
    text = _system("Period => 5 ms;\n    features\n      a: in event port;")
    parsed, diagnostics = parse_aadl(text, "order.aadl")
    assert parsed is not None
    (warning,) = diagnostics
    assert (warning.severity, warning.line, warning.column) == ("warning", 6, 5)
    assert warning.message.startswith("the 'features' section of system type 'S' is out of order")


def test_malformed_based_integer() -> None:
    (error,) = _errors(_system("X => 8#99#;"))
    assert (error.line, error.column) == (5, 12)
    assert error.message == "'99' are not digits of base 8 - fix the literal 8#99#"
    (huge,) = _errors(_system("X => 1e999;"))
    assert "out of range" in huge.message


# ------------------------------------------------------------------ guards and files


def test_oversized_file_is_refused() -> None:
    text = "-- " + "x" * MAX_FILE_BYTES
    (error,) = _errors(text)
    assert (error.line, error.severity) == (0, "error")
    assert "split it into several packages" in error.message


def test_deep_nesting_is_refused_without_a_crash() -> None:
    depth = MAX_NESTING + 1
    (error,) = _errors(_system("X => " + "(" * depth + "1" + ")" * depth + ";"))
    assert error.line == 5
    assert error.message.startswith(f"brackets are nested more than {MAX_NESTING} levels deep")
    assert parse_aadl(_system("X => " + "(" * 5000 + ";"), "deep.aadl")[0] is None


def test_parse_files_reads_each_and_reports_unreadable_ones(tmp_path: Path) -> None:
    good = tmp_path / "good.aadl"
    good.write_text("package G public system S end S; end G;\n", encoding="utf-8")
    latin = tmp_path / "latin.aadl"
    latin.write_bytes("-- caf\xe9\npackage L end L;\n".encode("latin-1"))
    broken = tmp_path / "broken.aadl"
    broken.write_text("package B public system S end S;\n", encoding="utf-8")
    missing = tmp_path / "missing.aadl"
    files, diagnostics = parse_aadl_files([good, latin, broken, missing])
    assert [(f.source, [p.name for p in f.packages]) for f in files] == [
        (str(good), ["G"]),
        (str(latin), ["L"]),
    ]
    assert [(Path(d.file).name, d.severity, d.line) for d in diagnostics] == [
        ("latin.aadl", "warning", 1),
        ("broken.aadl", "error", 1),
        ("missing.aadl", "error", 0),
    ]
    assert diagnostics[2].message.startswith("cannot read the file:")


def test_a_large_model_parses_well_under_a_second() -> None:
    text = (FIXTURES / "rover.aadl").read_text(encoding="utf-8")
    body = text.split("public\n", 1)[1].rsplit("private\n", 1)[0]
    blocks = [
        body.replace("Planner", f"Planner{i}")
        .replace("Pose", f"Pose{i}")
        .replace("Worker", f"Worker{i}")
        .replace("Robot", f"Robot{i}")
        for i in range(20)
    ]
    big = "package Big\npublic\n" + "".join(blocks) + "end Big;\n"
    assert 50_000 < len(big) < MAX_FILE_BYTES
    parse_aadl("package Warm end Warm;", "warm.aadl")  # the grammar is compiled once
    started = time.perf_counter()
    parsed, diagnostics = parse_aadl(big, "big.aadl")
    elapsed = time.perf_counter() - started
    assert diagnostics == []
    assert parsed is not None
    assert len(parsed.packages[0].public) == 20 * 7
    assert elapsed < 1.0


_WORDS = [
    "package", "public", "private", "end", "system", "process", "thread", "implementation",
    "features", "subcomponents", "connections", "properties", "modes", "flows", "annex",
    "in", "out", "event", "data", "port", "access", "requires", "provides", "applies", "to",
    "reference", "classifier", "mode", "initial", "a", "b", "P", "T.impl", "x::y", ";", ":",
    ",", ".", "->", "<->", "=>", "+=>", "(", ")", "[", "]", "{", "}", "-[", "]->", "..",
    "1", "2.5", '"s"', "{** t **}", "--c\n", "\n", "$", '"', "{**",
]  # fmt: skip


@settings(max_examples=300, deadline=None)
@given(st.lists(st.sampled_from(_WORDS), max_size=60))
def test_arbitrary_token_soup_never_raises(words: list[str]) -> None:
    parsed, diagnostics = parse_aadl(" ".join(words), "soup.aadl")
    errors = [d for d in diagnostics if d.severity == "error"]
    assert (parsed is None) == bool(errors)
    assert all(d.file == "soup.aadl" and d.message for d in diagnostics)


@settings(max_examples=150, deadline=None)
@given(st.data())
def test_damaged_fixture_never_raises(data: st.DataObject) -> None:
    text = (FIXTURES / "rover.aadl").read_text(encoding="utf-8")
    start = data.draw(st.integers(0, len(text) - 1))
    length = data.draw(st.integers(1, 40))
    insert = data.draw(st.sampled_from(["", ";", "end", "(", "x", "-["]))
    damaged = text[:start] + insert + text[start + length :]
    parsed, diagnostics = parse_aadl(damaged, "damaged.aadl")
    if parsed is None:
        assert any(d.severity == "error" and d.line > 0 for d in diagnostics)
