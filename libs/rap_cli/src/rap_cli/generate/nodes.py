"""A node module per generated component: handlers for its inputs, a ``send_<port>`` per
output, its knowledge keys, a config Struct, snapshot and restore hooks, and the gate.

Everything the user writes goes in ``# region user:`` blocks (see :mod:`.regions`). The
generated default behaviour forwards: each input handler writes the component's
knowledge keys and sends every output (the input itself where the types agree, an
example message otherwise), so that the generated package runs end to end before any
code is written; replace it with the component's logic.
"""

from __future__ import annotations

from rap_schemas import DeploymentPlan

from .messages import MessageNames
from .names import identifier
from .pyfmt import Call, docstring, import_from, lines, q
from .regions import begin, end
from .wiring import ComponentWiring, PortWiring

__all__ = ["PLACEHOLDER_CHECK", "module_name", "node_module", "periodic_threads"]

PLACEHOLDER_CHECK = "# placeholder: approves every plan within the model's constraints;"
"""The first line of a generated check() region: while it is there, rap generate warns."""


def module_name(component: str, taken: dict[str, str]) -> str:
    """The module (in ``<package>.nodes``) of ``component``."""
    return taken.get(component) or identifier(component, prefix="c")


def _cls(p: PortWiring, names: MessageNames) -> str | None:
    cls = names.wire(p.type)
    if cls is None:
        return None
    return cls if names.is_rap(p.type) else f"messages.{cls}"


def _docline(text: str) -> str:
    return " ".join(text.split()).replace('"""', "'''").replace("\\", "/")


def periodic_threads(cw: ComponentWiring, taken: set[str]) -> list[tuple[str, str, float]]:
    """(thread, handler function, period in seconds) of each thread of ``cw`` that the
    model dispatches periodically at a known rate; each function ``on_<thread>``, made
    unique against ``taken`` (the input handlers' names) and the others. A sporadic
    thread, or one without a rate, gets no handler (its inputs' handlers serve it)."""
    out: list[tuple[str, str, float]] = []
    used = set(taken)
    for thread, spec in cw.spec.threads.items():
        d = spec.dispatch
        if d is None or d.kind != "periodic" or not d.rate_hz:
            continue
        base = fn = f"on_{identifier(thread)}"
        n = 1
        while fn in used:
            n += 1
            fn = f"{base}_{n}"
        used.add(fn)
        out.append((thread, fn, 1.0 / d.rate_hz))
    return out


def _keys(name: str, keys: list[str]) -> list[str]:
    """``NAME: tuple[str, ...] = ("a", "b")`` (wrapped when long)."""
    head = f"{name}: tuple[str, ...] = "
    if len(keys) <= 1:
        return [f"{head}({q(keys[0])},)" if keys else f"{head}()"]
    return lines(Call(head, tuple(q(k) for k in keys)))


def _def(head: str, params: str, tail: str) -> list[str]:
    """``head(params)tail``: a ``def`` line, its parameters one a line when too long."""
    return lines(Call(head, tuple(params.split(", "))), "", tail)


def _max_age(cw: ComponentWiring) -> float:
    """The default ``plan_max_age`` of an execute stage's Config: the model's
    ``config: {plan_max_age: ..}`` when it gives a number, else 1 s."""
    value = cw.spec.config.get("plan_max_age")
    if isinstance(value, int | float) and not isinstance(value, bool) and value > 0:
        return float(value)
    return 1.0


def _region(rid: str, body: list[str], indent: str) -> list[str]:
    return [begin(rid, indent), *(f"{indent}{b}" if b else "" for b in body), end(rid, indent)]


def _send_body(cw: ComponentWiring, p: PortWiring, names: MessageNames) -> list[str]:
    """The body of ``send_<port>(ctx, msg)``."""
    cls = _cls(p, names)
    lines = []
    if p.channel.knowledge:
        arg = "msg" if cls else "True"
        lines.append(f"await ctx.kb.write({q(p.channel.knowledge)}, {arg})")
    if p.role == "proposal":
        lines.append("await propose(ctx, msg)" if cls else "await propose(ctx, Empty())")
    elif p.channel.family == "data":
        lines.append(f"await ctx.publish({q(p.channel.key)}, {'msg' if cls else 'Empty()'})")
    else:
        lines.append(f"await ctx.emit({q(p.channel.key)}{', msg' if cls else ''})")
    return lines


