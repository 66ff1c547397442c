"""``rap trace CYCLE``: the causal chain of one loop cycle, from the sample that started
it (the scan) to the last call (the plan at the robot), with each stage's timings, as
the system's adaptation manager recorded it (it answers on
``rap/<system>/admin/manager/trace``; ``rap up`` runs one beside knowledge)."""

from __future__ import annotations

import json
import time
from typing import TYPE_CHECKING, Annotated

import anyio
import msgspec
import typer

from .cli import failed, usage
from .reach import (
    Reach,
    Where,
    open_fabric,
    reach_options,
)

if TYPE_CHECKING:
    from adaptation_manager.views import CycleTrace, TraceReply

__all__ = ["register", "render"]

_HEX = frozenset("0123456789abcdef")


async def _ask(reach: Reach, payload: bytes, timeout: float) -> bytes:
    from adaptation_manager.views import MANAGER, TRACE_VERB
    from rap_schemas import keys
    from rap_sdk import FabricError

    key = keys.admin(reach.system, MANAGER, TRACE_VERB)
    nobody = (
        f"no adaptation manager of system {reach.system!r} answers (through {reach.where}) - "
        "rap up runs one beside knowledge; or start it: python -m adaptation_manager "
        f"--system {reach.system}"
    )
    async with open_fabric(reach) as fabric:
        try:
            await fabric.wait_matched(key, queryable=True, timeout=timeout)
        except FabricError:
            failed(nobody)
        try:
            replies = await fabric.query(key, payload, timeout=timeout)
        except FabricError as exc:
            failed(f"the adaptation manager did not answer within {timeout:g} s: {exc}")
    if not replies:
        failed(nobody)
    reply = replies[0]
    if not reply.ok:
        failed(f"the adaptation manager refused: {reply.payload.decode('utf-8', 'replace')}")
    return reply.payload


def _short(key: str, system: str) -> str:
    """``rap/<system>/data/tb1/scan`` as ``data/tb1/scan``."""
    prefix = f"rap/{system}/"
    return key[len(prefix) :] if key.startswith(prefix) else key


def _clock(ns: int) -> str:
    if ns <= 0:
        return "-"
    return time.strftime("%H:%M:%S", time.gmtime(ns / 1e9)) + f".{ns % 1_000_000_000:09d}"[:7]


def render(trace: CycleTrace) -> str:
    """The chain as text: one line per handler call, indented under the call that sent
    its sample, with when it started (from the cycle's start), how long its sample
    waited (transport and queue; ``~``: to the ms, from the uid of a sample the manager
    does not follow, such as the scan) and how long it ran; what it sent that nobody's
    call took (data to the robot) under it."""
    sys_ = trace.system
    lines = [
        f"cycle {trace.cycle} ({trace.state}) of system {sys_}",
        f"started by {_short(trace.root_key, sys_) or 'a sample'} at {_clock(trace.start)} UTC; "
        f"last call ended at +{trace.total_ms:.3f} ms",
        "",
        f"{'at':>11} {'waited':>10} {'ran':>10}  {'stage':<11} call",
    ]
    taken = {s.trigger_key for s in trace.steps}
    last_end = 0.0
    for step in trace.steps:
        pad = "  " * step.depth
        # a sample the manager does not follow (the scan): its time from its uid, to the ms
        approx = "~" if not step.trigger_source else ""
        wait = f"{approx}{step.wait_ms:.3f} ms" if step.wait_ms is not None else "-"
        ran = f"{step.duration_ms:.3f} ms" if step.ended else "running"
        src = f" from {step.trigger_source}" if step.trigger_source else ""
        fail = "" if step.ok else f"  FAILED: {step.error}"
        lines.append(
            f"+{step.offset_ms:>8.3f} ms {wait:>10} {ran:>10}  {step.stage or '-':<11} "
            f"{pad}{step.node}.{step.handler} on {_short(step.trigger_key, sys_)}{src}{fail}"
        )
        end = step.offset_ms + step.duration_ms
        last_end = max(last_end, end)
        arrow = f"{'':>11} {'':>10} {'':>10}  {'':<11} {pad}  -> "
        lines.extend(
            f"{arrow}{_short(key, sys_)} at +{end:.3f} ms" for key in step.sent if key not in taken
        )
    if not trace.steps:
        lines.append("  (no handler call recorded)")
    for plan in trace.plans:
        who = [f"proposed by {plan.proposer or '?'}"]
        if plan.legitimator:
            who.append(f"judged by {plan.legitimator}")
        if plan.executor:
            who.append(f"executed by {plan.executor}")
        why = f": {plan.reason}" if plan.reason else ""
        lines.append(f"plan {plan.plan[:16]} {plan.status} ({', '.join(who)}){why}")
    lines.extend(f"outstanding: {o}" for o in trace.outstanding)
    return "\n".join(lines)


