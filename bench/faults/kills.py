"""Scenario 1: kill -9 of every service and stage process of the lidar loop under
``rap up --all`` supervision, mid-cycle, with the knowledge service on SQLite and on a
Redis of our own (append-only, an fsync per write).

For each backend: ``rap up`` of a model copy whose simulator's occlusion changes every
second (a plan every ~0.5 s in steady state), an observer on the robot's router, and a
probe writing numbered durable knowledge writes all along. Then, one after the other:
knowledge, the adaptation manager, the edge runner (analysis, planner, legitimate), the
robot runner (monitor, executor) and the simulator are killed (SIGKILL) right after an
anomaly was seen (a cycle is in flight). Measured for each: the time until ``rap up``
started it again, from that restart to the next plan sent to the robot (target: 2 s),
and the plans sent meanwhile. At the end: acknowledged writes missing (target: 0) and
plans sent twice, by plan id (target: 0)."""

from __future__ import annotations

import itertools
import os
import signal
import statistics
import time
from pathlib import Path
from typing import Any

import anyio
import yaml

from .common import Observer, RapUp, RedisServer, ScenarioError, observer, rap_up, say, write_model
from .probe import Probe

__all__ = ["TARGETS", "run_kills"]

TARGET_S = 2.0
"""Seconds from a restart to the loop's next executed plan."""
TARGETS: dict[str, tuple[str, str, str]] = {
    "knowledge": ("edge", "knowledge", "the knowledge service"),
    "manager": ("edge", "manager", "the adaptation manager"),
    "edge-runner": ("edge", "runner", "the edge runner: analysis, planner, legitimate"),
    "robot-runner": ("robot", "runner", "the robot runner: monitor, executor"),
    "simulator": ("robot", "robot", "the simulator (component robot)"),
}
"""Short name -> (compute node, rap up's process name, what it is)."""
TOKENS: dict[str, tuple[str, ...]] = {
    "knowledge": ("knowledge",),
    "manager": ("manager",),
    "edge-runner": ("analysis", "planner", "legitimate"),
    "robot-runner": ("monitor", "executor"),
    "simulator": ("sim_world",),
}
"""The liveliness tokens each target's process declares once it serves (the simulator's:
its ``--name`` when the model's ``run:`` gives one, see :func:`_sim_token`)."""


def _sim_token(model: Path) -> str:
    """The simulator's node name: ``--name`` in its ``run:`` command, else sim_world's
    default."""
    run = yaml.safe_load(model.read_text())["components"]["robot"]["run"]
    return str(run[run.index("--name") + 1]) if "--name" in run else TOKENS["simulator"][0]


WARMUP_S = 60.0
RECOVER_S = 30.0


async def _kill_one(
    up: RapUp, obs: Observer, probe: Probe, which: str, settle: float
) -> dict[str, Any]:
    node, name, what = TARGETS[which]
    await anyio.sleep(settle)  # the loop runs undisturbed for a while
    anomaly = await obs.next("anomaly", time.monotonic(), timeout=15.0)
    child = up.child(node, name)
    pid = child["pid"]
    if pid is None:
        raise ScenarioError(f"{node}/{name} has no pid in up.json: {child}")
    os.kill(int(pid), signal.SIGKILL)
    t_kill = time.monotonic()
    say(
        f"  killed {what} (pid {pid})"
        + (" right after an anomaly" if anomaly is not None else " (no anomaly seen for 15 s)")
    )
    i = await up.lines.first(up.restarted(node, name, t_kill), timeout=RECOVER_S)
    t_restart = up.lines.items[i][0]
    plan = await obs.next("plan", t_restart, timeout=RECOVER_S)
    tokens = (_sim_token(up.model),) if which == "simulator" else TOKENS[which]
    t_back = await obs.wait_back(tokens, t_restart, timeout=RECOVER_S)
    plan_back = None if t_back is None else await obs.next("plan", t_back, timeout=RECOVER_S)
    out: dict[str, Any] = {
        "target": which,
        "what": what,
        "node": node,
        "process": name,
        "killed_mid_cycle": anomaly is not None,
        "restart_after_s": round(t_restart - t_kill, 3),
        "plans_while_down": len(obs.plans(t_kill, t_restart)),
        "serving_after_restart_s": None if t_back is None else round(t_back - t_restart, 3),
        "plan_after_serving_s": None
        if plan_back is None or t_back is None
        else round(plan_back["t"] - t_back, 3),
    }
    if plan is None:
        out.update(plan_after_restart_s=None, ok=False)
        say(f"  NO plan within {RECOVER_S:g} s of the restart")
    else:
        after = plan["t"] - t_restart
        out.update(plan_after_restart_s=round(after, 3), ok=after <= TARGET_S)
        out["plan_after_kill_s"] = round(plan["t"] - t_kill, 3)
        say(
            f"  restarted {out['restart_after_s']} s after the kill; next plan "
            f"{after:.3f} s after the restart ({'ok' if out['ok'] else 'MISSED'}); serving "
            f"again {out['serving_after_restart_s']} s after the restart, a plan "
            f"{out['plan_after_serving_s']} s later"
        )
    out["probe_failures_around"] = probe.failed_between(t_kill, time.monotonic())
    return out


