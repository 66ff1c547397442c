"""Fleet: many robots, each with its own five-stage MAPLE-K loop, on one machine.

    python -m bench.fleet [--robots 50] [--rate 5] [--seconds 30] [--warmup 5]
                          [--runners 2] [--source sim|driver]
    make bench-fleet

What it measures: ``--robots`` simulated robots (sim_world in real time, one world with
every robot in it, a 360-beam lidar each at ``--rate`` Hz), each with its own five
stages (the race's chain of bench/loop/chain.py, built per robot by bench/fleet/nodes.py:
monitor, analyse, plan, legitimate with the approval gate, execute; per-robot topics,
events and knowledge keys), one knowledge service process and ``--runners`` runner
processes sharing the robots, all on loopback Zenoh. After a warm-up (at least
``--warmup`` s, then until every scan of a whole second had its plan back within 1 s:
the loops' start-up is not measured; the time it took is reported) it measures for
``--seconds`` s: the loop latency of every cycle (scan published by sim_world ->
that robot's spin plan received by sim_world, matched by cycle uid), lost cycles (no
plan within 1 s), and each process's CPU (% of one core) and resident memory. Budget:
no lost cycle and loop p99 < 50 ms (exit 1 on a miss, saying what missed); the loops
must also settle and the source keep its pace (scans at >= 98 % of the rate), or the
figures would not describe the load asked for.

``--source driver`` replaces sim_world with a plain scan driver (one prepared scan per
robot, the same bursts): the loops' cost without the simulator's.

A run with the defaults (50 robots, 5 Hz, 2 runners, 5 s warm-up, sim_world; --seconds
of at least 30) writes bench/results/fleet.json and the "fleet" section of
docs/benchmarks.md; any other run writes bench/results/fleet.quick.json only. Logs
and the generated deployment plan go to out/bench-fleet/.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from typing import Any

import anyio
from knowledge.config import HistoryRule

from bench.report import hardware, hardware_line, pct, table, write_json, write_section

from .run import (
    LOST_AFTER,
    SETTLE_MAX,
    SOURCES,
    Cycle,
    Interrupted,
    Options,
    cycles_in,
    measure,
    pacing,
)

HISTORY = HistoryRule().max_count
"""Versions the knowledge service keeps per key by default (the fleet runs it so)."""
P99_BUDGET_MS = 50.0
PACE = 0.98
"""The least fraction of the asked scan rate the source must keep."""


def _say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _ms(ns: float) -> float:
    return round(ns / 1e6, 2)


def _per(cpu_s: float, n: float) -> float | None:
    """Milliseconds of CPU per one of ``n``."""
    return round(1000 * cpu_s / n, 3) if n else None


def _latency(lat: list[int]) -> dict[str, Any]:
    if not lat:
        return {"p50_ms": None, "p90_ms": None, "p99_ms": None, "max_ms": None, "n": 0}
    return {
        "p50_ms": _ms(pct(lat, 0.5)),
        "p90_ms": _ms(pct(lat, 0.9)),
        "p99_ms": _ms(pct(lat, 0.99)),
        "max_ms": _ms(max(lat)),
        "n": len(lat),
    }


def per_second(cycles: list[Cycle], w0: int, limit: float) -> list[dict[str, Any]]:
    """Each second of the window: cycles, lost, p50, p99 and max latency (ms)."""
    secs: dict[int, list[Cycle]] = {}
    for c in cycles:
        secs.setdefault(int((c.ts - w0) // 1_000_000_000), []).append(c)
    out = []
    for k in sorted(secs):
        lat = [c.latency for c in secs[k] if c.latency is not None and c.latency <= limit]
        out.append(
            {
                "second": k,
                "cycles": len(secs[k]),
                "lost": len(secs[k]) - len(lat),
                **{f: v for f, v in _latency(lat).items() if f in ("p50_ms", "p99_ms", "max_ms")},
            }
        )
    return out


def summarise(opts: Options, raw: dict[str, Any]) -> dict[str, Any]:
    window = raw["window_ns"]
    window_s = (window[1] - window[0]) / 1e9
    cycles = cycles_in(raw["probe"], window)
    limit = LOST_AFTER * 1e9
    ok = [c for c in cycles if c.latency is not None and c.latency <= limit]
    lat = [c.latency for c in ok if c.latency is not None]
    late = sum(1 for c in cycles if c.latency is not None and c.latency > limit)
    # where in its tick's burst a scan was published: quarters of the fleet
    quarters: list[dict[str, Any]] = []
    for q in range(4):
        part = [c.latency for c in ok if c.latency is not None and c.pos * 4 // opts.robots == q]
        if part:
            quarters.append({"quarter": q + 1, **_latency(part)})
    per_robot: dict[str, list[int]] = {}
    for c in ok:
        if c.latency is not None:
            per_robot.setdefault(c.robot, []).append(c.latency)
    worst = max(per_robot.items(), key=lambda kv: pct(kv[1], 0.99), default=None)
    res = raw["resources"]
    for row in res["processes"]:
        row["cpu_ms_per_cycle"] = _per(row["cpu_s"], len(cycles))
    # the loops' own processes: all but the source's (the first row)
    loop_cpu = sum(row["cpu_s"] for row in res["processes"][1:])
    return {
        "config": {
            "robots": opts.robots,
            "rate_hz": opts.rate,
            "seconds": opts.seconds,
            "warmup_min_s": opts.warmup,
            "runners": opts.runners,
            "source": raw["source"],
            "lost_after_s": LOST_AFTER,
            "plan": raw["plan"],
        },
        "warmup_s": raw["warmup_s"],
        "settled": raw["settled"],
        "latency": _latency(lat),
        "cycles": len(cycles),
        "lost": len(cycles) - len(ok),
        "late": late,
        "plans_dropped_by_source_inbox": raw["plans_dropped"],
        "unmatched_plans": raw["probe"].unmatched,
        "duplicate_plans": raw["probe"].duplicates,
        "scan_rate_hz": round(len(cycles) / (opts.robots * window_s), 3) if window_s else 0.0,
        "pacing": pacing(raw["probe"], window),
        "by_burst_quarter": quarters,
        "per_second": per_second(cycles, window[0], limit),
        "worst_robot": (None if worst is None else {"robot": worst[0], **_latency(worst[1])}),
        "resources": res,
        "cpu_ms_per_cycle": _per(res["total"]["cpu_s"], len(cycles)),
        "loop_cpu_ms_per_tick": _per(loop_cpu, len(cycles) / opts.robots),
        "wall_seconds": raw["wall_seconds"],
    }


def budgets(s: dict[str, Any]) -> list[dict[str, Any]]:
    p99 = s["latency"]["p99_ms"]
    rate = s["config"]["rate_hz"]
    return [
        {
            "what": "loops settled before measuring (warm-up s)",
            "value": s["warmup_s"],
            "budget": f"settled within {SETTLE_MAX:g} s after the warm-up",
            "ok": s["settled"],
        },
        {"what": "lost cycles", "value": s["lost"], "budget": "0", "ok": s["lost"] == 0},
        {
            "what": "loop p99 (ms)",
            "value": p99,
            "budget": f"< {P99_BUDGET_MS:g}",
            "ok": p99 is not None and p99 < P99_BUDGET_MS,
        },
        {
            "what": "scans per robot per second",
            "value": s["scan_rate_hz"],
            "budget": f">= {PACE * rate:g}",
            "ok": s["scan_rate_hz"] >= PACE * rate,
        },
    ]


def render(s: dict[str, Any], checks: list[dict[str, Any]], hw: dict[str, Any]) -> str:
    c, lat, res = s["config"], s["latency"], s["resources"]
    drops = s["plans_dropped_by_source_inbox"]
    source = (
        "sim_world in real time (one world, every robot in it; this process also hosts the probe)"
        if c["source"] == "sim_world"
        else "a plain scan driver (one prepared scan per robot, the same bursts)"
    )
    proc_rows = [
        [
            p["process"],
            p["cpu_s"],
            p["cpu_pct"],
            p["cpu_ms_per_cycle"],
            p["rss_start_mib"],
            p["rss_mib"],
            p["rss_peak_mib"],
        ]
        for p in res["processes"]
    ]
    t = res["total"]
    proc_rows.append(
        ["total", t["cpu_s"], t["cpu_pct"], s["cpu_ms_per_cycle"], "", t["rss_mib"], ""]
    )
    lines = [
        "## Fleet: many robots' loops on one machine (`make bench-fleet`)",
        "",
        f"Hardware: {hardware_line(hw)}",
        "",
        f"{c['robots']} robots, each with its own five-stage loop (bench/loop's chain, built "
        "per robot by `bench/fleet/nodes.py`: monitor, analyse, plan, legitimate with the "
        "approval gate, execute; every scan runs the whole loop) at "
        f"{c['rate_hz']:g} Hz. Scan source: {source}. One knowledge service process "
        f"(memory backend) and {c['runners']} `maplek_runner` processes, robot i's five "
        f"nodes on runner i mod {c['runners']}, on loopback Zenoh "
        f"(`python -m bench.fleet`, plan `{c['plan']}`). Warm-up: {s['warmup_s']:g} s from the "
        f"first scan (at least {c['warmup_min_s']:g} s, then until every scan of a whole "
        "second had its plan back within the loss limit: the loops' start, with each "
        "node's first reads of its keys, is not in the figures), then "
        f"{res['window_s']:g} s measured.",
        "",
        "Loop latency: scan published (its envelope stamp) -> that robot's spin plan "
        "received by the source, matched by cycle uid; a cycle is lost when its plan has "
        f"not arrived within {c['lost_after_s']:g} s.",
        "",
        table(
            ["cycles", "lost", "p50 ms", "p90 ms", "p99 ms", "max ms", "scans/robot/s"],
            [
                [
                    s["cycles"],
                    s["lost"],
                    lat["p50_ms"],
                    lat["p90_ms"],
                    lat["p99_ms"],
                    lat["max_ms"],
                    s["scan_rate_hz"],
                ]
            ],
        ),
        "",
        f"Plans the source's inboxes dropped (each robot's keeps its newest 4): "
        f"{drops['warmup']} during the warm-up, {drops['window']} in the window; plans "
        f"matching no scan of the run: {s['unmatched_plans']}; duplicates: "
        f"{s['duplicate_plans']}; plans later than the loss limit: {s['late']}.",
        "",
        "Each process over the measured window (CPU: seconds, % of one core, and per "
        "cycle measured; RSS at the window's start and end, and its peak over the "
        "process's life):",
        "",
        table(
            [
                "process",
                "CPU s",
                "CPU % of a core",
                "CPU ms/cycle",
                "RSS MiB at start",
                "RSS MiB at end",
                "peak RSS MiB",
            ],
            proc_rows,
        ),
        "",
        *_history_note(c["robots"], c["rate_hz"]),
        f"All together: {t['cpu_pct_of_machine']}% of the machine's {res['machine']['cores']} "
        f"cores. The machine was {res['machine']['busy_pct_of_machine']}% busy in the "
        f"window; other processes (not this benchmark's) used "
        f"{res['machine']['others_pct']}% of one core.",
        "",
        "Budget:",
        "",
        table(
            ["what", "measured", "budget", ""],
            [[b["what"], b["value"], b["budget"], "ok" if b["ok"] else "MISSED"] for b in checks],
        ),
        "",
        *_where(s),
    ]
    return "\n".join(lines)


def _history_note(robots: int, rate: float) -> list[str]:
    if HISTORY is None:
        return []
    return [
        f"The knowledge service keeps the last {HISTORY} versions of each key (its default "
        f"history; here {3 * robots} keys, a scan among each robot's three), so its RSS "
        f"grows while the histories fill ({HISTORY} versions take {HISTORY / rate:g} s at "
        f"{rate:g} Hz): its end-of-window figure is not its steady state.",
        "",
    ]


def _where(s: dict[str, Any]) -> list[str]:
    pace, q = s["pacing"], s["by_burst_quarter"]
    tick, robots = s["loop_cpu_ms_per_tick"], s["config"]["robots"]
    cores = s["resources"]["machine"]["cores"]
    floor = round(tick / cores, 1) if tick is not None else None
    first, last = (q[0]["p50_ms"], q[-1]["p50_ms"]) if q else (None, None)
    if first and last and last <= 1.25 * first:
        spread = (
            "Every quarter waits about as long: the runners take a tick's events in "
            "arrival order, stage by stage, so the tick's cycles advance together and end "
            "together."
        )
    else:
        spread = "Later quarters wait longer: their cycles queue behind the first ones."
    source = "sim_world" if s["config"]["source"] == "sim_world" else "the driver"
    rate = s["config"]["rate_hz"]
    kept = (
        f"{source} kept real time with {robots} robots:"
        if s["scan_rate_hz"] >= PACE * rate
        else f"{source} did NOT keep real time with {robots} robots:"
    )
    rows = [[x["quarter"], x["p50_ms"], x["p99_ms"], x["max_ms"], x["n"]] for x in q]
    out = [
        "Where the time goes: the source publishes every robot's scan of a tick in one "
        f"burst (p50 {pace.get('burst_p50_ms')} ms from the first scan's stamp to the "
        f"last's, max {pace.get('burst_max_ms')} ms), so a tick's cycles queue behind "
        "each other in the runners, which share the cores with the knowledge service "
        "and the source. By the scan's place in its burst (quarter 1: the first quarter "
        "of the robots published):",
        "",
        table(["burst quarter", "p50 ms", "p99 ms", "max ms", "n"], rows),
        "",
        f"{spread} "
        f"The loops' processes (knowledge and runners) spend {tick} ms of CPU per tick of "
        f"{robots} scans, {floor} ms per core on {cores} cores: the p50 is of that order, "
        "a tick's work queued behind itself (not all of it is on a cycle's path: the "
        "knowledge service stores the writes, the runners collect garbage when idle). The "
        "p99 adds what else wanted the cores at the time: the source's own steps, other "
        "processes.",
        "",
        f"The source's pace: {kept} {s['scan_rate_hz']} scans per robot per second, each "
        f"tick's first scan at most {pace.get('lag_max_ms')} ms (p99 "
        f"{pace.get('lag_p99_ms')} ms) later than the least late tick of the window.",
    ]
    w = s["worst_robot"]
    if w is not None:
        out += [
            "",
            f"Worst robot by p99: {w['robot']} (p50 {w['p50_ms']} ms, p99 {w['p99_ms']} ms, "
            f"max {w['max_ms']} ms).",
        ]
    return out


def _run(opts: Options) -> dict[str, Any] | None:
    """The raw figures of a run; None when SIGINT or SIGTERM stopped it."""
    raw: dict[str, Any] | None = None
    try:
        raw = anyio.run(measure, opts, _say, backend_options={"use_uvloop": True})
    except* Interrupted:
        pass
    return raw


def main() -> int:
    ap = argparse.ArgumentParser(
        prog="python -m bench.fleet",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("--robots", type=int, default=50, help="robots in the fleet (default 50)")
    ap.add_argument("--rate", type=float, default=5.0, help="lidar scans per second per robot")
    ap.add_argument("--seconds", type=float, default=30.0, help="measured seconds (default 30)")
    ap.add_argument(
        "--warmup",
        type=float,
        default=5.0,
        help="least seconds before measuring; then until the loops have settled",
    )
    ap.add_argument("--runners", type=int, default=2, help="runner processes (default 2)")
    ap.add_argument("--source", choices=SOURCES, default="sim", help="scan source")
    a = ap.parse_args()
    if not 1 <= a.robots <= 1000:
        ap.error("--robots: give 1 to 1000")
    if not 0 < a.rate <= 100:
        ap.error("--rate: give Hz > 0 and at most 100")
    if not 1 <= a.runners <= a.robots:
        ap.error("--runners: give 1 to --robots")
    if a.seconds <= 0 or a.warmup < 0:
        ap.error("--seconds must be > 0 and --warmup >= 0")
    opts = Options(
        robots=a.robots,
        rate=a.rate,
        seconds=a.seconds,
        warmup=a.warmup,
        runners=a.runners,
        source=a.source,
    )
    hw = hardware()
    _say(f"bench/fleet on {hardware_line(hw)}")
    raw = _run(opts)
    if raw is None:
        _say("interrupted; the processes are stopped, nothing written")
        return 130
    s = summarise(opts, raw)
    checks = budgets(s)
    # the figure the page states: the defaults, measured at least as long
    official = replace(opts, seconds=Options().seconds) == Options() and opts.seconds >= 30
    path = write_json(
        "fleet" if official else "fleet.quick", {"hardware": hw, **s, "budgets": checks}
    )
    text = render(s, checks, hw)
    if official:
        write_section("fleet", text)
    print(text)
    _say(f"written: {path}" + (" and the fleet section of docs/benchmarks.md" if official else ""))
    missed = [b for b in checks if not b["ok"]]
    for b in missed:
        _say(f"MISSED {b['what']}: {b['value']} (budget {b['budget']})")
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
