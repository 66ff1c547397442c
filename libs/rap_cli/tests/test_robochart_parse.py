"""The RoboChart / RoboArch parser on models written for these tests
(``fixtures/robochart/``, inline snippets): every construct with its fields and lines,
one test per kind of syntax mistake with the message a user reads, and the guards
against oversized and deeply nested input."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from rap_cli.diagnostics import Diagnostic
from rap_cli.robochart import (
    MAX_BYTES,
    MAX_NESTING,
    parse_roboarch,
    parse_robochart,
    parse_robochart_files,
)
from rap_cli.robochart import syntax as s

FIXTURES = Path(__file__).parent / "fixtures" / "robochart"


def _rct(name: str) -> s.RcFile:
    path = FIXTURES / name
    parsed, diagnostics = parse_robochart(path.read_text(encoding="utf-8"), name)
    assert diagnostics == []
    assert parsed is not None
    return parsed


def _decl(file: s.RcFile | s.RacFile, name: str) -> object:
    (found,) = [d for d in file.declarations if d.name == name]
    return found


def _node(nodes: tuple[s.Node, ...], name: str) -> s.Node:
    (found,) = [n for n in nodes if n.name == name]
    return found


def _line(x: object) -> int:
    loc = getattr(x, "loc", None)
    assert isinstance(loc, s.Loc)
    return loc.line


# ------------------------------------------------------------------------------ types


def test_package_and_imports() -> None:
    types = _rct("types.rct")
    assert types.package == "cleaner::types"
    assert [(i.path, i.wildcard, i.loc.line) for i in types.imports] == [
        ("cleaner::machines", True, 4),
        ("geometry::Point", False, 5),
    ]
    assert types.loc == s.Loc("types.rct", 1, 1)


def test_primitive_type_and_records_with_fields() -> None:
    types = _rct("types.rct")
    handle = _decl(types, "Handle")
    assert handle == s.PrimitiveType("Handle", s.Loc("types.rct", 7, 1))
    pose = _decl(types, "Pose")
    assert isinstance(pose, s.Record)
    assert pose.kind == "datatype"
    assert pose.loc.line == 9
    assert [(f.name, f.type, f.loc.line) for f in pose.fields] == [
        ("x", s.TypeName("real", s.Loc("types.rct", 10, 6)), 10),
        ("y", s.TypeName("real", s.Loc("types.rct", 11, 5)), 11),
        ("heading", s.TypeName("real", s.Loc("types.rct", 12, 12)), 12),
    ]
    dust = _decl(types, "DustMap")
    assert isinstance(dust, s.Record)
    assert dust.kind == "record"
    assert [f.name for f in dust.fields] == [
        "cells",
        "dirty",
        "origin",
        "owner",
        "label",
        "valid",
        "count",
    ]


def test_type_expressions() -> None:
    dust = _decl(_rct("types.rct"), "DustMap")
    assert isinstance(dust, s.Record)
    cells, dirty, origin, owner, label, valid, count = (f.type for f in dust.fields)
    assert isinstance(cells, s.SeqType)
    assert isinstance(cells.elem, s.SeqType)
    assert isinstance(cells.elem.elem, s.TypeName)
    assert cells.elem.elem.name == "nat"
    assert isinstance(dirty, s.SetType)
    assert isinstance(dirty.elem, s.TypeName)
    assert dirty.elem.name == "Point"
    assert isinstance(origin, s.ProductType)
    assert [getattr(t, "name", None) for t in origin.items] == ["real", "real"]
    assert isinstance(owner, s.TypeName)
    assert owner.name == "geometry::Frame"
    names = [getattr(t, "name", None) for t in (label, valid, count)]
    assert names == ["string", "boolean", "int"]


def test_enumerations_with_and_without_commas() -> None:
    types = _rct("types.rct")
    mode, level = _decl(types, "Mode"), _decl(types, "Level")
    assert isinstance(mode, s.Enumeration)
    assert isinstance(level, s.Enumeration)
    assert [lit.name for lit in mode.literals] == ["IDLE", "CLEANING", "DOCKING"]
    assert mode.loc.line == 25
    assert [(lit.name, lit.loc.line) for lit in level.literals] == [("LOW", 28), ("HIGH", 29)]


def test_functions_keep_signature_and_conditions_as_text() -> None:
    types = _rct("types.rct")
    clamp = _decl(types, "clamp")
    assert isinstance(clamp, s.FunctionDecl)
    assert clamp.loc.line == 34  # after the two-line block comment
    assert [p.name for p in clamp.params] == ["v", "lo", "hi"]
    assert clamp.result == s.TypeName("real", s.Loc("types.rct", 34, 50))
    assert [t.text for t in clamp.preconditions] == ["lo <= hi"]
    (post,) = clamp.postconditions
    assert post.text == "result == (if v < lo then lo else if v > hi then hi else v end end)"
    assert post.loc == s.Loc("types.rct", 36, 16)
    apply = _decl(types, "apply")
    assert isinstance(apply, s.FunctionDecl)
    f_type = apply.params[0].type
    assert isinstance(f_type, s.FunctionType)
    assert f_type.domain == s.TypeParam("X", s.Loc("types.rct", 39, 20))
    assert isinstance(apply.result, s.SeqType)
    assert apply.preconditions == ()


def test_top_level_consts_with_and_without_value() -> None:
    types = _rct("types.rct")
    speed, rooms = _decl(types, "MAX_SPEED"), _decl(types, "ROOMS")
    assert isinstance(speed, s.Variable)
    assert isinstance(rooms, s.Variable)
    assert speed.const
    assert speed.value == s.Text("0.5", s.Loc("types.rct", 43, 26))
    assert (rooms.const, rooms.value, rooms.loc.line) == (True, None, 44)


# ------------------------------------------------------------------------------ interfaces


def test_interface_members() -> None:
    sensing = _decl(_rct("machines.rct"), "Sensing")
    assert isinstance(sensing, s.Interface)
    assert [(e.name, e.type is None, e.loc.line) for e in sensing.events] == [
        ("bump", True, 6),
        ("dust", False, 7),
    ]
    assert [(v.name, v.const, v.loc.line) for v in sensing.variables] == [
        ("battery", False, 8),
        ("capacity", True, 9),
    ]
    assert [c.name for c in sensing.consts] == ["capacity"]
    assert sensing.variables[1].value is not None
    assert sensing.variables[1].value.text == "100"
    assert [c.name for c in sensing.clocks] == ["t"]
    (turn,) = sensing.operations
    assert (turn.name, [p.name for p in turn.params], turn.loc.line) == (
        "turn",
        ["angle", "speed"],
        11,
    )
    driving = _decl(_rct("machines.rct"), "Driving")
    assert isinstance(driving, s.Interface)
    assert [(o.name, len(o.params)) for o in driving.operations] == [("move", 2), ("stop", 0)]


def test_robotic_platform() -> None:
    vacuum = _decl(_rct("machines.rct"), "Vacuum")
    assert isinstance(vacuum, s.RoboticPlatform)
    assert vacuum.loc.line == 19
    assert [u.interface for u in vacuum.uses] == ["Sensing"]
    assert [(u.interface, u.loc.line) for u in vacuum.provides] == [("Driving", 21)]
    assert [u.interface for u in vacuum.requires] == ["Sensing"]
    assert [e.name for e in vacuum.events] == ["cliff"]
    assert [v.name for v in vacuum.variables] == ["temperature"]
    assert [o.name for o in vacuum.operations] == ["brush"]


# ------------------------------------------------------------------------------ state machines


def test_state_machine_members() -> None:
    cleaner = _decl(_rct("machines.rct"), "Cleaner")
    assert isinstance(cleaner, s.StateMachine)
    assert (cleaner.kind, cleaner.loc.line, cleaner.params) == ("stm", 28, ())
    assert [u.interface for u in cleaner.uses] == ["Sensing"]
    assert [u.interface for u in cleaner.requires] == ["Driving"]
    assert [u.interface for u in cleaner.provides] == ["Sensing"]
    target, limit = cleaner.variables
    assert (target.name, target.const, limit.name, limit.const) == ("target", False, "limit", True)
    assert target.value is not None
    assert target.value.text == "Pose (| x = 0, y = 0, heading = 0 |)"
    assert [(e.name, e.loc.line) for e in cleaner.events] == [("done", 34), ("mode", 35)]
    assert [(c.name, c.loc.line) for c in cleaner.clocks] == [("c", 36)]


def test_nodes_nested_states_and_state_actions() -> None:
    cleaner = _decl(_rct("machines.rct"), "Cleaner")
    assert isinstance(cleaner, s.StateMachine)
    kinds = [(type(n).__name__, n.name, n.loc.line) for n in cleaner.nodes]
    assert kinds == [
        ("Initial", "i0", 37),
        ("State", "Idle", 38),
        ("State", "Cleaning", 42),
        ("Junction", "decide", 53),
        ("Junction", "coin", 54),
        ("Final", "off", 55),
    ]
    idle = _node(cleaner.nodes, "Idle")
    assert isinstance(idle, s.State)
    assert idle.entry == s.Text("stop() ; count = 0", s.Loc("machines.rct", 39, 9))
    assert idle.exit is not None
    assert (idle.exit.text, idle.exit.loc.line, idle.during) == ("done", 40, None)
    cleaning = _node(cleaner.nodes, "Cleaning")
    assert isinstance(cleaning, s.State)
    assert cleaning.during is not None
    assert cleaning.during.text == "move(0.2, 0) ; count = count + 1"
    assert [(type(n).__name__, n.name) for n in cleaning.nodes] == [
        ("Initial", "j"),
        ("State", "Forward"),
        ("Final", "stop_here"),
    ]
    (inner,) = cleaning.transitions
    assert (inner.name, inner.source, inner.target, inner.loc.line) == ("inner", "j", "Forward", 48)
    coin = _node(cleaner.nodes, "coin")
    decide = _node(cleaner.nodes, "decide")
    assert isinstance(coin, s.Junction)
    assert isinstance(decide, s.Junction)
    assert (coin.probabilistic, decide.probabilistic) == (True, False)


def test_transitions_keep_trigger_guard_action_text_with_location() -> None:
    cleaner = _decl(_rct("machines.rct"), "Cleaner")
    assert isinstance(cleaner, s.StateMachine)
    t0, start, t2, t3 = cleaner.transitions
    assert (t0.name, t0.source, t0.target, t0.loc.line) == ("t0", "i0", "Idle", 56)
    assert (t0.trigger, t0.guard, t0.action, t0.probability) == (None, None, None, None)
    assert (start.source, start.target) == ("Idle", "decide")
    assert start.trigger == s.Text("dust ? level", s.Loc("machines.rct", 63, 11))
    assert start.guard == s.Text("level > 0.1 /\\ battery > 20", s.Loc("machines.rct", 64, 13))
    assert start.action == s.Text(
        "mode ! CLEANING ; target = Pose (| x = 1, y = 2, heading = 0 |)",
        s.Loc("machines.rct", 65, 10),
    )
    assert t2.probability == s.Text("0.5", s.Loc("machines.rct", 70, 15))
    assert t3.trigger is not None
    assert t3.action is not None
    assert (t3.trigger.text, t3.action.text) == ("bump", "turn(90, 1)")


def test_operation_definition_parses_like_a_state_machine() -> None:
    spin = _decl(_rct("machines.rct"), "Spin")
    assert isinstance(spin, s.StateMachine)
    assert (spin.kind, spin.loc.line) == ("operation", 80)
    assert [(p.name, getattr(p.type, "name", None)) for p in spin.params] == [("angle", "real")]
    assert [u.interface for u in spin.requires] == ["Driving"]
    assert [n.name for n in spin.nodes] == ["i", "Turning", "f"]
    turning = _node(spin.nodes, "Turning")
    assert isinstance(turning, s.State)
    assert turning.entry is not None
    assert turning.entry.text == "turn(angle, 1)"


# ------------------------------------------------------------------------------ controllers


def test_controller_machines_operations_and_connections() -> None:
    brain = _decl(_rct("machines.rct"), "Brain")
    assert isinstance(brain, s.Controller)
    assert brain.loc.line == 93
    assert [u.interface for u in (*brain.uses, *brain.provides, *brain.requires)] == [
        "Sensing",
        "Driving",
        "Driving",
    ]
    assert [e.name for e in brain.events] == ["dust"]
    main, watchdog = brain.machines
    assert (main.name, main.kind, main.target, main.definition, main.loc.line) == (
        "main",
        "sref",
        "Cleaner",
        None,
        98,
    )
    assert (watchdog.name, watchdog.kind, watchdog.target) == ("Watchdog", "stm", None)
    assert watchdog.definition is not None
    assert [n.name for n in watchdog.definition.nodes] == ["w0", "Watching"]
    assert [(o.name, o.target) for o in brain.operations] == [("spin", "Spin")]
    plain, asynchronous, both = brain.connections
    assert plain == s.Connection(
        "Brain", "dust", "main", "dust", False, False, s.Loc("machines.rct", 109, 2)
    )
    assert (asynchronous.asynchronous, asynchronous.bidirectional) == (True, False)
    assert (both.from_node, both.to_event, both.asynchronous, both.bidirectional) == (
        "Watchdog",
        "done",
        True,
        True,
    )


def test_modules_with_referenced_and_inline_parts() -> None:
    machines = _rct("machines.rct")
    robot, bench = _decl(machines, "Robot"), _decl(machines, "Bench")
    assert isinstance(robot, s.Module)
    assert isinstance(bench, s.Module)
    assert robot.platform == s.PlatformRef("rp", "Vacuum", None, s.Loc("machines.rct", 115, 2))
    assert [(c.name, c.target) for c in robot.controllers] == [("brain", "Brain")]
    (conn,) = robot.connections
    assert (conn.from_node, conn.to_node, conn.asynchronous, conn.loc.line) == (
        "rp",
        "brain",
        True,
        117,
    )
    assert bench.platform is not None
    assert bench.platform.definition is not None
    assert (bench.platform.name, bench.platform.target) == ("Sim", None)
    assert [u.interface for u in bench.platform.definition.uses] == ["Sensing"]
    (inline,) = bench.controllers
    assert inline.definition is not None
    assert [m.target for m in inline.definition.machines] == ["Cleaner"]


def test_keywords_are_contextual_and_names_keep_their_case() -> None:
    text = (
        "interface plan {\n  event state : Seq(real)\n  event To\n  var initial : nat\n}\n"
        "stm Plan {\n  event on\n  initial i\n  state S {}\n"
        "  transition t { from i to S trigger on }\n}\n"
    )
    parsed, diagnostics = parse_robochart(text, "kw.rct")
    assert diagnostics == []
    assert parsed is not None
    plan = _decl(parsed, "plan")
    assert isinstance(plan, s.Interface)
    assert [e.name for e in plan.events] == ["state", "To"]
    assert [v.name for v in plan.variables] == ["initial"]
    machine = _decl(parsed, "Plan")
    assert isinstance(machine, s.StateMachine)
    assert machine.transitions[0].trigger is not None
    assert machine.transitions[0].trigger.text == "on"


def test_text_spans_lines_keeps_inner_comments_and_stops_at_the_next_clause() -> None:
    text = (
        "stm M {\n  initial i\n  state S {\n"
        "    entry a = {x : int | x > 0 @ x}; // first\n"
        "      b = if a then <1, 2> else <> end\n"
        "    // not part of the action\n"
        "    initial j\n  }\n}\n"
    )
    parsed, diagnostics = parse_robochart(text, "t.rct")
    assert diagnostics == []
    assert parsed is not None
    machine = parsed.declarations[0]
    assert isinstance(machine, s.StateMachine)
    state = _node(machine.nodes, "S")
    assert isinstance(state, s.State)
    assert state.entry == s.Text(
        "a = {x : int | x > 0 @ x}; // first\n      b = if a then <1, 2> else <> end",
        s.Loc("t.rct", 4, 11),
    )
    assert [n.name for n in state.nodes] == ["j"]


# ------------------------------------------------------------------------------ RoboArch


def _rac() -> s.RacFile:
    text = (FIXTURES / "layered.rac").read_text(encoding="utf-8")
    parsed, diagnostics = parse_roboarch(text, "layered.rac")
    assert [(d.severity, d.line) for d in diagnostics] == [("note", 36)]
    assert parsed is not None
    return parsed


def test_roboarch_system_declarations_and_connections() -> None:
    rac = _rac()
    assert rac.system == "Cleaner"
    assert [type(d).__name__ for d in rac.declarations] == [
        "Record",
        "Interface",
        "Interface",
        "RoboticPlatform",
    ]
    assert [
        (c.from_node, c.from_event, c.to_node, c.to_event, c.loc.line) for c in rac.connections
    ] == [
        ("Vacuum", "dust", "Motion", "dust", 48),
        ("Motion", "dust", "Supervisor", "dust", 49),
        ("Supervisor", "route", "Motion", "route", 50),
    ]
    assert [c.asynchronous for c in rac.connections] == [False, True, False]


def test_roboarch_layers_ports_pattern_and_stages() -> None:
    supervisor, motion = _rac().layers
    assert (supervisor.name, supervisor.layer_type, supervisor.loc.line) == (
        "Supervisor",
        "PlanningLayer",
        22,
    )
    assert supervisor.pattern == "MAPLE-K"
    assert [(v.name, getattr(v.type, "name", None), v.loc.line) for v in supervisor.inputs] == [
        ("dust", "Reading", 23),
        ("bump", None, 23),
    ]
    (route,) = supervisor.outputs
    assert isinstance(route.type, s.SeqType)
    assert [(b.name, b.loc.line) for b in supervisor.stages] == [
        ("monitor", 26),
        ("plan", 30),
        ("execute", 33),
        ("scheduler", 36),
    ]
    monitor = supervisor.stages[0]
    assert [v.name for v in monitor.values("inputs")] == ["dust"]
    (history,) = monitor.values("recorded_data")
    assert isinstance(history.type, s.SeqType)
    assert [v.name for v in supervisor.stages[3].values("period")] == ["10"]
    assert (motion.layer_type, motion.pattern, motion.stages) == ("ControlLayer", None, ())
    assert [u.interface for u in motion.uses] == ["Sensing"]
    assert [u.interface for u in motion.requires] == ["Driving"]
    assert [v.name for v in motion.inputs] == ["route"]
    assert [v.name for v in motion.outputs] == ["dust"]


def test_unknown_roboarch_block_is_a_located_note() -> None:
    (note,) = _rac().notes
    assert note.loc == s.Loc("layered.rac", 36, 2)
    assert "scheduler" in note.message


# ------------------------------------------------------------------------------ mistakes


def _error(text: str, *, arch: bool = False) -> Diagnostic:
    parsed, diagnostics = (parse_roboarch if arch else parse_robochart)(text, "bad")
    assert parsed is None
    (diagnostic,) = diagnostics
    assert diagnostic.severity == "error"
    assert " - " in diagnostic.message  # what is wrong, then how to fix it
    return diagnostic


STM = "stm M {\n  initial i\n  state S {}\n"


@pytest.mark.parametrize(
    ("text", "line", "column", "says"),
    [
        pytest.param(
            STM + "  transition t {\n    from i\n    trigger e\n  }\n}\n",
            6,
            5,
            "in transition 't': found 'trigger' where 'to' is expected - write 'to' here",
            id="missing-to",
        ),
        pytest.param(
            STM + "  transition t { from i to S action a condition c }\n}\n",
            4,
            39,
            "found 'condition' where '}' is expected - a transition's clauses go in the order",
            id="clauses-out-of-order",
        ),
        pytest.param(
            STM + "  stat T {}\n}\n",
            4,
            3,
            "in stm 'M': found name 'stat' where",
            id="misspelt-keyword",
        ),
        pytest.param(
            STM + "  transition t { from i to S action }\n}\n",
            4,
            37,
            "found '}' where an action is expected - write an action here",
            id="empty-action",
        ),
        pytest.param(
            STM + "  state T { entry }\n}\n",
            4,
            19,
            "found '}' where an entry action is expected",
            id="empty-entry",
        ),
        pytest.param(
            STM + "  transition t { from i to S action f(x\n  }\n}\n",
            5,
            3,
            "found '}' but '(' at line 4 column 38 is still open - close it with ')' first",
            id="unclosed-paren-in-action",
        ),
        pytest.param(
            STM + "  transition t { from i to S condition a[1)\n  }\n}\n",
            4,
            43,
            "found ')' but '[' at line 4 column 41 is still open",
            id="mismatched-bracket",
        ),
        pytest.param(
            STM + "  transition t { from i to S action f(x))\n  }\n}\n",
            4,
            41,
            "found ')' where '}' is expected",
            id="stray-closing-bracket",
        ),
        pytest.param(
            STM + "  transition t { from i to S action f(x\n",
            4,
            38,
            "'(' is never closed - add ')' where an action ends",
            id="paren-open-at-end",
        ),
        pytest.param(
            "stm M {\n  state S {\n    entry x = 1\n",
            3,
            16,
            "found the end of the file where 'during' or 'entry' or 'exit' or 'final'",
            id="unclosed-block",
        ),
        pytest.param(
            "datatype D {\n  f : Seq(\n}\n",
            3,
            1,
            "in datatype 'D': found '}' where a name or '(' or '?' or 'Seq' or 'Set' is expected",
            id="incomplete-type",
        ),
        pytest.param(
            "datatype D {\n  f real\n}\n",
            2,
            5,
            "found name 'real' where ':' is expected - write ':' here",
            id="field-without-colon",
        ),
        pytest.param(
            "controller C {\n  connection a e to b on f\n}\n",
            2,
            16,
            "found name 'e' where 'on' is expected - write 'on' here",
            id="connection-without-on",
        ),
        pytest.param(
            "controller C {\n  connection a on e to b on f (_sync)\n}\n",
            2,
            32,
            "found name '_sync' where '_async' or '_bidirec' is expected - did you mean '_async'?",
            id="bad-connection-flag",
        ),
        pytest.param(
            "controller C {\n  sref = M\n}\n",
            2,
            8,
            "found '=' where a name is expected - write a name here",
            id="reference-without-name",
        ),
        pytest.param(
            "interface I { event e : real ^ }\n",
            1,
            30,
            "found '^' where",
            id="unexpected-symbol",
        ),
        pytest.param(
            "interface I {\n  /* event e }\n",
            2,
            3,
            "comment '/*' is never closed - end it with '*/'",
            id="unterminated-comment",
        ),
        pytest.param(
            'interface I { const s : string = "abc\n}\n',
            1,
            34,
            "string is not closed on its line",
            id="unterminated-string",
        ),
        pytest.param(
            "import a::*::b\n",
            1,
            12,
            "found '::' where",
            id="bad-import",
        ),
    ],
)
def test_syntax_error_is_located_and_worded_for_a_user(
    text: str, line: int, column: int, says: str
) -> None:
    diagnostic = _error(text)
    assert (diagnostic.file, diagnostic.line, diagnostic.column) == ("bad", line, column)
    assert says in diagnostic.message


def test_misspelt_keyword_gets_a_suggestion() -> None:
    assert _error(STM + "  stat T {}\n}\n").message.endswith("did you mean 'state'?")


@pytest.mark.parametrize(
    ("text", "line", "column", "says"),
    [
        pytest.param(
            "layer L { }\n", 1, 1, "found 'layer' where 'system' is expected", id="no-system"
        ),
        pytest.param(
            "system S\nlayer L { inputs = ; }\n",
            2,
            20,
            "in layer 'L': found ';' where a name or a number or a string is expected",
            id="empty-property",
        ),
        pytest.param(
            "system S\nlayer L { monitor { inputs = a } }\n",
            2,
            32,
            "in 'monitor': found '}' where",
            id="property-without-semicolon",
        ),
        pytest.param(
            "system S\nconnections = A on x to B on y\n",
            2,
            31,
            "found the end of the file where",
            id="connections-without-semicolon",
        ),
    ],
)
def test_roboarch_syntax_error_is_located(text: str, line: int, column: int, says: str) -> None:
    diagnostic = _error(text, arch=True)
    assert (diagnostic.line, diagnostic.column) == (line, column)
    assert says in diagnostic.message


def test_diagnostic_reads_file_line_column_severity_what_and_how() -> None:
    line = str(_error("controller C {\n  connection a e to b on f\n}\n"))
    assert line == (
        "bad:2:16: error: syntax error in controller 'C': found name 'e' where 'on' is "
        "expected - write 'on' here"
    )


def test_second_entry_action_is_an_error_but_the_file_is_kept() -> None:
    parsed, diagnostics = parse_robochart(
        "stm M {\n  state S {\n    entry a\n    entry b\n  }\n}\n", "d.rct"
    )
    assert parsed is not None
    assert [(d.severity, d.line, d.column) for d in diagnostics] == [("error", 4, 11)]
    assert "second entry action (the first is at line 3)" in diagnostics[0].message


def test_second_platform_in_a_module_is_an_error() -> None:
    parsed, diagnostics = parse_robochart("module M {\n  rref a = P\n  rref b = Q\n}\n", "m.rct")
    assert parsed is not None
    assert [(d.severity, d.line) for d in diagnostics] == [("error", 3)]


def test_unknown_top_level_declaration_is_skipped_with_a_warning_and_a_note() -> None:
    text = "package p\n\nwidget W {\n  a { b }\n};\nstn X { }\ninterface I { event e }\n"
    parsed, diagnostics = parse_robochart(text, "u.rct")
    assert parsed is not None
    assert [d.name for d in parsed.declarations] == ["I"]
    assert [(d.severity, d.line, d.column) for d in diagnostics] == [
        ("warning", 3, 1),
        ("warning", 6, 1),
    ]
    assert "'widget' does not start a declaration RAP reads; lines 3-5 skipped" in str(
        diagnostics[0]
    )
    assert diagnostics[1].message.endswith("did you mean 'stm'?")
    assert [n.loc.line for n in parsed.notes] == [3, 6]


def test_unknown_word_inside_a_block_is_an_error_not_a_skip() -> None:
    diagnostic = _error("interface I {\n  widget W { }\n}\n")
    assert (diagnostic.line, diagnostic.column) == (2, 10)


def test_empty_file_is_an_empty_package() -> None:
    parsed, diagnostics = parse_robochart("// nothing yet\n", "e.rct")
    assert diagnostics == []
    assert parsed == s.RcFile(None, (), (), (), s.Loc("e.rct", 1, 1))


# ------------------------------------------------------------------------------ guards


def test_oversized_text_is_a_diagnostic() -> None:
    text = "// " + "x" * MAX_BYTES + "\n"
    parsed, diagnostics = parse_robochart(text, "big.rct")
    assert parsed is None
    (diagnostic,) = diagnostics
    assert diagnostic.severity == "error"
    assert diagnostic.message.startswith(f"file is {MAX_BYTES + 4} bytes")
    assert "split it into several packages" in diagnostic.message


def test_nesting_up_to_the_limit_parses_without_recursion() -> None:
    depth = MAX_NESTING - 1
    text = "stm M {\n" + "state S {\n" * depth + "}\n" * depth + "}\n"
    parsed, diagnostics = parse_robochart(text, "deep.rct")
    assert diagnostics == []
    assert parsed is not None
    node: s.Node = parsed.declarations[0].nodes[0]  # type: ignore[union-attr]
    levels = 1
    while isinstance(node, s.State) and node.nodes:
        node, levels = node.nodes[0], levels + 1
    assert levels == depth


@pytest.mark.parametrize(
    "text",
    [
        pytest.param("stm M {" + " state S {" * 5000 + " }" * 5001, id="states"),
        pytest.param("stm M { state S { entry " + "(" * 5000 + ")" * 5000 + " } }", id="parens"),
        pytest.param("datatype D { f : " + "Seq(" * 5000 + "real" + ")" * 5000 + " }", id="types"),
    ],
)
def test_deep_nesting_is_a_diagnostic_not_a_recursion_error(text: str) -> None:
    diagnostic = _error(text)
    assert f"brackets nest deeper than {MAX_NESTING} levels" in diagnostic.message
    assert diagnostic.line == 1


@settings(max_examples=150, deadline=None)
@given(
    st.sampled_from(["types.rct", "machines.rct", "layered.rac"]),
    st.integers(min_value=0, max_value=4000),
    st.integers(min_value=0, max_value=20),
    st.text(alphabet='{}()[];:,=|<>/*"?!-_ \nabstmX0', max_size=6),
)
def test_damaged_models_never_raise(name: str, at: int, cut: int, insert: str) -> None:
    text = (FIXTURES / name).read_text(encoding="utf-8")
    at %= len(text)
    damaged = text[:at] + insert + text[at + cut :]
    parse = parse_roboarch if name.endswith(".rac") else parse_robochart
    parsed, diagnostics = parse(damaged, name)
    lines = damaged.count("\n") + 1
    for d in diagnostics:
        assert 1 <= d.line <= lines
        assert d.column >= 1
    assert parsed is not None or any(d.severity == "error" for d in diagnostics)


# ------------------------------------------------------------------------------ files


def test_files_are_picked_by_extension_and_directories_expanded(tmp_path: Path) -> None:
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "a.rct").write_text("package a\n", encoding="utf-8")
    (tmp_path / "b.rac").write_text("system B\n", encoding="utf-8")
    (tmp_path / "notes.txt").write_text("ignored inside a directory\n", encoding="utf-8")
    files, diagnostics = parse_robochart_files([tmp_path])
    assert diagnostics == []
    assert [(type(f).__name__, f.loc.file) for f in files] == [
        ("RacFile", str(tmp_path / "b.rac")),
        ("RcFile", str(tmp_path / "sub" / "a.rct")),
    ]


def test_unreadable_or_foreign_files_are_diagnostics(tmp_path: Path) -> None:
    foreign = tmp_path / "model.aadl"
    foreign.write_text("package x\n", encoding="utf-8")
    binary = tmp_path / "bad.rct"
    binary.write_bytes(b"package \xff\xfe\n")
    big = tmp_path / "big.rac"
    with big.open("wb") as f:
        f.truncate(MAX_BYTES + 1)
    missing = tmp_path / "missing.rct"
    broken = tmp_path / "broken.rct"
    broken.write_text("stm M {\n", encoding="utf-8")
    files, diagnostics = parse_robochart_files([foreign, binary, big, missing, broken])
    assert files == []
    assert [(Path(d.file).name, d.severity, d.line) for d in diagnostics] == [
        ("model.aadl", "error", 0),
        ("bad.rct", "error", 0),
        ("big.rac", "error", 0),
        ("missing.rct", "error", 0),
        ("broken.rct", "error", 1),
    ]
    assert "not a RoboChart or RoboArch file - give .rct or .rac files" in diagnostics[0].message
    assert "file is not UTF-8 text (byte 8) - save it as UTF-8" in diagnostics[1].message
    assert "more than the" in diagnostics[2].message
    assert str(diagnostics[3]).startswith(f"{missing}: error: cannot read the file")
