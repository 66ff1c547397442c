"""``rap status``, ``rap config``, ``rap pause|resume|restart|swap|snapshot|restore``: the
admin verbs of a running system's components, called over its fabric (rap_sdk.admin)
from any machine that reaches one of its routers.

Each request is signed as the identity ``--as`` (or ``RAP_AS``) names, with its
certificate in ``--certs`` (or ``RAP_CERTS``, or ``<model folder>/certs``): a component
whose process has identities refuses unsigned requests, and changes from anyone but an
operator."""

from __future__ import annotations

import json
import sys
import time
from typing import TYPE_CHECKING, Annotated, Any

import anyio
import msgspec
import typer
import yaml
from rap_schemas.admin import (
    AdminReply,
    ComponentState,
    ComponentStatus,
    ComponentSwap,
    ConfigRequest,
    RestartRequest,
    RestoreRequest,
)

from .cli import FAILED, OK, failed, usage
from .reach import (
    Reach,
    Where,
    open_fabric,
    reach_options,
)

if TYPE_CHECKING:
    from rap_sdk.identity import Signer

__all__ = ["register"]

JsonOpt = Annotated[bool, typer.Option("--json", help="Print JSON instead of a table.")]
TimeoutOpt = Annotated[
    float, typer.Option("--timeout", help="Seconds to wait for the components' answers.")
]
ComponentArg = Annotated[
    str, typer.Argument(help="The component (its name in the model).", show_default=False)
]


async def _call(
    reach: Reach,
    component: str,
    verb: str,
    request: msgspec.Struct | None,
    timeout: float,
    signer: Signer | None,
) -> list[AdminReply]:
    from rap_sdk.admin import AdminError, call

    async with open_fabric(reach) as fabric:
        try:
            return await call(
                fabric, reach.system, component, verb, request, timeout=timeout, signer=signer
            )
        except AdminError as exc:
            failed(f"{verb} {component}: {exc}")


def _one(
    where: Where, component: str, verb: str, request: msgspec.Struct | None, timeout: float
) -> tuple[Reach, AdminReply]:
    """Call ``verb`` on one component (signed as ``--as``, when given); fail clearly when
    nobody or several answer."""
    if component in ("*", "**") or "/" in component:
        usage(f"{component!r}: name one component (rap status lists them)")
    reach = where.resolve()
    signer = where.signer()
    replies = anyio.run(_call, reach, component, verb, request, timeout, signer)
    if not replies:
        hint = "is it running? `rap status` lists what answers"
        plan = reach.plan
        if plan is not None:
            spec = plan.components.get(component)
            if spec is None:
                hint = (
                    f"it is not a component of the model; its components: "
                    f"{', '.join(plan.components)}"
                )
            elif spec.module is None:
                hint = (
                    "it runs outside RAP's runners (external or a run: command): if it "
                    "uses the SDK it answers under its own Node's name, which `rap status` "
                    "lists"
                )
        failed(
            f"no component {component!r} answers in system {reach.system!r} (through "
            f"{reach.where}) - {hint}"
        )
    if len(replies) > 1:
        failed(f"{len(replies)} components named {component!r} answered; names must be unique")
    return reach, replies[0]


def _report(reply: AdminReply, as_json: bool) -> None:
    if as_json:
        typer.echo(msgspec.json.encode(reply).decode())
    if not reply.ok:
        where = f" at {reply.path}" if reply.path else ""
        failed(f"{reply.verb} {reply.component}: refused{where}: {reply.message}")
    if not as_json:
        line = f"{reply.component}: {reply.message or reply.verb + ' done'}"
        if reply.status is not None:
            line += f" (now {reply.status.state.value})"
        typer.echo(line)


# -- status ---------------------------------------------------------------------------------


def _age(ns: int, now: int) -> str:
    if ns <= 0:
        return "-"
    s = max(0.0, (now - ns) / 1e9)
    return f"{s:.1f}s ago" if s < 120 else f"{s / 60:.0f}m ago"


def _expected(reach: Reach) -> dict[str, tuple[str, str]]:
    """Components the model runs under a runtime: name -> (compute node, stage)."""
    plan = reach.plan
    if plan is None:
        return {}
    out = {}
    for name, spec in plan.components.items():
        if spec.module is not None and not spec.external and spec.node is not None:
            out[name] = (spec.node, spec.stage.value if spec.stage else "")
    return out


def _rows(reach: Reach, replies: list[AdminReply]) -> list[ComponentStatus]:
    found = [r.status for r in replies if r.status is not None]
    names = {s.name for s in found}
    for name, (node, stage) in _expected(reach).items():
        if name not in names:
            found.append(
                ComponentStatus(
                    name=name, state=ComponentState.GONE, compute_node=node, stage=stage
                )
            )
    return sorted(found, key=lambda s: (s.compute_node, s.name))


def _full(s: ComponentStatus) -> dict[str, Any]:
    """Every field, defaults included (the wire form leaves them out)."""
    return {f: msgspec.to_builtins(getattr(s, f)) for f in s.__struct_fields__}


