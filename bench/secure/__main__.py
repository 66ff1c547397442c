"""``python -m bench.secure [--quick] [--report-only]``: what mutual TLS and the access
control derived from the model cost a message through a compute node's router.

One router runs as ``rap up`` runs it (``python -m rap_cli.router`` with the config
``router_config`` writes for the lidar-occlusion model), three ways in the same run:
``plain`` (tcp, the model as shipped), ``tls`` (``fabric: {tls: true, acl: false}``)
and ``tls+acl`` (``fabric: {tls: true}``: every message checked against the model's
rules). Two RAP sessions connect to it as the processes ``rap up`` starts, each with its
own certificate under TLS: ``edge.runner`` puts a verdict (the Legitimate stage's
output), ``robot.runner`` answers each with a new-data event (the monitor's output), the
keys the model allows them. Measured, interleaved over rounds so drift hits every mode
alike:

- the round trip (two messages, four router hops) p50 and p99, sequential;
- the router's CPU time per message while ``edge.runner`` floods allowed verdicts, and
  (``tls+acl``) while ``robot.robot`` (the simulator, which may not put verdicts) floods
  refused ones, with how many lines the router logged about them (refusals are logged
  with the identity, repeats counted rather than written one by one).

Budgets (ratios in the same run): ``tls+acl`` round trip p50 <= 1.5x ``plain``; the
router's CPU per refused message <= 2x per allowed message; the refusals of a flood
logged in at most 20 lines. Writes bench/results/secure.json and the ``secure`` section of
docs/benchmarks.md.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import anyio
from rap_cli.certs_cli import write_certs
from rap_cli.deploy import TlsFiles, client_config, render_zenoh, router_config
from rap_cli.testing import model_copy
from rap_schemas import keys, load_plan
from rap_sdk.fabric import ZenohConfig, ZenohFabric, free_port, node_overlay
from rap_sdk.testing import OutputLines, stop_process

from ..fuzz import procinfo
from ..report import ROOT, hardware_line, pct, run_suite, table

MODEL = ROOT / "examples/lidar_occlusion/model.yaml"
S = "demo"
VERDICT = keys.event(S, "verdict")
NEW_DATA = keys.event(S, "new-data")
MODES = ("plain", "tls", "tls+acl", "tls+acl quiet")
"""``tls+acl quiet``: the same router with ``RUST_LOG=warn``, so Zenoh does not trace its
access-control checks and refusals go unlogged (what the refusal log costs)."""
BUDGETS = {"tls_acl_vs_plain_p50": 1.5, "refused_vs_allowed_cpu": 2.0, "refusal_log_lines": 20}
SIZE = 256
"""Bytes of each message (a small envelope, as a verdict is)."""


class Router:
    def __init__(self, mode: str, endpoint: str, certs: Path, proc: Any, log: OutputLines):
        self.mode, self.endpoint, self.certs, self.proc, self.log = (
            mode,
            endpoint,
            certs,
            proc,
            log,
        )

    def session(self, identity: str) -> ZenohFabric:
        secure = self.mode != "plain"
        text = json.dumps(client_config(self.endpoint, secure=secure))
        env = {"RAP_AS": identity, "RAP_CERTS": str(self.certs)} if secure else {}
        # block: every put reaches the router (a flood measures the router, not drops)
        return ZenohFabric(node_overlay(ZenohConfig(congestion_control="block"), text, env=env))

    async def cpu_s(self) -> float:
        snap = await procinfo.snapshot(self.proc.pid)
        return float(snap.get("cpu_s", 0.0))


@asynccontextmanager
async def router(mode: str, work: Path) -> AsyncIterator[Router]:
    folder = work / mode.replace(" ", "-")
    folder.mkdir(parents=True)
    quiet = mode.endswith(" quiet")
    mode = mode.removesuffix(" quiet")
    model = model_copy(MODEL, folder)
    if mode != "plain":
        acl = "true" if mode == "tls+acl" else "false"
        model.write_text(model.read_text() + f"\nfabric:\n  tls: true\n  acl: {acl}\n")
    plan = load_plan(model).plan
    certs = folder / "certs"
    tls = None
    if mode != "plain":
        write_certs(plan, certs)
        tls = TlsFiles.of(certs, "edge")
    endpoint = f"{'tls' if tls else 'tcp'}/127.0.0.1:{free_port()}"
    conf = router_config(plan, "edge", local=[endpoint], listen=[], tls=tls)
    assert ("access_control" in conf) == (mode == "tls+acl"), mode
    path = folder / "router.json5"
    path.write_text(render_zenoh(conf, title=f"bench.secure {mode}"))
    async with (
        await anyio.open_process(
            [sys.executable, "-m", "rap_cli.router", "--config", str(path)],
            stderr=subprocess.STDOUT,
            env={**os.environ, "RUST_LOG": "warn"} if quiet else None,
        ) as proc,
        anyio.create_task_group() as tg,
    ):
        log = OutputLines(proc, timeout=10)
        tg.start_soon(log.pump)
        try:
            await log.line("listening on")
            yield Router(mode, endpoint, certs, proc, log)
        finally:
            await stop_process(proc)
            tg.cancel_scope.cancel()


async def _ready(pub: ZenohFabric, key: str, sub: Any) -> None:
    """Until a put of ``pub`` on ``key`` reaches ``sub`` (routes are declared)."""
    with anyio.fail_after(10):
        while True:
            await pub.publish(key, b"hello")
            with anyio.move_on_after(0.1):
                await sub.get()
                return


async def _drain(sub: Any) -> None:
    while True:
        with anyio.move_on_after(0.2) as scope:
            await sub.get()
        if scope.cancelled_caught:
            return


async def round_trips(r: Router, n: int, warm: int) -> list[int]:
    """``n`` sequential round trips edge.runner -> robot.runner -> edge.runner, ns."""
    async with (
        r.session("edge.runner") as edge,
        r.session("robot.runner") as robot,
        anyio.create_task_group() as tg,
    ):
        verdicts = robot.subscribe(VERDICT)
        back = edge.subscribe(NEW_DATA)

        async def echo() -> None:
            while True:
                s = await verdicts.get()
                await robot.publish(NEW_DATA, s.payload)

        await _ready(edge, VERDICT, verdicts)
        await _ready(robot, NEW_DATA, back)
        await _drain(verdicts)
        await _drain(back)
        tg.start_soon(echo)
        payload = bytes(SIZE)
        out: list[int] = []
        for i in range(n + warm):
            t0 = time.perf_counter_ns()
            await edge.publish(VERDICT, payload)
            with anyio.fail_after(5):
                await back.get()
            if i >= warm:
                out.append(time.perf_counter_ns() - t0)
        tg.cancel_scope.cancel()
    return out


async def flood(r: Router, identity: str, n: int) -> dict[str, Any]:
    """``identity`` puts ``n`` verdicts as fast as it can while robot.runner listens: the
    router's CPU seconds over that, and what reached the listener."""
    async with r.session(identity) as sender, r.session("robot.runner") as robot:
        verdicts = robot.subscribe(VERDICT)
        await anyio.sleep(0.5)  # declarations settle
        lines0 = len(r.log.lines)
        cpu0 = await r.cpu_s()
        payload = bytes(SIZE)
        got = 0

        async def count() -> None:
            nonlocal got
            while True:
                await verdicts.get()
                got += 1

        async with anyio.create_task_group() as tg:
            tg.start_soon(count)
            for _ in range(n):
                await sender.publish(VERDICT, payload)
            await anyio.sleep(1.0)  # the router's backlog
            tg.cancel_scope.cancel()
        cpu = await r.cpu_s() - cpu0
        refusals = [x for x in r.log.lines[lines0:] if "refused:" in x]
    return {
        "identity": identity,
        "sent": n,
        "delivered": got,
        "router_cpu_s": round(cpu, 3),
        "router_cpu_us_per_msg": round(cpu * 1e6 / n, 2),
        "refusal_log_lines": len(refusals),
        "refusal_log_sample": refusals[:2],
    }


