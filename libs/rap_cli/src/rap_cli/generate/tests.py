"""The tests of a generated package: a Harness test per component and a whole-loop test.

They run against the generated default behaviour (each input sends every output; the
legitimate stage approves; execute acts through the gate), on the in-memory fabric with
RAP's knowledge service. Each test's expectations sit in a user region: when a
component's code changes what it sends, change them there; regenerating keeps them.
"""

from __future__ import annotations

from .messages import MessageNames
from .names import identifier
from .regions import begin, end
from .wiring import Channel, ComponentWiring, PortWiring, Wiring

__all__ = ["component_test", "conftest", "loop_test"]

_HEAD = [
    "from __future__ import annotations",
    "",
    "import pytest",
    "from knowledge.app import open_service",
    "from knowledge.config import KnowledgeConfig",
    "from rap_schemas import Empty, Verdict",
    "from rap_sdk import Context, Node",
    "from rap_sdk.gate import propose",
    "from rap_sdk.testing import Harness",
    "",
]


def conftest() -> str:
    return "\n".join(
        [
            '"""Shared settings of the generated tests (regenerated)."""',
            "",
            "import pytest",
            "",
            "",
            "@pytest.fixture",
            "def anyio_backend() -> str:",
            '    return "asyncio"',
            "",
        ]
    )


def _cls(p: PortWiring, names: MessageNames) -> str | None:
    cls = names.wire(p.type)
    if cls is None:
        return None
    return cls if names.is_rap(p.type) else f"messages.{cls}"


def _send(p: PortWiring, names: MessageNames, indent: str) -> str:
    cls = _cls(p, names)
    msg = f"sample({cls})" if cls else "Empty()"
    verb = "publish" if p.channel.family == "data" else "emit"
    return f"{indent}await h.{verb}({p.channel.key!r}, {msg})"


def _expect(ch: Channel, indent: str, after: str = "") -> str:
    verb = "expect_data" if ch.family == "data" else "expect_event"
    since = f", after={after}" if after else ""
    return f"{indent}await h.{verb}({ch.key!r}{since})"


def _checks(rid: str, body: list[str], switch: str) -> list[str]:
    """The generated expectations (regenerated with the model), while the nodes forward
    (their ``FORWARD``), then the user's own checks."""
    return [
        f"        if {switch}:  # the generated behaviour: each input reaches every output",
        *(f"    {line}" if line.strip() else line for line in body),
        begin(rid, "        "),
        end(rid, "        "),
    ]


def _proposer(plan_cls: str) -> list[str]:
    return [
        "",
        "",
        "def proposer() -> Node:",
        '    """A stand-in plan stage: on event ``test-go`` it proposes an example plan."""',
        '    node = Node("test-proposer", stage="plan")',
        "",
        '    @node.on_event("test-go")',
        "    async def go(ctx: Context) -> None:",
        f"        await propose(ctx, {_sample(plan_cls)})",
        "",
        "    return node",
    ]


def _sample(cls: str) -> str:
    return "Empty()" if cls == "Empty" else f"sample({cls})"


def _imports(package: str, modules: list[str], extra: list[str] | None = None) -> list[str]:
    out = [f"from {package} import messages", f"from {package}.samples import sample"]
    out += [f"from {package}.nodes import {m}" for m in modules]
    out += extra or []
    return [*out, "", "pytestmark = pytest.mark.anyio", "", 'SYSTEM = "test"']


def _plan_cls(cw: ComponentWiring, names: MessageNames) -> str:
    cls = names.wire(cw.plan_type)
    if cls is None:
        return "Empty"
    return cls if names.is_rap(cw.plan_type) else f"messages.{cls}"


