"""Scenario 3: the link between the robot and the edge cut for a while, on two hosts.

The hosts are two network namespaces this run creates (``ip netns add``) joined by a
veth pair with a private /30 between them; nothing appears on the machine's own network,
and both are deleted at the end whatever happens (with any process left in them).
``rap up MODEL --node edge`` runs in one, ``rap up MODEL --node robot --address
edge=IP`` in the other, and the observer (bench/faults/observer.py) in the robot's, a
client of its router. After the loop closed, the robot's end of the link is set down
for each cut (``ip link set DEV down``), then up again. Measured per cut: the time from
the link's return to the next plan sent to the robot, plans seen while it was down, and
what the JSON-lines logs of the run folders say in that window: nodes that lost their
liveliness and came back (the runners' ``rap_sdk.peers`` lines) and links lost and
restored (each router's log)."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import anyio
from rap_sdk.testing import HostsUnavailable, TwoHosts, ip, two_hosts

from .common import RapUp, ScenarioError, observer, rap_up, say, write_model

__all__ = ["run_partition"]

RESUME_S = 60.0
WARMUP_S = 60.0


@contextlib.contextmanager
def hosts() -> Iterator[TwoHosts]:
    """The run's two namespaces (rap_sdk.testing.two_hosts); what stops them is said."""
    try:
        with two_hosts("rapf", 232) as h:
            yield h
    except HostsUnavailable as exc:
        raise ScenarioError(str(exc)) from None


def _ip(*args: str) -> None:
    try:
        ip(*args)
    except RuntimeError as exc:
        raise ScenarioError(str(exc)) from None


def _in(ns: str) -> list[str]:
    return ["ip", "netns", "exec", ns]


def _window(up: RapUp, node: str, t0_ns: int, t1_ns: int) -> dict[str, Any]:
    """What the JSON-lines logs of ``node``'s run folder say between the two times."""
    lost: list[str] = []
    back: list[str] = []
    for rec in up.jsonl(node, "runner") + up.jsonl(node, "knowledge"):
        ts = int(rec.get("ts", 0))
        if not t0_ns <= ts <= t1_ns:
            continue
        msg = str(rec.get("message", ""))
        if "lost its liveliness" in msg:
            lost.append(msg.rsplit("node ", 1)[-1].split(" ", 1)[0])
        elif "is alive again" in msg:
            back.append(msg.rsplit("node ", 1)[-1].split(" ", 1)[0])
    links = {"lost": 0, "restored": 0}
    for line in up.text(node, "router").splitlines():
        if " rap.router: link to " not in line:
            continue
        stamp = line[:23]
        try:
            t = time.mktime(time.strptime(stamp[:19], "%Y-%m-%d %H:%M:%S")) + int(stamp[20:]) / 1e3
        except ValueError:
            continue
        if t0_ns / 1e9 <= t <= t1_ns / 1e9:
            for what in links:
                if f" {what} (" in line:
                    links[what] += 1
    return {
        "liveliness_lost": sorted(set(lost)),
        "alive_again": sorted(set(back)),
        "router_links": links,
    }


async def run_partition(folder: Path, *, cuts: list[float], settle: float) -> dict[str, Any]:
    say(f"partition: cuts of {', '.join(f'{c:g} s' for c in cuts)} between two namespaces")
    out: list[dict[str, Any]] = []
    with hosts() as h:
        model = write_model(folder)
        addr = ["--address", f"edge={h.edge_ip}"]
        async with (
            rap_up(model, folder / "edge", node="edge", args=addr, prefix=_in(h.edge)) as edge,
            rap_up(model, folder / "robot", node="robot", args=addr, prefix=_in(h.robot)) as robot,
            observer(
                robot.router("robot"), prefix=_in(h.robot), stderr=folder / "observer.err"
            ) as obs,
        ):
            say(f"  edge in {h.edge} ({h.edge_ip}), robot in {h.robot} ({h.robot_ip})")
            if await obs.next("plan", 0.0, timeout=WARMUP_S) is None:
                raise ScenarioError(
                    f"the loop sent no plan across the link within {WARMUP_S:g} s:\n"
                    f"{robot.lines.tail()}\n{edge.lines.tail()}"
                )
            for seconds in cuts:
                await anyio.sleep(settle)  # the loop runs over the link for a while
                t_cut, w_cut = time.monotonic(), time.time_ns()
                _ip("-n", h.robot, "link", "set", "dev", h.robot_dev, "down")
                say(f"  link down for {seconds:g} s")
                try:
                    await anyio.sleep(seconds)  # the partition under test
                finally:
                    _ip("-n", h.robot, "link", "set", "dev", h.robot_dev, "up")
                t_back, w_back = time.monotonic(), time.time_ns()
                plan = await obs.next("plan", t_back, timeout=RESUME_S)
                resume = None if plan is None else round(plan["t"] - t_back, 3)
                await anyio.sleep(settle)  # the logs of the return
                during = obs.plans(t_cut + 0.5, t_back)
                entry: dict[str, Any] = {
                    "cut_s": seconds,
                    "plan_after_link_back_s": resume,
                    "plans_while_cut": len(during),
                    "robot_logs": _window(robot, "robot", w_cut, time.time_ns()),
                    "edge_logs": _window(edge, "edge", w_cut, time.time_ns()),
                    "link_back_at_ns": w_back,
                }
                r, e = entry["robot_logs"], entry["edge_logs"]
                entry["logged"] = bool(
                    r["liveliness_lost"]
                    and r["alive_again"]
                    and e["liveliness_lost"]
                    and e["alive_again"]
                    and r["router_links"]["lost"]
                    and r["router_links"]["restored"]
                )
                entry["ok"] = resume is not None and entry["logged"]
                out.append(entry)
                say(
                    f"  link back; next plan {resume} s later; logged: lost liveliness "
                    f"{r['liveliness_lost']} (robot), {e['liveliness_lost']} (edge); router "
                    f"links {r['router_links']} (robot), {e['router_links']} (edge)"
                )
            execs = obs.executions()
    return {
        "cuts": out,
        "plans": execs,
        "ok": all(c["ok"] for c in out) and execs["executed_twice"] == 0,
    }