def _table(rows: list[ComponentStatus]) -> str:
    now = time.time_ns()
    head = (
        "COMPONENT",
        "NODE",
        "STAGE",
        "STATE",
        "LAST CYCLE",
        "P50 ms",
        "P99 ms",
        "INBOX",
        "HANDLED",
        "ERRORS",
    )
    lines = [head]
    for s in rows:
        errors = s.failed + s.rejected + s.dropped
        # the end of the id: a cycle id is a UUIDv7, whose first digits are its time
        cycle = f"..{s.last_cycle[-8:]} {_age(s.last_call, now)}" if s.last_cycle else "-"
        lines.append(
            (
                s.name,
                s.compute_node or "-",
                s.stage or "-",
                s.state.value if s.state is not ComponentState.GONE else "gone",
                cycle,
                f"{s.p50_ms:.2f}",
                f"{s.p99_ms:.2f}",
                str(s.inbox),
                str(s.handled),
                str(errors) if not errors else f"{errors} (f{s.failed}/r{s.rejected}/d{s.dropped})",
            )
        )
    widths = [max(len(row[i]) for row in lines) for i in range(len(head))]
    return "\n".join(
        "  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)).rstrip() for row in lines
    )


def _warn_refused(replies: list[AdminReply]) -> None:
    """Say which components refused to answer and why (they are listed as gone)."""
    for r in replies:
        if not r.ok:
            typer.echo(f"rap: warning: {r.component}: refused: {r.message}", err=True)


async def _watch(
    reach: Reach, timeout: float, as_json: bool, interval: float, signer: Signer | None
) -> None:
    from rap_sdk.admin import AdminError, call

    tty = sys.stdout.isatty()
    async with open_fabric(reach) as fabric:
        while True:
            try:
                replies = await call(
                    fabric, reach.system, "*", "status", timeout=timeout, signer=signer
                )
            except AdminError as exc:
                typer.echo(f"rap: warning: {exc}", err=True)
                replies = []
            _warn_refused(replies)
            rows = _rows(reach, replies)
            if as_json:
                typer.echo(json.dumps([_full(s) for s in rows]))
            else:
                if tty:
                    typer.echo("\x1b[H\x1b[2J", nl=False)
                typer.echo(
                    f"system {reach.system} - {time.strftime('%H:%M:%S')} "
                    f"(every {interval:g} s; Ctrl-C ends)"
                )
                typer.echo(_table(rows))
            await anyio.sleep(interval)


@reach_options
def status(
    as_json: JsonOpt = False,
    watch: Annotated[bool, typer.Option("--watch", "-w", help="Refresh until Ctrl-C.")] = False,
    interval: Annotated[float, typer.Option("--interval", help="Seconds between refreshes.")] = 1.0,
    timeout: TimeoutOpt = 2.0,
    *,
    where: Where,
) -> None:
    """Every component of the running system: compute node, stage, state (idle, active,
    paused, failed, gone), last cycle, handler latency p50/p99, inbox, errors. With a
    model, components it runs that do not answer are listed as gone. Exit 1 when one is
    gone or failed.

    Example: `rap status --watch` (in the model's folder);
    `rap status -c tcp/192.0.2.5:7447 -s demo --json`
    """
    reach = where.resolve()
    signer = where.signer()
    if watch:
        try:
            anyio.run(_watch, reach, timeout, as_json, interval, signer)
        except KeyboardInterrupt:
            raise typer.Exit(OK) from None
        return
    replies = anyio.run(_call, reach, "*", "status", None, timeout, signer)
    _warn_refused(replies)
    rows = _rows(reach, replies)
    if as_json:
        typer.echo(json.dumps([_full(s) for s in rows], indent=2))
    elif not rows:
        failed(f"no component answers in system {reach.system!r} (through {reach.where})")
    else:
        typer.echo(_table(rows))
    bad = [s.name for s in rows if s.state in (ComponentState.GONE, ComponentState.FAILED)]
    if bad:
        if not as_json:
            typer.echo(f"gone or failing: {', '.join(bad)}", err=True)
        raise typer.Exit(FAILED)


# -- config -------------------------------------------------------------------------------------

config_app = typer.Typer(
    help="A running component's config: get it, or set fields (validated; a bad value is "
    "refused and the old config kept).",
    no_args_is_help=True,
)


