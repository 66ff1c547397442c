"""Lark parse tree -> :mod:`rap_cli.robochart.syntax` nodes (non-recursive).

:class:`Build` also collects diagnostics for what parses but is wrong or not modelled (a
second ``entry``, a second pattern, an unknown RoboArch block, a skipped declaration).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any, Literal

from lark import Token, Transformer_NonRecursive, v_args
from lark.tree import Meta

from rap_cli.diagnostics import Diagnostic, Severity

from . import syntax as s

__all__ = ["Build"]

_MAPLEK_STAGES = frozenset({"monitor", "analyse", "plan", "legitimate", "execute", "knowledge"})


@v_args(meta=True)
class Build(Transformer_NonRecursive[Token, Any]):
    """Parse tree -> :mod:`syntax` nodes; collects diagnostics for what parses but is
    wrong or not modelled (a second ``entry``, an unknown RoboArch block)."""

    def __init__(self, source: str, skipped: Iterable[tuple[int, int, str, str, str]]) -> None:
        super().__init__()
        self._source = source
        self.diagnostics: list[Diagnostic] = []
        self._notes: list[s.Note] = []
        for line, column, word, extent, hint in skipped:
            loc = s.Loc(source, line, column)
            message = f"'{word}' does not start a declaration RAP reads; {extent} skipped"
            self._notes.append(s.Note(loc, message))
            self._report(loc, "warning", f"{message} - {hint}")

    def _loc(self, meta: Meta | Token) -> s.Loc:
        return s.Loc(self._source, getattr(meta, "line", 1) or 1, getattr(meta, "column", 1) or 1)

    def _text(self, token: Token | None) -> s.Text | None:
        return None if token is None else s.Text(str(token), self._loc(token))

    def _report(self, loc: s.Loc, severity: Severity, message: str) -> None:
        self.diagnostics.append(Diagnostic(loc.file, loc.line, loc.column, severity, message))

    def _note(self, loc: s.Loc, message: str, fix: str) -> None:
        self._notes.append(s.Note(loc, message))
        self._report(loc, "note", f"{message} - {fix}")

    # ---- files, names, types

    def rct_file(self, meta: Meta, c: list[Any]) -> s.RcFile:
        package = c[0]
        return s.RcFile(
            package=package,
            imports=tuple(x for x in c[1:] if isinstance(x, s.Import)),
            declarations=tuple(x for x in c[1:] if not isinstance(x, s.Import)),
            notes=tuple(self._notes),
            loc=s.Loc(self._source, 1, 1),
        )

    def package(self, meta: Meta, c: list[Any]) -> str:
        return str(c[0])

    def import_(self, meta: Meta, c: list[Any]) -> s.Import:
        return s.Import("::".join(c[:-1]), c[-1] is not None, self._loc(meta))

    def import_all(self, meta: Meta, c: list[Any]) -> bool:
        return True

    def qname(self, meta: Meta, c: list[Token]) -> str:
        return "::".join(c)

    def type_name(self, meta: Meta, c: list[Any]) -> s.TypeName:
        return s.TypeName(c[0], self._loc(meta))

    def seq_type(self, meta: Meta, c: list[Any]) -> s.SeqType:
        return s.SeqType(c[0], self._loc(meta))

    def set_type(self, meta: Meta, c: list[Any]) -> s.SetType:
        return s.SetType(c[0], self._loc(meta))

    def type_param(self, meta: Meta, c: list[Any]) -> s.TypeParam:
        return s.TypeParam(str(c[0]), self._loc(meta))

    def product_type(self, meta: Meta, c: list[Any]) -> s.ProductType:
        return s.ProductType(tuple(c), self._loc(meta))

    def function_type(self, meta: Meta, c: list[Any]) -> s.FunctionType:
        return s.FunctionType(c[0], c[1], self._loc(meta))

    def primitive_type(self, meta: Meta, c: list[Any]) -> s.PrimitiveType:
        return s.PrimitiveType(str(c[0]), self._loc(meta))

    def record(self, meta: Meta, c: list[Any]) -> s.Record:
        return s.Record(str(c[1]), c[0], tuple(c[2:]), self._loc(meta))

    def field(self, meta: Meta, c: list[Any]) -> s.Field:
        return s.Field(str(c[0]), c[1], self._loc(meta))

    def enumeration(self, meta: Meta, c: list[Any]) -> s.Enumeration:
        return s.Enumeration(str(c[0]), tuple(c[1:]), self._loc(meta))

    def enum_literal(self, meta: Meta, c: list[Any]) -> s.EnumLiteral:
        return s.EnumLiteral(str(c[0]), self._loc(meta))

    # ---- members

    def event_decl(self, meta: Meta, c: list[Any]) -> s.Event:
        return s.Event(str(c[0]), c[1], self._loc(meta))

    def var_decl(self, meta: Meta, c: list[Any]) -> s.Variable:
        return s.Variable(str(c[1]), c[2], c[0] == "const", self._text(c[3]), self._loc(meta))

    def clock_decl(self, meta: Meta, c: list[Any]) -> s.Clock:
        return s.Clock(str(c[0]), self._loc(meta))

    def op_sig(self, meta: Meta, c: list[Any]) -> s.OperationSig:
        return s.OperationSig(str(c[0]), c[1] or (), self._loc(meta))

    def params(self, meta: Meta, c: list[Any]) -> tuple[s.Param, ...]:
        return tuple(c)

    def param(self, meta: Meta, c: list[Any]) -> s.Param:
        return s.Param(str(c[0]), c[1], self._loc(meta))

    def interface_use(self, meta: Meta, c: list[Any]) -> s.InterfaceUse:
        return s.InterfaceUse(c[0], c[1], self._loc(meta))

    def interface(self, meta: Meta, c: list[Any]) -> s.Interface:
        items = c[1:]
        return s.Interface(
            name=str(c[0]),
            events=_only(items, s.Event),
            variables=_only(items, s.Variable),
            operations=_only(items, s.OperationSig),
            clocks=_only(items, s.Clock),
            loc=self._loc(meta),
        )

    def platform(self, meta: Meta, c: list[Any]) -> s.RoboticPlatform:
        items = c[1:]
        return s.RoboticPlatform(
            name=str(c[0]),
            **_uses(items),
            events=_only(items, s.Event),
            variables=_only(items, s.Variable),
            operations=_only(items, s.OperationSig),
            clocks=_only(items, s.Clock),
            loc=self._loc(meta),
        )

    # ---- controllers and modules

    def controller(self, meta: Meta, c: list[Any]) -> s.Controller:
        machines: list[s.MachineRef] = []
        operations: list[s.OperationRef] = []
        for x in c[1:]:
            if isinstance(x, s.MachineRef):
                machines.append(x)
            elif isinstance(x, s.OperationRef):
                operations.append(x)
            elif isinstance(x, s.StateMachine) and x.kind == "stm":
                machines.append(s.MachineRef(x.name, "stm", None, x, x.loc))
            elif isinstance(x, s.StateMachine):
                operations.append(s.OperationRef(x.name, None, x, x.loc))
        return s.Controller(
            name=str(c[0]),
            **_uses(c[1:]),
            events=_only(c[1:], s.Event),
            variables=_only(c[1:], s.Variable),
            clocks=_only(c[1:], s.Clock),
            machines=tuple(machines),
            operations=tuple(operations),
            connections=_only(c[1:], s.Connection),
            loc=self._loc(meta),
        )

    def machine_ref(self, meta: Meta, c: list[Any]) -> s.MachineRef:
        return s.MachineRef(str(c[1]), c[0], c[2], None, self._loc(meta))

    def op_ref(self, meta: Meta, c: list[Any]) -> s.OperationRef:
        return s.OperationRef(str(c[0]), c[1], None, self._loc(meta))

    def connection(self, meta: Meta, c: list[Any]) -> s.Connection:
        (a, e), (b, f), *options = c
        flags = {flag for option in options for flag in option}
        return s.Connection(a, e, b, f, "_async" in flags, "_bidirec" in flags, self._loc(meta))

    rac_connection = connection

    def endpoint(self, meta: Meta, c: list[Token]) -> tuple[str, str]:
        return str(c[0]), str(c[1])

    def connection_option(self, meta: Meta, c: list[str]) -> set[str]:
        return set(c)

    def module(self, meta: Meta, c: list[Any]) -> s.Module:
        platforms = [x for x in c[1:] if isinstance(x, s.PlatformRef | s.RoboticPlatform)]
        for extra in platforms[1:]:
            self._report(
                extra.loc,
                "error",
                f"module '{c[0]}' has a second robotic platform - keep one platform per module",
            )
        platform = platforms[0] if platforms else None
        if isinstance(platform, s.RoboticPlatform):
            platform = s.PlatformRef(platform.name, None, platform, platform.loc)
        controllers = [
            s.ControllerRef(x.name, None, x, x.loc) if isinstance(x, s.Controller) else x
            for x in c[1:]
            if isinstance(x, s.Controller | s.ControllerRef)
        ]
        return s.Module(
            name=str(c[0]),
            platform=platform,
            controllers=tuple(controllers),
            connections=_only(c[1:], s.Connection),
            loc=self._loc(meta),
        )

    def platform_ref(self, meta: Meta, c: list[Any]) -> s.PlatformRef:
        return s.PlatformRef(str(c[0]), c[1], None, self._loc(meta))

    def controller_ref(self, meta: Meta, c: list[Any]) -> s.ControllerRef:
        return s.ControllerRef(str(c[0]), c[1], None, self._loc(meta))

    # ---- state machines

    def _machine(
        self,
        meta: Meta,
        name: Token,
        kind: Literal["stm", "operation"],
        params: Any,
        items: list[Any],
    ) -> s.StateMachine:
        return s.StateMachine(
            name=str(name),
            kind=kind,
            params=params or (),
            **_uses(items),
            variables=_only(items, s.Variable),
            events=_only(items, s.Event),
            clocks=_only(items, s.Clock),
            operations=_only(items, s.OperationRef),
            nodes=_only(items, s.State, s.Initial, s.Final, s.Junction),
            transitions=_only(items, s.Transition),
            loc=self._loc(meta),
        )

    def stm(self, meta: Meta, c: list[Any]) -> s.StateMachine:
        return self._machine(meta, c[0], "stm", None, c[1:])

    def operation(self, meta: Meta, c: list[Any]) -> s.StateMachine:
        return self._machine(meta, c[0], "operation", c[1], c[2:])

    def state(self, meta: Meta, c: list[Any]) -> s.State:
        actions: dict[str, s.Text] = {}
        for kind, text in (x for x in c[1:] if isinstance(x, tuple)):
            if kind in actions:
                self._report(
                    text.loc,
                    "error",
                    f"state '{c[0]}' has a second {kind} action (the first is at line "
                    f"{actions[kind].loc.line}) - join them with ';'",
                )
            else:
                actions[kind] = text
        return s.State(
            name=str(c[0]),
            entry=actions.get("entry"),
            during=actions.get("during"),
            exit=actions.get("exit"),
            nodes=_only(c[1:], s.State, s.Initial, s.Final, s.Junction),
            transitions=_only(c[1:], s.Transition),
            loc=self._loc(meta),
        )

    def state_action(self, meta: Meta, c: list[Any]) -> tuple[str, s.Text | None]:
        return str(c[0]), self._text(c[1])

    def initial(self, meta: Meta, c: list[Any]) -> s.Initial:
        return s.Initial(str(c[0]), self._loc(meta))

    def final(self, meta: Meta, c: list[Any]) -> s.Final:
        return s.Final(str(c[0]), self._loc(meta))

    def junction(self, meta: Meta, c: list[Any]) -> s.Junction:
        return s.Junction(str(c[1]), c[0] is not None, self._loc(meta))

    def transition(self, meta: Meta, c: list[Any]) -> s.Transition:
        name, source, target, trigger, probability, guard, action = c
        return s.Transition(
            str(name), source, target, trigger, probability, guard, action, self._loc(meta)
        )

    def trigger(self, meta: Meta, c: list[Any]) -> s.Text | None:
        return self._text(c[0])

    probability = condition = action = trigger

    # ---- functions

    def function(self, meta: Meta, c: list[Any]) -> s.FunctionDecl:
        clauses: list[tuple[str, s.Text]] = c[3] or []
        return s.FunctionDecl(
            name=str(c[0]),
            params=c[1] or (),
            result=c[2],
            preconditions=tuple(t for k, t in clauses if k == "precondition"),
            postconditions=tuple(t for k, t in clauses if k == "postcondition"),
            loc=self._loc(meta),
        )

    def function_body(self, meta: Meta, c: list[Any]) -> list[Any]:
        return c

    def function_clause(self, meta: Meta, c: list[Any]) -> tuple[str, s.Text | None]:
        return str(c[0]), self._text(c[1])

    # ---- keyword alternatives kept as strings

    def _keyword(self, meta: Meta, c: list[Token]) -> str:
        return str(c[0])

    record_kind = var_kind = use_kind = machine_ref_kind = connection_flag = _keyword
    state_action_kind = function_clause_kind = probabilistic = _keyword

    # ---- RoboArch

    def rac_file(self, meta: Meta, c: list[Any]) -> s.RacFile:
        items = c[1:]
        connections = [conn for x in items if isinstance(x, list) for conn in x]
        return s.RacFile(
            system=c[0],
            declarations=tuple(x for x in items if not isinstance(x, s.Layer | list)),
            layers=_only(items, s.Layer),
            connections=tuple(connections),
            notes=tuple(self._notes),
            loc=s.Loc(self._source, 1, 1),
        )

    def system(self, meta: Meta, c: list[Any]) -> str:
        return str(c[0])

    def rac_connections(self, meta: Meta, c: list[Any]) -> list[s.Connection]:
        return list(c)

    def layer(self, meta: Meta, c: list[Any]) -> s.Layer:
        name, layer_type, items = str(c[0]), c[1], c[2:]
        props = _only(items, s.Property)
        pattern = [v for p in props if p.key == "pattern" for v in p.values]
        for extra in pattern[1:]:
            self._report(
                extra.loc,
                "error",
                f"layer '{name}' names a second pattern '{extra.name}' - keep one",
            )
        stages = _only(items, s.LayerBlock)
        for stage in stages:
            if stage.name.lower() not in _MAPLEK_STAGES:
                self._note(
                    stage.loc,
                    f"block '{stage.name}' of layer '{name}' is not a MAPLE-K stage; "
                    "it is kept as a generic block",
                    "rename it to monitor, analyse, plan, legitimate or execute if it is one",
                )
        return s.Layer(
            name=name,
            layer_type=None if layer_type is None else str(layer_type),
            **_uses(items),
            inputs=tuple(v for p in props if p.key == "inputs" for v in p.values),
            outputs=tuple(v for p in props if p.key == "outputs" for v in p.values),
            pattern=pattern[0].name if pattern else None,
            stages=stages,
            properties=tuple(p for p in props if p.key not in ("inputs", "outputs", "pattern")),
            loc=self._loc(meta),
        )

    def layer_block(self, meta: Meta, c: list[Any]) -> s.LayerBlock:
        return s.LayerBlock(
            name=str(c[0]),
            **_uses(c[1:]),
            properties=_only(c[1:], s.Property),
            blocks=_only(c[1:], s.LayerBlock),
            loc=self._loc(meta),
        )

    def layer_property(self, meta: Meta, c: list[Any]) -> s.Property:
        return s.Property(str(c[0]), tuple(c[1:]), self._loc(meta))

    def named_value(self, meta: Meta, c: list[Any]) -> s.PropertyValue:
        return s.PropertyValue(str(c[0]), c[1], self._loc(meta))

    def hyphen_value(self, meta: Meta, c: list[Token]) -> s.PropertyValue:
        return s.PropertyValue("-".join(c), None, self._loc(meta))

    def literal_value(self, meta: Meta, c: list[Token]) -> s.PropertyValue:
        return s.PropertyValue(str(c[0]), None, self._loc(meta))


def _only(items: Iterable[Any], *types: type) -> tuple[Any, ...]:
    """The items of the given types, in order."""
    return tuple(x for x in items if isinstance(x, types))


def _uses(items: Iterable[Any]) -> dict[str, tuple[s.InterfaceUse, ...]]:
    """``uses``/``provides``/``requires`` keyword arguments from a body's items."""
    found: dict[str, list[s.InterfaceUse]] = {"uses": [], "provides": [], "requires": []}
    for x in items:
        if isinstance(x, s.InterfaceUse):
            found[x.kind].append(x)
    return {k: tuple(v) for k, v in found.items()}