@reach_options
def trace(
    cycle: Annotated[
        str | None,
        typer.Argument(
            help="The cycle's hex uid: a unique prefix is enough, or '..' and a unique "
            "suffix (as rap status shows each component's last cycle).",
            show_default=False,
        ),
    ] = None,
    last: Annotated[
        bool, typer.Option("--last", help="The latest complete cycle instead of CYCLE.")
    ] = False,
    executed: Annotated[
        bool,
        typer.Option(
            "--executed", help="With --last: the latest one in which a plan reached execute."
        ),
    ] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON (rap trace's reply).")] = (
        False
    ),
    timeout: Annotated[
        float, typer.Option("--timeout", help="Seconds to wait for the manager's answer.")
    ] = 5.0,
    *,
    where: Where,
) -> None:
    """The causal chain of one loop cycle: each handler call from the sample that
    started it (the scan) to the last one (the plan sent to the robot), under the call
    that sent its sample, with when it started, how long its sample waited and how long
    it ran. The system's adaptation manager answers from the cycles it holds (rap up
    runs it beside knowledge). Exit 1 when it does not hold the cycle.

    Example: `rap trace --last --executed -m examples/lidar_occlusion/model.yaml`, or
    `rap trace 019a3c5e -s demo -c tcp/127.0.0.1:7447 --json`."""
    if cycle is None and not last:
        usage(
            "give a CYCLE (its hex uid, a unique prefix of it, or ..END as rap status "
            "shows it) or --last"
        )
    if cycle is not None and last:
        usage("give a CYCLE or --last, not both")
    if executed and not last:
        usage("--executed goes with --last")
    if timeout <= 0:
        usage(f"--timeout {timeout:g}: give a number of seconds > 0")
    if cycle is not None:
        cycle = cycle.strip().lower()
        digits = cycle.removeprefix("..")
        if not digits or len(digits) > 32 or not set(digits) <= _HEX:
            usage(
                f"CYCLE {cycle!r} is not a cycle's hex uid (up to 32 hex digits, the start of "
                "one, or '..' and its end as rap status shows it) - copy it from rap status, "
                "rap logs or the dashboard"
            )
    reach = where.resolve()
    payload = msgspec.json.encode(
        {"last": True, "executed": executed} if last else {"cycle": cycle}
    )
    raw = anyio.run(_ask, reach, payload, timeout)
    from adaptation_manager.views import TraceReply

    try:
        reply: TraceReply = msgspec.json.decode(raw, type=TraceReply)
    except (msgspec.ValidationError, msgspec.DecodeError) as exc:
        failed(f"the adaptation manager's answer cannot be read: {exc} - is it of this version?")
    if not reply.ok or reply.trace is None:
        more = f"; it matches: {', '.join(reply.matches)}" if reply.matches else ""
        failed(f"{reply.message or 'no trace'}{more}")
    if as_json:
        typer.echo(json.dumps(msgspec.to_builtins(reply.trace), indent=2))
    else:
        typer.echo(render(reply.trace))


def register(app: typer.Typer) -> None:
    """Add ``rap trace`` to ``app``."""
    app.command("trace")(trace)