def _values(pairs: list[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for pair in pairs:
        key, sep, text = pair.partition("=")
        if not sep or not key:
            usage(f"{pair!r}: give KEY=VALUE (e.g. threshold=0.4)")
        try:
            out[key] = yaml.safe_load(text) if text else ""
        except yaml.YAMLError as exc:
            usage(f"{pair!r}: the value is not a YAML scalar: {exc}")
    return out


@config_app.command("get")
@reach_options
def config_get(
    component: ComponentArg,
    as_json: JsonOpt = False,
    timeout: TimeoutOpt = 5.0,
    *,
    where: Where,
) -> None:
    """Print a component's config.

    Example: `rap config get analysis`
    """
    _, reply = _one(where, component, "config", None, timeout)
    if not reply.ok:
        _report(reply, as_json)
    conf = reply.config
    if as_json:
        typer.echo(json.dumps(conf, indent=2))
    elif conf is None:
        typer.echo(f"{component} declares no config")
    else:
        typer.echo(yaml.safe_dump(conf, sort_keys=False).rstrip())


@config_app.command("set")
@reach_options
def config_set(
    component: ComponentArg,
    values: Annotated[
        list[str],
        typer.Argument(
            help="KEY=VALUE pairs (values read as YAML: 0.4, true, text).",
            show_default=False,
            metavar="KEY=VALUE...",
        ),
    ],
    as_json: JsonOpt = False,
    timeout: TimeoutOpt = 5.0,
    *,
    where: Where,
) -> None:
    """Set config fields of a running component; it takes them before its next handler
    call. A bad value is refused with its `$.path` and the old config kept (exit 1).

    Example: `rap config set analysis threshold=0.4 window=5`
    """
    _, reply = _one(where, component, "config", ConfigRequest(values=_values(values)), timeout)
    _report(reply, as_json)


# -- the other verbs ----------------------------------------------------------------------------


def _simple(verb: str, doc: str, timeout_default: float = 5.0) -> Any:
    @reach_options
    def command(
        component: ComponentArg,
        as_json: JsonOpt = False,
        timeout: TimeoutOpt = timeout_default,
        *,
        where: Where,
    ) -> None:
        _report(_one(where, component, verb, None, timeout)[1], as_json)

    command.__doc__ = doc
    command.__name__ = verb
    return command


@reach_options
def swap(
    component: ComponentArg,
    target: Annotated[
        str,
        typer.Argument(
            help="The new implementation, module:attr: a Node, or a function returning one; "
            "importable where the component runs.",
            show_default=False,
            metavar="MODULE:ATTR",
        ),
    ],
    as_json: JsonOpt = False,
    timeout: TimeoutOpt = 30.0,
    *,
    where: Where,
) -> None:
    """Replace a component's implementation in its running process: its state is taken
    and restored into the new one, and what arrives meanwhile waits in its inboxes (no
    event lost, none handled twice). The new one must handle the same inputs and be of
    the same stage; its config is carried over.

    Example: `rap swap analysis lidar_occlusion.nodes:fresh_analysis`
    """
    if ":" not in target:
        usage(f"{target!r}: give MODULE:ATTR (e.g. my_robot.analysis_v2:analysis)")
    _report(_one(where, component, "swap", ComponentSwap(target=target), timeout)[1], as_json)


@reach_options
def restart(
    component: ComponentArg,
    from_snapshot: Annotated[
        bool,
        typer.Option(
            "--from-snapshot",
            help="Restore its latest snapshot in knowledge (else it keeps the state it has).",
        ),
    ] = False,
    as_json: JsonOpt = False,
    timeout: TimeoutOpt = 30.0,
    *,
    where: Where,
) -> None:
    """Restart a component in its process: its liveliness goes down and up, it is
    re-created from its implementation when that is a function, and it keeps the state
    it has (with --from-snapshot: its latest snapshot in knowledge). Input waits
    meanwhile.

    Example: `rap restart analysis`, `rap restart analysis --from-snapshot`
    """
    request = RestartRequest(from_snapshot=from_snapshot)
    _report(_one(where, component, "restart", request, timeout)[1], as_json)


@reach_options
def restore(
    component: ComponentArg,
    version: Annotated[
        int, typer.Option("--version", help="The snapshot's knowledge version (0: the latest).")
    ] = 0,
    as_json: JsonOpt = False,
    timeout: TimeoutOpt = 10.0,
    *,
    where: Where,
) -> None:
    """Restore a component's state from a snapshot kept in knowledge (`rap snapshot`).

    Example: `rap restore analysis` (the latest), `rap restore analysis --version V` (V as
    `rap snapshot` printed it)
    """
    if version < 0:
        usage(f"--version {version}: give a version >= 0")
    _, reply = _one(where, component, "restore", RestoreRequest(version=version), timeout)
    _report(reply, as_json)


def register(app: typer.Typer) -> None:
    app.command("status")(status)
    app.add_typer(config_app, name="config")
    app.command("pause")(
        _simple(
            "pause",
            "Pause a component: its running handler finishes, then none runs until `rap "
            "resume`; what arrives waits in its inboxes under their own capacity and "
            "overflow policy (data keeps the newest, events queue), drops counted.\n\n"
            "Example: `rap pause planner`",
        )
    )
    app.command("resume")(
        _simple(
            "resume",
            "Resume a paused component: what waited is handled, in order.\n\n"
            "Example: `rap resume planner`",
        )
    )
    app.command("restart")(restart)
    app.command("swap")(swap)
    app.command("snapshot")(
        _simple(
            "snapshot",
            "Take a component's state and keep it in knowledge (key "
            "admin/snapshot/COMPONENT, versioned): `rap restore` and restarts resume from "
            "it.\n\nExample: `rap snapshot analysis`",
            10.0,
        )
    )
    app.command("restore")(restore)