async def _measure(quick: bool, work: Path) -> dict[str, Any]:
    rounds, n, warm = (2, 200, 20) if quick else (5, 1000, 50)
    flood_n = 5_000 if quick else 50_000
    rtt: dict[str, list[int]] = {m: [] for m in MODES}
    round_p50: dict[str, list[float]] = {m: [] for m in MODES}
    floods: dict[str, Any] = {}
    async with (
        router("plain", work) as plain,
        router("tls", work) as tls,
        router("tls+acl", work) as acl,
        router("tls+acl quiet", work) as quiet,
    ):
        routers = {"plain": plain, "tls": tls, "tls+acl": acl, "tls+acl quiet": quiet}
        for rnd in range(rounds):
            for mode, r in routers.items():
                print(f"  round trips {mode} ({rnd + 1}/{rounds})", file=sys.stderr, flush=True)
                ns = await round_trips(r, n // rounds, warm)
                rtt[mode] += ns
                round_p50[mode].append(pct(ns, 0.5))
        for mode, r in routers.items():
            print(f"  flood of allowed verdicts, {mode}", file=sys.stderr, flush=True)
            floods[f"{mode} allowed"] = await flood(r, "edge.runner", flood_n)
        print("  flood of refused verdicts, tls+acl", file=sys.stderr, flush=True)
        floods["tls+acl refused"] = await flood(acl, "robot.robot", flood_n)
    latency = {
        m: {
            "n": len(v),
            "p50_us": round(pct(v, 0.5) / 1e3, 1),
            "p99_us": round(pct(v, 0.99) / 1e3, 1),
            "round_p50s_us": [round(x / 1e3, 1) for x in round_p50[m]],
        }
        for m, v in rtt.items()
    }
    return {"size": SIZE, "round_trip": latency, "flood": floods}


def measure(quick: bool) -> dict[str, Any]:
    env_conf = os.environ.pop("RAP_ZENOH_CONFIG", None)  # it would be laid over ours
    try:
        with tempfile.TemporaryDirectory(prefix="rap-bench-secure-") as tmp:
            return anyio.run(_measure, quick, Path(tmp))
    finally:
        if env_conf is not None:
            os.environ["RAP_ZENOH_CONFIG"] = env_conf


def verdicts(m: dict[str, Any]) -> dict[str, Any]:
    lat, fl = m["round_trip"], m["flood"]
    ratio = lat["tls+acl"]["p50_us"] / lat["plain"]["p50_us"]
    allowed = fl["tls+acl allowed"]["router_cpu_us_per_msg"]
    refused = fl["tls+acl refused"]["router_cpu_us_per_msg"]
    cpu_ratio = refused / allowed if allowed else float("inf")
    lines = fl["tls+acl refused"]["refusal_log_lines"]
    return {
        "tls_acl_vs_plain_p50": {
            "value": round(ratio, 2),
            "budget": BUDGETS["tls_acl_vs_plain_p50"],
            "ok": ratio <= BUDGETS["tls_acl_vs_plain_p50"],
        },
        "refused_vs_allowed_cpu": {
            "value": round(cpu_ratio, 2),
            "budget": BUDGETS["refused_vs_allowed_cpu"],
            "ok": cpu_ratio <= BUDGETS["refused_vs_allowed_cpu"],
        },
        "refusal_log_lines": {
            "value": lines,
            "budget": BUDGETS["refusal_log_lines"],
            "ok": 0 < lines <= BUDGETS["refusal_log_lines"]
            and fl["tls+acl refused"]["delivered"] == 0,
        },
    }


def render(m: dict[str, Any], v: dict[str, Any], hw: dict[str, Any]) -> str:
    lat, fl = m["round_trip"], m["flood"]
    base = lat["plain"]["p50_us"]
    rows = [
        [
            mode,
            lat[mode]["n"],
            lat[mode]["p50_us"],
            lat[mode]["p99_us"],
            f"{lat[mode]['p50_us'] / base:.2f}",
        ]
        for mode in MODES
    ]
    frows = [
        [
            name,
            f["identity"],
            f"{f['sent']:,}",
            f"{f['delivered']:,}",
            f["router_cpu_us_per_msg"],
            f["refusal_log_lines"],
        ]
        for name, f in fl.items()
    ]
    brows = [[k, b["value"], b["budget"], "ok" if b["ok"] else "MISSED"] for k, b in v.items()]
    return "\n\n".join(
        [
            "## Security: TLS and access control through a router (`python -m bench.secure`)",
            f"On {hardware_line(hw)}. One router as `rap up` runs it, three ways in the same "
            f"run; two RAP sessions as `edge.runner` and `robot.runner`; {m['size']} B "
            "messages; a round trip is two messages through the router (four hops).",
            table(["mode", "round trips", "p50 us", "p99 us", "p50 vs plain"], rows),
            "Floods (as fast as the sender can put, congestion control block): the router's "
            "CPU per message, what the subscriber's inbox took (its default policy drops "
            "what it cannot keep up with), and the lines the router logged about refusals.",
            table(
                ["flood", "sender", "sent", "delivered", "router CPU us/msg", "refusal lines"],
                frows,
            ),
            table(["budget", "measured", "budget", "result"], brows),
        ]
    )


if __name__ == "__main__":
    sys.exit(run_suite("secure", measure, verdicts, render))