def _gaps(plans: list[dict[str, Any]]) -> dict[str, Any]:
    ts = [p["t"] for p in plans]
    gaps = sorted(b - a for a, b in itertools.pairwise(ts))
    if not gaps:
        return {"plans": len(plans)}
    return {
        "plans": len(plans),
        "median_gap_s": round(statistics.median(gaps), 3),
        "max_gap_s": round(gaps[-1], 3),
    }


async def run_backend(
    folder: Path, backend: str, targets: list[str], *, settle: float, baseline: float
) -> dict[str, Any]:
    redis: RedisServer | None = None
    if backend == "redis":
        redis = RedisServer(folder / "redis")
        await redis.start()
        say(f"  redis-server of our own on port {redis.port} (appendonly, fsync always)")
    try:
        model = write_model(
            folder, backend=backend, redis_url=redis.url if redis is not None else None
        )
        async with rap_up(model, folder / "run") as up:
            say(f"  rap up --all is up ({backend} knowledge)")
            async with observer(up.router("robot"), stderr=folder / "observer.err") as obs:
                first = await obs.next("plan", 0.0, timeout=WARMUP_S)
                if first is None:
                    raise ScenarioError(
                        f"the loop sent no plan within {WARMUP_S:g} s of start; see "
                        f"{folder / 'run'}:\n{up.lines.tail()}"
                    )
                t_base = time.monotonic()
                await anyio.sleep(baseline)  # the undisturbed loop: the plan rate
                base = _gaps(obs.plans(t_base, time.monotonic()))
                say(f"  undisturbed: {base}")
                probe = Probe(up.router("edge"), run=f"kills-{backend}")
                kills = []
                try:
                    async with probe:
                        for which in targets:
                            kill = await _kill_one(up, obs, probe, which, settle)
                            kills.append(kill)
                        await anyio.sleep(settle)
                    writes = await probe.verify()
                finally:
                    await probe.close()
                execs = obs.executions()
                restarts = {
                    f"{n}/{c['name']}": c["restarts"]
                    for n in ("edge", "robot")
                    for c in up.state(n)["children"]
                }
        say(
            f"  {backend}: {writes['acknowledged']} writes acknowledged, "
            f"{writes['acknowledged_lost']} lost; {execs['plans_sent']} plans, "
            f"{execs['executed_twice']} sent twice"
        )
        return {
            "backend": backend,
            "undisturbed": base,
            "kills": kills,
            "writes": writes,
            "plans": execs,
            "restarts": restarts,
            "ok": all(k["ok"] for k in kills)
            and writes["acknowledged_lost"] == 0
            and execs["executed_twice"] == 0,
        }
    finally:
        if redis is not None:
            await redis.stop()


async def run_kills(
    folder: Path, *, backends: list[str], targets: list[str], quick: bool
) -> dict[str, Any]:
    unknown = sorted(set(targets) - set(TARGETS))
    if unknown:
        raise ScenarioError(f"unknown kill target(s) {unknown}; known: {', '.join(TARGETS)}")
    out: dict[str, Any] = {"target_s": TARGET_S, "backends": {}}
    for backend in backends:
        say(f"kills, {backend} backend: {', '.join(targets)}")
        out["backends"][backend] = await run_backend(
            folder / backend,
            backend,
            targets,
            settle=1.0 if quick else 3.0,
            baseline=2.0 if quick else 10.0,
        )
    out["ok"] = all(b["ok"] for b in out["backends"].values())
    return out