def _forward(cw: ComponentWiring, names: MessageNames, incoming: str | None) -> list[str]:
    """Default behaviour of a handler: write the keys, send every output."""
    value = "msg" if incoming else "True"
    lines = [
        f"await ctx.kb.write({q(key)}, {value})"
        for key in cw.spec.writes
        if not any(o.channel.knowledge == key for o in cw.outputs)
    ]
    return lines + _send_all(cw, names, incoming, "msg")


def _send_all(cw: ComponentWiring, names: MessageNames, given: str | None, expr: str) -> list[str]:
    """A call of every ``send_<port>``: with ``expr`` (of class ``given``) where the
    output takes that class, an example message otherwise."""
    lines = []
    for o in cw.outputs:
        cls = _cls(o, names)
        fn = f"send_{identifier(o.port)}"
        if cls is None:
            lines.append(f"await {fn}(ctx)")
        elif cls == given:
            lines.append(f"await {fn}(ctx, {expr})")
        else:
            lines.append(f"await {fn}(ctx, sample({cls}))")
    return lines


def _guarded(rid: str, user: list[str], generated: list[str]) -> list[str]:
    """A handler body: the user's region, then the generated forwarding while
    ``FORWARD`` is on (regenerated with the model: new outputs are forwarded too)."""
    out = _region(rid, user, "    ")
    if generated:
        out += ["    if FORWARD:", *(f"        {line}" for line in generated)]
    return out


