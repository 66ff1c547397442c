"""The loop race: scan at the robot -> spin plan at the robot, RAP against RPIO 0.4.3.

    python -m bench.loop [--quick] [--no-peer] [--no-instructions]

In one run:
- instructions per cycle of the in-process chain, untraced and traced, against the five
  handlers called directly and the contract floor, counted under callgrind
  (bench/loop/instructions.py);
- the floor: the five handlers called directly, back to back (hot caches) and paced
  like the loop rows (``floor-paced``: same rates, same idle gaps), and the contract
  floor paced the same way (``contract-paced``: the handlers plus what RAP's contract
  asks of a cycle, no dispatch; bench/loop/contract.py);
- raw Zenoh echo (two hops, no event loop), the same with both ends woken in their
  asyncio loops (``zenoh-echo-loop``), the same round trip through RAP, the chain
  in one process on the in-memory fabric, RAP with all five stages in one runner
  process, RAP with each stage in its own process (both over loopback Zenoh, the
  knowledge service in its own process), and the peer over Redis and over MQTT
  (bench/loop/peer.py, in its own virtual environment), at 5, 20 and 100 Hz; then each
  loop climbs a ladder of rates to the highest it sustains with no lost cycle.
Writes bench/results/loop.json and the "loop" section of docs/benchmarks.md.

Budgets (checked, reported, exit 1 on a miss), each a ratio in the same run: the chain
<= 450 k instructions per cycle untraced and <= 650 k traced, its paced p50 <= 3x the
paced floor; one-process p50 <= 2.4x the raw Zenoh echo and <= 0.45x RPIO over Redis;
five-process p50 <= 0.9x RPIO over Redis; p99 <= 2x p50 for both at 20 and 100 Hz; no
lost cycle at 100 Hz.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import anyio

from bench.report import ROOT, hardware, hardware_line, pct, table, write_json, write_section

from .rap import run_contract_paced, run_floor, run_floor_paced, run_inproc, run_rap
from .transport import zenoh_echo, zenoh_echo_loop, zenoh_relay

RATES = [5.0, 20.0, 100.0]
RAP_LADDER = [200.0, 400.0, 700.0, 1000.0]
PEER_LADDER = (200.0, 300.0, 500.0)


FLOORS = (
    "floor-paced",
    "contract-paced",
    "zenoh-echo",
    "zenoh-echo-loop",
    "zenoh-relay",
    "rap-echo",
    "rap-inproc",
)
"""Rows that take the loop apart: the handlers alone, the handlers with what RAP's
contract asks of a cycle, two cross-process hops on raw Zenoh (answered on Zenoh's
thread, and woken in an event loop at both ends), six such hops, the same round trip
through RAP, and the whole chain in one process without a transport."""


def _say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _stats(lat_ns: list[int]) -> dict[str, Any]:
    if not lat_ns:
        return {"p50_ms": None, "p90_ms": None, "p99_ms": None, "n": 0}
    return {
        "p50_ms": round(pct(lat_ns, 0.5) / 1e6, 3),
        "p90_ms": round(pct(lat_ns, 0.9) / 1e6, 3),
        "p99_ms": round(pct(lat_ns, 0.99) / 1e6, 3),
        "n": len(lat_ns),
    }


def _row(system: str, r: dict[str, Any]) -> dict[str, Any]:
    return {
        "system": system,
        "rate_hz": r["rate_hz"],
        **_stats(r.get("latencies_ns", [])),
        "lost": r.get("lost"),
        "send_rate_hz": r.get("send_rate_hz"),
    }


def _cycles(rate: float, seconds: float, lo: int = 30, hi: int = 2000) -> int:
    return int(min(hi, max(lo, rate * seconds)))


async def _rap(
    variant: str, rates: list[float], seconds: float, logs: Path
) -> list[dict[str, Any]]:
    rows = []
    for rate in rates:  # one deployment per rate: each starts as cold as the peer's does
        res = await run_rap(variant, [rate], _cycles(rate, seconds), 20, logs)
        rows.append(_row(variant, res[0]))
        _say(f"  {variant} {rate:g} Hz: {rows[-1]}")
    return rows


def _ladder(rows: list[dict[str, Any]]) -> float | None:
    best = None
    for r in sorted(rows, key=lambda r: r["rate_hz"]):
        if r["lost"] or (r["send_rate_hz"] or 0) < 0.95 * r["rate_hz"]:
            break
        best = r["rate_hz"]
    return best


def main() -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.loop", description=__doc__)
    ap.add_argument("--quick", action="store_true", help="short rounds (a smoke run)")
    ap.add_argument("--no-peer", action="store_true", help="RAP only (no RPIO venv)")
    ap.add_argument(
        "--no-instructions", action="store_true", help="skip the callgrind counts (~5 min)"
    )
    a = ap.parse_args()
    seconds = 2.0 if a.quick else 8.0
    logs = ROOT / "out" / "bench-loop"
    t0 = time.perf_counter()
    out: dict[str, Any] = {"hardware": hardware(), "seconds_per_rate": seconds}
    rows: list[dict[str, Any]] = []
    if not a.no_instructions:
        from .instructions import measure

        _say("instructions per cycle (callgrind)")
        out["instructions"] = measure(60 if a.quick else 200)
    floor = run_floor(5000)
    out["floor"] = _stats(floor)
    _say(f"floor: {out['floor']}")
    sustained: dict[str, float | None] = {}
    uv = {"use_uvloop": True}
    for rate in RATES:
        r = anyio.run(run_floor_paced, rate, _cycles(rate, seconds), 20, backend_options=uv)
        rows.append(_row("floor-paced", r))
        _say(f"  floor-paced {rate:g} Hz: {rows[-1]}")
        r = anyio.run(run_contract_paced, rate, _cycles(rate, seconds), 20, backend_options=uv)
        rows.append(_row("contract-paced", r))
        _say(f"  contract-paced {rate:g} Hz: {rows[-1]}")
    for rate in RATES:  # the transport floor: two hops, raw Zenoh, no event loop
        r = zenoh_echo(rate, _cycles(rate, seconds))
        rows.append(_row("zenoh-echo", r))
        _say(f"  zenoh-echo {rate:g} Hz: {rows[-1]}")
    for rate in RATES:  # the same, each end woken in its event loop as RAP's processes
        r = zenoh_echo_loop(rate, _cycles(rate, seconds))
        rows.append(_row("zenoh-echo-loop", r))
        _say(f"  zenoh-echo-loop {rate:g} Hz: {rows[-1]}")
    for rate in RATES:  # the five-process layout's transport floor: six hops, loops woken
        r = zenoh_relay(rate, _cycles(rate, seconds))
        rows.append(_row("zenoh-relay", r))
        _say(f"  zenoh-relay {rate:g} Hz: {rows[-1]}")
    # RAP's processes run on uvloop (as rap_sdk.app.run and maplek_runner do); so does
    # the robot here
    rows += anyio.run(_rap, "rap-echo", RATES, seconds, logs, backend_options=uv)
    for rate in RATES:
        r = anyio.run(run_inproc, [rate], _cycles(rate, seconds), 20, backend_options=uv)[0]
        rows.append(_row("rap-inproc", r))
        _say(f"  rap-inproc {rate:g} Hz: {rows[-1]}")
    for variant in ("rap-1proc", "rap-5proc"):
        fixed = anyio.run(_rap, variant, RATES, seconds, logs, backend_options=uv)
        ladder = anyio.run(_rap, variant, RAP_LADDER, min(seconds, 3.0), logs, backend_options=uv)
        rows += fixed
        out.setdefault("ladder", {})[variant] = ladder
        sustained[variant] = _ladder(fixed + ladder)
    if not a.no_peer:
        from .peer import run_peer, sustained_rate

        for variant in ("redis", "mqtt"):
            name = f"rpio-{variant}"
            for rate in RATES:  # as many cycles per rate as RAP's rounds
                r = run_peer(variant, [rate], _cycles(rate, seconds), 20)["rates"][0]
                rows.append(_row(name, r))
                _say(f"  {name} {r['rate_hz']:g} Hz: {rows[-1]}")
            lad = sustained_rate(variant, ladder=(*RATES, *PEER_LADDER), seconds=min(seconds, 3.0))
            sustained[name] = lad["sustained_hz"]
            out.setdefault("ladder", {})[name] = lad["steps"]
    out["rows"] = rows
    out["sustained_hz"] = sustained
    checks = _budgets(rows, out.get("instructions"))
    out["budgets"] = checks
    out["wall_seconds"] = round(time.perf_counter() - t0, 1)
    write_json("loop", out)
    write_section("loop", _doc(out))
    for c in checks:
        _say(f"{'ok  ' if c['ok'] else 'MISS'} {c['what']}: {c['value']} (budget {c['budget']})")
    return 0 if all(c["ok"] for c in checks) else 1


def _find(rows: list[dict[str, Any]], system: str, rate: float) -> dict[str, Any] | None:
    return next((r for r in rows if r["system"] == system and r["rate_hz"] == rate), None)


def _check(what: str, value: float, budget: float, floor: str = "") -> dict[str, Any]:
    return {"what": what, "value": value, "budget": budget, "ok": value <= budget, "floor": floor}


def _ratio(rows: list[dict[str, Any]], a: str, b: str, rate: float) -> float | None:
    ra, rb = _find(rows, a, rate), _find(rows, b, rate)
    if ra is None or rb is None or not ra["p50_ms"] or not rb["p50_ms"]:
        return None
    return round(ra["p50_ms"] / rb["p50_ms"], 3)


def _one_proc_floor(rows: list[dict[str, Any]], rate: float) -> float | None:
    """The least a one-process loop can take at ``rate`` (p50, ms): a round trip between
    two processes woken in their event loops, plus the chain keeping the contract with
    no dispatch (it leaves out the knowledge writes that go to the service's process)."""
    loop, contract = _find(rows, "zenoh-echo-loop", rate), _find(rows, "contract-paced", rate)
    if loop is None or contract is None or not loop["p50_ms"] or not contract["p50_ms"]:
        return None
    return round(loop["p50_ms"] + contract["p50_ms"], 3)


def _budgets(rows: list[dict[str, Any]], instr: dict[str, Any] | None) -> list[dict[str, Any]]:
    checks = []
    if instr:
        direct = instr.get("direct")
        for kind, budget in (("chain", 450_000), ("chain-traced", 650_000)):
            if kind in instr:
                checks.append(
                    _check(
                        f"in-process chain instructions per cycle ({kind})",
                        instr[kind],
                        budget,
                        f"the handlers alone: {direct:,}" if direct else "",
                    )
                )
    for rate in RATES:
        for what, a, b, budget in (
            ("rap-inproc p50 / floor-paced p50", "rap-inproc", "floor-paced", 3.0),
            ("rap-1proc p50 / zenoh-echo p50", "rap-1proc", "zenoh-echo", 2.4),
            ("rap-1proc p50 / rpio-redis p50", "rap-1proc", "rpio-redis", 0.45),
            ("rap-5proc p50 / rpio-redis p50", "rap-5proc", "rpio-redis", 0.9),
        ):
            ratio = _ratio(rows, a, b, rate)
            if ratio is not None:
                floor = ""
                if a == "rap-5proc":
                    relay = _ratio(rows, "zenoh-relay", b, rate)
                    floor = f"zenoh-relay: {relay}" if relay is not None else ""
                elif a == "rap-inproc":
                    contract = _ratio(rows, "contract-paced", b, rate)
                    floor = f"contract-paced: {contract}" if contract is not None else ""
                elif (a, b) == ("rap-1proc", "zenoh-echo"):
                    least = _one_proc_floor(rows, rate)
                    echo = _find(rows, b, rate)
                    if least is not None and echo is not None and echo["p50_ms"]:
                        floor = f"zenoh-echo-loop + contract-paced: {least / echo['p50_ms']:.3f}"
                checks.append(_check(f"{what} at {rate:g} Hz", ratio, budget, floor))
        for variant in ("rap-1proc", "rap-5proc"):
            r = _find(rows, variant, rate)
            if r is None or r["p50_ms"] is None:
                continue
            if rate >= 20.0:
                value = round(r["p99_ms"] / r["p50_ms"], 2)
                checks.append(_check(f"{variant} p99 / own p50 at {rate:g} Hz", value, 2.0))
            if rate == 100.0:
                checks.append(_check(f"{variant} lost cycles at 100 Hz", r["lost"], 0))
    return checks


ROWS_EXPLAINED = [
    "What each row is:",
    "",
    "- `floor-paced`: the five handlers called directly (knowledge in a dict, the gate's "
    "check, no runtime), one cycle per period like the loop rows, the event loop idle "
    "in between: what the loop's own logic costs with caches as cold as a paced cycle "
    "finds them.",
    "- `contract-paced`: the same five stages as coroutines awaited one after another, "
    "doing what RAP's message and knowledge contract asks of a cycle (six envelopes "
    "with uid, time, sequence, cycle, cause and versions; three versioned knowledge "
    "writes kept in history; two reads checked against the versions their trigger "
    "names; the gate) and nothing else: no routing, inbox, trace or task switch "
    "(bench/loop/contract.py). Paced like `floor-paced`, it is the least a runtime "
    "keeping the contract can take; `rap-inproc` less this row is what RAP's dispatch "
    "costs.",
    "- `zenoh-echo`: two cross-process hops on raw Zenoh (robot -> echo -> robot), "
    "answered inside Zenoh's callback thread: no event loop at either end, no RAP code. "
    "Both raw-Zenoh rows run Zenoh's tasks on the two worker threads RAP's processes use "
    "(`ZenohConfig.runtime`).",
    "- `zenoh-echo-loop`: the same two hops with both ends woken in their asyncio loops "
    "(uvloop), as every RAP process is: the child is a one-stage relay (below) and the "
    "robot takes the echo from Zenoh's thread into its loop before it timestamps it. "
    "No RAP code: the least a round trip between two RAP processes can cost.",
    "- `zenoh-relay`: the five-process layout's transport floor on raw Zenoh: the "
    "robot -> five relay processes -> robot (six cross-process hops, all sessions "
    "meshed), each relay woken in its asyncio loop (uvloop) and putting the sample on "
    "from there: what six RAP hops pay at least, with no envelope, no decoding and no "
    "knowledge.",
    "- `rap-echo`: the same round trip through RAP (one node in a runner process, "
    "answering each scan with a plan).",
    "- `rap-inproc`: robot, the five stages and the knowledge service in one process on "
    "the in-memory fabric: what RAP's runtime costs per cycle, no transport.",
    "- `rap-1proc`: the five stages in one runner process, the knowledge service in its "
    "own, the robot in the bench process, over loopback Zenoh.",
    "- `rap-5proc`: each stage in its own runner process (six hops between processes).",
    "- `rpio-redis`, `rpio-mqtt`: the peer, RPIO 0.4.3's generated five-stage loop over "
    "Redis and over MQTT, run by the reference harness.",
    "",
    "Wall-clock rows are paced rounds of a few seconds each; on a small shared machine "
    "their p50 ratios move by up to 1.5x from one run to the next (compare runs before "
    "reading much into one budget line). The instruction counts above do not move.",
]


def _doc(out: dict[str, Any]) -> str:
    cols = ["system", "rate_hz", "p50_ms", "p90_ms", "p99_ms", "lost", "send_rate_hz", "n"]
    lines = [
        "## MAPLE-K loop race (`make bench-loop`)",
        "",
        f"Hardware: {hardware_line(out['hardware'])}",
        "",
        "Loop latency, scan published at the robot -> spin plan received at the robot "
        "(`python -m bench.loop`, every scan runs all five stages). "
        f"Floor (the five handlers called directly, back to back, hot caches): p50 "
        f"{out['floor']['p50_ms']} ms, p99 {out['floor']['p99_ms']} ms.",
        "",
        *_instructions_doc(out.get("instructions")),
        table(cols, [[r.get(c) for c in cols] for r in out["rows"]]),
        "",
        *ROWS_EXPLAINED,
        "",
        "Highest rate with no lost cycle: "
        + ", ".join(
            f"{k} {v if v is not None else '-'} Hz" for k, v in out["sustained_hz"].items()
        ),
        "",
        table(
            ["what", "value", "budget", "ok", "floor"],
            [
                [b["what"], b["value"], b["budget"], b["ok"], b.get("floor", "")]
                for b in out["budgets"]
            ],
        ),
        "",
        *_where(out["rows"]),
    ]
    return "\n".join(lines)


def _instructions_doc(instr: dict[str, Any] | None) -> list[str]:
    if not instr:
        return []
    rows = [
        [kind, f"{instr[kind]:,}", instr.get(f"{kind}_vs_direct", "")]
        for kind in ("direct", "contract", "chain", "chain-traced")
        if kind in instr
    ]
    return [
        f"Instructions per cycle (callgrind, {instr['cycles']} cycles after "
        f"{instr['warmup']} of warm-up, start-up cancelled out): `direct` is the five "
        "handlers called directly, `contract` the same with what RAP's contract asks of "
        "a cycle and no dispatch (the `contract-paced` row), `chain` the robot, the five "
        "stages and the knowledge "
        "service in one process on the in-memory fabric, `chain-traced` the same with a "
        "subscriber to every trace record. Counts do not drift with machine load.",
        "",
        table(["kind", "instructions per cycle", "x direct"], rows),
        "",
    ]


def _where(rows: list[dict[str, Any]]) -> list[str]:
    """Where RAP's loop latency goes, from this run's rows: p50 of each floor and of
    each variant, with what the budgets allow at the same rate."""
    systems = (*FLOORS, "rap-1proc", "rap-5proc", "rpio-redis")
    cols = [
        "rate_hz",
        *systems,
        "1proc floor",
        "5proc / echo",
        "5proc - relay",
        "2.4 x echo",
        "0.45 x rpio",
        "0.9 x rpio",
    ]
    body = []
    for rate in RATES:
        p50 = {s: (r or {}).get("p50_ms") for s in systems for r in [_find(rows, s, rate)]}
        peer, echo, five = p50["rpio-redis"], p50["zenoh-echo"], p50["rap-5proc"]
        relay = p50["zenoh-relay"]
        body.append(
            [
                rate,
                *p50.values(),
                _one_proc_floor(rows, rate),
                round(five / echo, 2) if five and echo else None,
                round(five - relay, 3) if five and relay else None,
                round(2.4 * echo, 3) if echo else None,
                *(round(peer * f, 3) if peer else None for f in (0.45, 0.9)),
            ]
        )
    return [
        "Where the time goes (p50, ms, this run), with what each budget allows at the "
        "same rate. Every RAP loop pays at least `zenoh-echo-loop`: the robot is in "
        "another process, and both are asyncio processes; `rap-echo` is that round trip "
        "through RAP. One runner process adds the chain (`rap-inproc`; `contract-paced` "
        "is the least of it) and the knowledge writes going out to the knowledge "
        "service's process; five processes add four more hops, each paying an event-loop wake-up "
        "at both ends (`5proc / echo` is that loop's p50 in raw Zenoh round trips; "
        "`zenoh-relay` is those six hops with their wake-ups and nothing else, and "
        "`5proc - relay` what RAP's stages, envelopes and knowledge add to them). "
        "`1proc floor` is `zenoh-echo-loop` plus `contract-paced`: the least a "
        "one-process loop can take, with no RAP dispatch at all and the knowledge "
        "service's writes left out; where `2.4 x echo` is under it, that budget is below "
        "a floor measured in this run.",
        "",
        table(cols, body),
    ]


def rewrite_doc() -> None:
    """The docs section again from bench/results/loop.json (after the text changed)."""
    import json

    write_section("loop", _doc(json.loads((ROOT / "bench" / "results" / "loop.json").read_text())))


if __name__ == "__main__":
    sys.exit(main())