def component_test(
    cw: ComponentWiring,
    wiring: Wiring,
    module: str,
    modules: dict[str, str],
    names: MessageNames,
    package: str,
) -> str:
    """The text of ``tests/test_<module>.py``."""
    fn = f"test_{identifier(cw.name)}"
    extra: list[str] = []
    body: list[str] = []
    start = [f"{module}.node"]
    sends = [o for o in cw.outputs if o.role == "output"]
    approved = [p for p in cw.inputs if p.role == "approved"]
    judged = [p for p in cw.inputs if p.role == "judged"]
    proposes = [o for o in cw.outputs if o.role == "proposal"]
    if approved:
        leg = [modules[n] for n in cw.legitimators if n in modules]
        extra += [f"from {package}.nodes import {m}" for m in leg]
        start += [f"{m}.node" for m in leg]
        start.append("proposer()")
        body += [
            "        # a plan goes through the legitimate stage and the gate to this stage",
            '        await h.emit("test-go")',
            '        verdict = (await h.expect_event("verdict")).decode(Verdict)',
            "        assert verdict.approved, verdict.reason",
            *(_expect(o.channel, "        ") for o in sends),
            f"        assert {module}.gate.stats.approved == 1",
        ]
    if judged:
        start.append("proposer()")
        body += [
            '        await h.emit("test-go")',
            '        verdict = (await h.expect_event("verdict")).decode(Verdict)',
            "        assert verdict.approved, verdict.reason",
        ]
    seen: set[Channel] = set()
    for p in cw.handlers:
        if p.channel in seen:
            continue
        seen.add(p.channel)
        body += [f"        # input {p.port}", "        mark = len(h.records)"]
        body.append(_send(p, names, "        "))
        body += [_expect(o.channel, "        ", "mark") for o in sends]
        if proposes:
            body.append('        await h.expect_event("new-plan", after=mark)')
    if not body:
        body = ["        pass  # nothing triggers it: it only has to come up"]
    plan_cls = _plan_cls(cw, names)
    out = [
        f'"""Component {cw.name!r} alone on a Harness (generated by ``rap generate``; your',
        'expectations go in the region: regenerating keeps it)."""',
        "",
        *_HEAD,
        *_imports(package, [module], extra),
    ]
    if approved or judged:
        out += _proposer(plan_cls)
    out += [
        "",
        "",
        f"async def {fn}_handles_its_inputs() -> None:",
        "    async with Harness(system=SYSTEM) as h:",
        "        await h.hold(open_service(KnowledgeConfig(system=SYSTEM), fabric=h.fabric))",
        f"        await h.start({', '.join(start)})",
        *_checks(fn, body, f"{module}.FORWARD"),
        "        assert not h.rejections()",
        "",
    ]
    return "\n".join(out)


def reachable(wiring: Wiring) -> list[Channel]:
    """The output channels that feeding every source reaches under the default behaviour."""
    fed = {p.channel for p in wiring.sources}
    out: list[Channel] = []
    changed = True
    approved_plans = False
    while changed:
        changed = False
        for cw in wiring.components.values():
            triggered = any(p.channel in fed for p in cw.inputs if p.role in ("input",))
            if any(p.role == "approved" for p in cw.inputs) and approved_plans:
                triggered = True
            if not triggered:
                continue
            for o in cw.outputs:
                if o.role == "proposal":
                    if not approved_plans and any(
                        p.role == "judged" for c in wiring.components.values() for p in c.inputs
                    ):
                        approved_plans = True
                        changed = True
                    continue
                if o.channel not in fed:
                    fed.add(o.channel)
                    out.append(o.channel)
                    changed = True
    return out


def loop_test(wiring: Wiring, modules: dict[str, str], names: MessageNames, package: str) -> str:
    """The text of ``tests/test_loop.py``: every component together, every source fed."""
    mods = [modules[n] for n in wiring.components]
    body = [_send(p, names, "        ") for p in wiring.sources]
    expected = reachable(wiring)
    body += [_expect(ch, "        ") for ch in expected]
    if any(o.role == "proposal" for cw in wiring.components.values() for o in cw.outputs):
        proposing = [
            cw
            for cw in wiring.components.values()
            if any(o.role == "proposal" for o in cw.outputs) and cw.handlers
        ]
        if proposing:
            body.append('        await h.expect_event("new-plan")')
    if not body:
        body = ["        pass  # no inputs come from outside: the components only come up"]
    out = [
        '"""The whole system on one Harness: every component, RAP\'s knowledge service, an',
        "example message on every input that comes from outside (the managed system), and",
        "every output that reaches (generated by ``rap generate``; your expectations go in",
        'the region)."""',
        "",
        *_HEAD,
        *_imports(package, mods),
        "",
        "",
        "async def test_the_loop_runs_end_to_end() -> None:",
        "    async with Harness(system=SYSTEM) as h:",
        "        await h.hold(open_service(KnowledgeConfig(system=SYSTEM), fabric=h.fabric))",
        f"        await h.start({', '.join(f'{m}.node' for m in mods)})",
        *_checks("loop", body, f"all(m.FORWARD for m in ({''.join(f'{m}, ' for m in mods)}))"),
        "        assert not h.rejections()",
        "",
    ]
    return "\n".join(out)