def node_module(
    cw: ComponentWiring, plan: DeploymentPlan, names: MessageNames, *, source: str
) -> str:
    """The text of ``<package>/nodes/<module>.py`` for component ``cw``."""
    stage = cw.stage
    gate_in = [p for p in cw.inputs if p.role in ("judged", "approved")]
    plan_cls = None
    if cw.plan_type is not None or gate_in or any(o.role == "proposal" for o in cw.outputs):
        plan_cls = names.wire(cw.plan_type)
        if plan_cls is not None and not names.is_rap(cw.plan_type):
            plan_cls = f"messages.{plan_cls}"
    plan_cls = plan_cls or "Empty"
    rap_types = sorted(
        {names.wire(p.type) or "" for p in [*cw.inputs, *cw.outputs] if names.is_rap(p.type)} - {""}
    )
    schema_imports = {"Empty", *rap_types}
    if gate_in:
        schema_imports.add("PlanProposal")
    gate_imports = []
    if any(o.role == "proposal" for o in cw.outputs):
        gate_imports.append("propose")
    if any(p.role == "judged" for p in cw.inputs):
        gate_imports.append("legitimate")
        schema_imports.add("PlanProposal")
    if any(p.role == "approved" for p in cw.inputs):
        gate_imports.append("ApprovalGate")

    def describe(p: PortWiring) -> str:
        return f"- {p.port}: {what(p)}"

    def what(p: PortWiring) -> str:
        kind = "data topic" if p.channel.family == "data" else "event"
        t = p.type or "no payload"
        extra = f", knowledge key {p.channel.knowledge!r}" if p.channel.knowledge else ""
        how = {
            "proposal": " - proposed to the Legitimate stage (the gate's event 'new-plan')",
            "judged": " - judged here (the gate: event 'new-plan', answered on 'verdict')",
            "approved": " - approved plans only (the gate: event 'verdict')",
        }.get(p.role, "")
        return f"{kind} {p.channel.key!r} ({t}{extra}){how}"

    doc = [
        f"Component {cw.name!r} ({stage or cw.spec.role or 'no stage'}) of system {plan.system!r}.",
        "",
    ]
    if cw.spec.doc:
        doc += [_docline(cw.spec.doc), ""]
    doc += [
        f"Generated by ``rap generate`` from {source}. Write your code between the",
        "``# region user: <id>`` and ``# endregion user: <id>`` lines (or in modules of",
        "your own): regenerating keeps those blocks and rewrites the rest of this file.",
        "",
    ]
    if cw.inputs:
        doc += ["Inputs:", *(describe(p) for p in cw.inputs), ""]
    if cw.outputs:
        doc += ["Outputs:", *(describe(p) for p in cw.outputs), ""]
    doc += [
        f"Knowledge: reads {', '.join(cw.reads) or 'nothing'}; writes "
        f"{', '.join(cw.writes) or 'nothing'}.",
    ]
    out = [*docstring("\n".join(doc), ""), "", "from __future__ import annotations", ""]
    out += ["import logging", "", "import msgspec", *import_from("rap_schemas", schema_imports)]
    out.append("from rap_sdk import Context, Node")
    if gate_imports:
        out += import_from("rap_sdk.gate", gate_imports)
    out += ["", "from .. import messages", "from ..samples import sample", ""]
    # the user's imports sort apart from the generated ones, and end with a blank line
    out.append("# isort: split")
    out += _region("imports", [""], "")
    out += [""]
    out += _region(
        "behaviour",
        [
            "FORWARD = True",
            '"""While True, each handler forwards after your code: it writes the knowledge',
            "keys and sends every output (the input where the types agree, an example",
            "otherwise), so that the package runs end to end from the start. Set it to",
            'False once your handlers send what they should; the generated tests follow it."""',
        ],
        "",
    )
    out += [
        "",
        '__all__ = ["Config", "State", "node"]',
        "",
        "log = logging.getLogger(__name__)",
        "",
        *_keys("READS", cw.reads),
        '"""Knowledge keys this component reads (the model\'s ``reads``)."""',
        *_keys("WRITES", cw.writes),
        '"""Knowledge keys this component writes (``writes``, and the knowledge ports it',
        'feeds)."""',
        "",
        "",
        "class Config(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):",
        f'    """Settings of {cw.name} (model: ``components.{cw.name}.config``)."""',
        "",
    ]
    if any(p.role == "approved" for p in cw.inputs):
        out += [
            f"    plan_max_age: float = {_max_age(cw)!r}",
            '    """Seconds an approved plan stays executable after its creation (the gate',
            "    takes the value the node is configured with: the model's ``config:``, or",
            '    ``rap admin config``)."""',
            "",
        ]
    out += _region("config", ["pass"], "    ")
    out += [
        "",
        "",
        "class State(msgspec.Struct, kw_only=True):",
        f'    """What {cw.name} remembers; snapshot and restore carry it across restarts',
        '    and swaps."""',
        "",
    ]
    out += _region("state", ["pass"], "    ")
    out += [
        "",
        "",
        "state = State()",
        f"node = Node({q(cw.name)}, stage={q(stage) if stage else None}, config=Config())",
    ]
    if any(p.role == "approved" for p in cw.inputs):
        legitimators = f"[{', '.join(q(n) for n in sorted(cw.legitimators))}]"
        args = (
            f"legitimators={legitimators}",
            "max_age=Config().plan_max_age",
            'max_age_config="plan_max_age"',
        )
        out += lines(Call("gate = ApprovalGate", args))
    out += [
        "",
        "",
        "@node.on_snapshot",
        "def snapshot() -> State:",
        "    return state",
        "",
        "",
        "@node.on_restore",
        "def restore(saved: State) -> None:",
        "    for name in State.__struct_fields__:",
        "        setattr(state, name, getattr(saved, name))",
    ]
    if any(p.role == "judged" for p in cw.inputs):
        out += [
            "",
            "",
            "def breaks_constraints(plan: msgspec.Struct) -> str | None:",
            '    """Why ``plan`` breaks its message\'s constraints (a Struct built in code is',
            '    not validated; decoding it again is), or None."""',
            "    try:",
            "        msgspec.convert(msgspec.to_builtins(plan), type(plan))",
            "    except msgspec.ValidationError as exc:",
            '        return f"the plan breaks the model\'s constraints: {exc}"',
            "    return None",
        ]
    for key in cw.reads:
        out += [
            "",
            "",
            f"async def read_{identifier(key)}(ctx: Context) -> object:",
            *docstring(f"Knowledge key {key!r} (None while nobody wrote it).", "    "),
            f"    return await ctx.kb.read({q(key)}, default=None)",
        ]
    for o in cw.outputs:
        cls = _cls(o, names)
        sig = f"ctx: Context, msg: {cls}" if cls else "ctx: Context"
        out += [
            "",
            "",
            *_def(f"async def send_{identifier(o.port)}", sig, " -> None:"),
            *docstring(f"Output {o.port}: {what(o)}.", "    "),
            *(f"    {line}" for line in _send_body(cw, o, names)),
        ]
    seen: set[tuple[str, str]] = set()
    taken: set[str] = set()
    for p in cw.handlers:
        chan = (p.channel.family, p.channel.key)
        if chan in seen:
            continue  # two ports on one channel: one handler (a key is handled once)
        seen.add(chan)
        cls = _cls(p, names)
        deco = "on_data" if p.channel.family == "data" else "on_event"
        fn = f"on_{identifier(p.port)}"
        taken.add(fn)
        sig = f"ctx: Context, msg: {cls}" if cls else "ctx: Context"
        out += [
            "",
            "",
            *lines(Call(f"@node.{deco}", (q(p.channel.key),))),
            *_def(f"async def {fn}", sig, " -> None:"),
            *docstring(f"Input {p.port}: {what(p)}.", "    "),
            *_guarded(
                fn, [f"# {cw.name}'s handling of {p.port} goes here"], _forward(cw, names, cls)
            ),
        ]
    for thread, fn, period in periodic_threads(cw, taken):
        spec = cw.spec.threads[thread]
        modes = f"; the model puts it in modes {', '.join(spec.in_modes)}" if spec.in_modes else ""
        out += [
            "",
            "",
            f"@node.every({period!r})",
            f"async def {fn}(ctx: Context) -> None:",
            f'    """Thread {thread}: periodic, every {period:g} s{modes}.',
            "",
            "    The runtime calls it on that period while the node runs, one call at a time;",
            '    a call that overruns skips the ticks it missed."""',
            *_region(fn, [f"# what {thread} does every period goes here"], "    "),
        ]
    judged = [p for p in cw.inputs if p.role == "judged"]
    if judged:
        out += [
            "",
            "",
            f"@legitimate(node, plan={plan_cls})",
            *_def(
                "async def check",
                f"ctx: Context, proposal: PlanProposal[{plan_cls}]",
                " -> str | None:",
            ),
            '    """Judge a proposed plan: None approves it, a string rejects it with that',
            "    reason (an exception rejects it too). A plan that breaks the constraints of",
            '    its message in the model is rejected before your checks run."""',
            "    broken = breaks_constraints(proposal.plan)",
            "    if broken is not None:",
            "        return broken",
            *_region(
                "check",
                [
                    PLACEHOLDER_CHECK,
                    "# write the checks that make a plan safe to run here",
                    "return None",
                ],
                "    ",
            ),
        ]
    approved = [p for p in cw.inputs if p.role == "approved"]
    if approved:
        body = _send_all(cw, names, plan_cls, "proposal.plan")
        out += [
            "",
            "",
            f"@gate.on_approved(node, plan={plan_cls})",
            *_def(
                "async def act", f"ctx: Context, proposal: PlanProposal[{plan_cls}]", " -> None:"
            ),
            '    """Execute a plan that the Legitimate stage approved (fresh, never run',
            '    before): the only way this stage acts on plans."""',
            *_guarded("act", ["# act on proposal.plan here"], body),
        ]
    out += ["", ""]
    out += _region("code", [], "")
    return "\n".join(out) + "\n"
