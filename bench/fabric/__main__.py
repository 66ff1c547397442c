"""``python -m bench.fabric [--quick] [--report-only]``: run every fabric measurement in
one run, write bench/results/fabric.json and the fabric section of docs/benchmarks.md,
and exit 1 when a budget is missed (unless --report-only)."""

from __future__ import annotations

import sys
from collections.abc import Awaitable, Callable
from typing import Any

import anyio

from ..report import hardware_line, pct, run_suite, summary_us, table
from . import local, remote

SIZES = (64, 4096)
ROUNDS = 7
BUDGETS = {"sdk_vs_raw_zenoh_p50": 1.3, "inproc_vs_queue_p50": 3.0}


def run(fn: Callable[..., Awaitable[Any]], *args: Any, uvloop: bool = False, **kw: Any) -> Any:
    async def main() -> Any:
        return await fn(*args, **kw)

    return anyio.run(main, backend_options={"use_uvloop": uvloop})


def step(msg: str) -> None:
    print(f"  {msg}", file=sys.stderr, flush=True)


def hop_us(rtt: dict[str, float]) -> dict[str, float]:
    """One hop = half a ping-pong round trip."""
    return {k: (round(v / 2, 2) if k.endswith("_us") else v) for k, v in rtt.items()}


def measure(quick: bool) -> dict[str, Any]:
    iters, warm = (350, 50) if quick else (3500, 300)
    tput_n = {64: 5000 if quick else 50000, 4096: 2000 if quick else 20000}
    out: dict[str, Any] = {"latency": {}, "throughput": {}, "inproc": {}, "handoff": {}}

    latency_cases: list[tuple[str, Callable[..., Awaitable[list[int]]], dict[str, Any]]] = [
        ("rap_sdk/zenoh", remote.sdk_latency, {}),
        ("raw zenoh-python -> asyncio", remote.zenoh_latency, {}),
        ("rap_sdk/zenoh (uvloop)", remote.sdk_latency, {"uvloop": True}),
        ("raw zenoh-python -> asyncio (uvloop)", remote.zenoh_latency, {"uvloop": True}),
        ("rap_sdk/zenoh (indirect callbacks)", remote.sdk_latency, {"direct": False}),
        ("rap_sdk fabric only, no envelope/node (diagnostic)", remote.fabric_latency, {}),
        (
            "raw zenoh-python, loop callback only (floor)",
            remote.zenoh_latency,
            {"via_queue": False},
        ),
        ("asyncio TCP echo", remote.tcp_latency, {}),
    ]
    # interleaved rounds, samples pooled: drift on a shared machine hits every path alike
    for size in SIZES:
        pooled: dict[str, list[int]] = {name: [] for name, _, _ in latency_cases}
        per_round: dict[str, list[float]] = {name: [] for name, _, _ in latency_cases}
        for rnd in range(ROUNDS):
            for name, fn, kw in latency_cases:
                step(f"latency {name} {size} B (round {rnd + 1}/{ROUNDS})")
                ns = run(fn, size, iters // ROUNDS, warm, **kw)
                pooled[name] += ns
                per_round[name].append(pct(ns, 0.5))
        for name, ns in pooled.items():
            out["latency"].setdefault(str(size), {})[name] = {
                **hop_us(summary_us(ns)),
                "round_p50s_ns": per_round[name],
            }

    tput_cases: list[tuple[str, Callable[..., Awaitable[dict[str, Any]]]]] = [
        ("rap_sdk/zenoh", remote.sdk_throughput),
        ("raw zenoh-python -> asyncio", remote.zenoh_throughput),
        ("asyncio TCP", remote.tcp_throughput),
    ]
    for size in SIZES:
        for name, fn in tput_cases:
            step(f"throughput {name} {size} B")
            r = run(fn, size, tput_n[size])
            secs = (r["last_ns"] - r["first_ns"]) / 1e9
            rate = (r["n"] - 1) / secs if secs > 0 else float("inf")
            out["throughput"].setdefault(str(size), {})[name] = {
                "msgs_per_s": round(rate),
                "mib_per_s": round(rate * size / 2**20, 1),
                "n": r["n"],
            }

    inproc_cases: list[tuple[str, Callable[..., Awaitable[list[int]]], dict[str, Any]]] = [
        ("asyncio.Queue hop", local.queue_hop, {}),
        ("rap_sdk stage->stage (ZenohFabric, traced)", local.stage_hop, {"kind": "zenoh"}),
        (
            "rap_sdk stage->stage (ZenohFabric, untraced)",
            local.stage_hop,
            {"kind": "zenoh", "trace": False},
        ),
        ("rap_sdk stage->stage (MemoryFabric, traced)", local.stage_hop, {"kind": "memory"}),
        (
            "rap_sdk stage->stage (ZenohFabric, traced, remote trace subscriber)",
            local.stage_hop,
            {"kind": "zenoh", "trace_listener": True},
        ),
        ("asyncio.Queue hop (uvloop)", local.queue_hop, {"uvloop": True}),
        (
            "rap_sdk stage->stage (ZenohFabric, traced, uvloop)",
            local.stage_hop,
            {"kind": "zenoh", "uvloop": True},
        ),
    ]
    for name, fn, kw in inproc_cases:
        step(f"in-process {name}")
        uv = kw.pop("uvloop", False)
        args = (kw.pop("kind"), iters * 3, warm) if "kind" in kw else (iters * 3, warm)
        out["inproc"][name] = summary_us(run(fn, *args, uvloop=uv, **kw))

    for scheme in ("per-sample call_soon_threadsafe", "batched"):
        for uv in (False, True):
            name = f"{scheme}{' (uvloop)' if uv else ''}"
            step(f"hand-off {name}")
            r = run(
                local.handoff,
                "batched" if scheme == "batched" else "single",
                iters,
                200_000 if not quick else 20_000,
                uvloop=uv,
            )
            out["handoff"][name] = {
                **summary_us(r["latency_ns"]),
                "burst_items_per_s": r["burst_items_per_s"],
            }
    return out


def paired(cases: dict[str, Any], a: str, b: str) -> float:
    """Median over rounds of p50(a)/p50(b), each pair measured back to back."""
    ra, rb = cases[a]["round_p50s_ns"], cases[b]["round_p50s_ns"]
    return round(pct([x / y for x, y in zip(ra, rb, strict=True)], 0.5), 2)


def ratios(m: dict[str, Any]) -> dict[str, Any]:
    r: dict[str, Any] = {}
    raw, floor = "raw zenoh-python -> asyncio", "raw zenoh-python, loop callback only (floor)"
    for size, c in m["latency"].items():
        r[f"sdk_vs_raw_zenoh_p50@{size}/asyncio"] = paired(c, "rap_sdk/zenoh", raw)
        r[f"sdk_vs_raw_zenoh_p50@{size}/uvloop"] = paired(
            c, "rap_sdk/zenoh (uvloop)", f"{raw} (uvloop)"
        )
        r[f"sdk_vs_raw_callback_floor_p50@{size}/asyncio"] = paired(c, "rap_sdk/zenoh", floor)
    inproc = m["inproc"]
    q, qu = inproc["asyncio.Queue hop"]["p50_us"], inproc["asyncio.Queue hop (uvloop)"]["p50_us"]
    r["inproc_vs_queue_p50/asyncio"] = round(
        inproc["rap_sdk stage->stage (ZenohFabric, traced)"]["p50_us"] / q, 2
    )
    r["inproc_vs_queue_p50/uvloop"] = round(
        inproc["rap_sdk stage->stage (ZenohFabric, traced, uvloop)"]["p50_us"] / qu, 2
    )
    return r


def verdicts(r: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Budgets are checked on the standard asyncio loop, as the issue states them;
    the uvloop and callback-floor ratios are reported beside them, not checked."""
    v = {}
    for key, value in r.items():
        base = key.split("@")[0].split("/")[0]
        if base in BUDGETS:
            checked = key.endswith("/asyncio")
            v[key] = {
                "ratio": value,
                "budget": BUDGETS[base],
                "checked": checked,
                "ok": value <= BUDGETS[base],
            }
    return v


def render(m: dict[str, Any], v: dict[str, Any], hw: dict[str, Any]) -> str:
    r = m["ratios"]
    parts = ["## Fabric (`make bench-fabric`)", "", f"Hardware: {hardware_line(hw)}", ""]
    parts += [
        "One-hop latency between two processes on loopback: half of a ping-pong round trip, "
        "measured from the send call to the coroutine that receives the reply. The SDK hop "
        "includes envelope sealing and opening, duplicate tracking, typed decoding and the "
        "node runtime. The baseline, raw zenoh-python -> asyncio, hands each sample from "
        "the Zenoh callback to the loop (call_soon_threadsafe) and through an asyncio.Queue "
        "to a coroutine, on both sides. The floor row handles the sample in the loop "
        "callback itself and never reaches coroutine code; every async handler costs at "
        "least one loop turn more than that. † Paths run interleaved in 7 rounds; a ratio is "
        "the median over rounds of the two p50s measured back to back (the machine's drift "
        "between runs is larger than the differences measured); p50/p99 pool all rounds.",
        "",
    ]
    rows = []
    for size, cases in m["latency"].items():
        for name, s in cases.items():
            loop = " (uvloop)" if "uvloop" in name else ""
            ratio = paired(cases, name, f"raw zenoh-python -> asyncio{loop}")
            rows.append([f"{size} B", name, s["p50_us"], s["p99_us"], f"{ratio:.2f}"])
    parts += [
        table(["size", "path", "p50 µs", "p99 µs", "p50 vs raw zenoh, same loop †"], rows),
        "",
    ]
    parts += ["One-way throughput between two processes (receiver-side rate):", ""]
    rows = [
        [f"{size} B", name, f"{s['msgs_per_s']:,}", s["mib_per_s"]]
        for size, cases in m["throughput"].items()
        for name, s in cases.items()
    ]
    parts += [table(["size", "path", "msgs/s", "MiB/s"], rows), ""]
    parts += [
        "In-process stage-to-stage delivery (emit -> next stage's handler start) vs a "
        "bare asyncio.Queue hop between two tasks:",
        "",
    ]
    q = m["inproc"]["asyncio.Queue hop"]["p50_us"]
    qu = m["inproc"]["asyncio.Queue hop (uvloop)"]["p50_us"]
    rows = [
        [name, s["p50_us"], s["p99_us"], f"{s['p50_us'] / (qu if 'uvloop' in name else q):.2f}"]
        for name, s in m["inproc"].items()
    ]
    parts += [table(["path", "p50 µs", "p99 µs", "p50 vs queue"], rows), ""]
    parts += [
        "Transport thread -> event loop hand-off (one item at a time; and a burst "
        "from one thread):",
        "",
    ]
    rows = [
        [name, s["p50_us"], s["p99_us"], f"{s['burst_items_per_s']:,}"]
        for name, s in m["handoff"].items()
    ]
    parts += [table(["scheme", "p50 µs", "p99 µs", "burst items/s"], rows), ""]
    parts += [
        "Budgets (checked on the standard asyncio loop, where the issue states them; "
        "uvloop and the callback floor are reported beside them):",
        "",
    ]
    rows = []
    for k, val in v.items():
        verdict = "ok" if val["ok"] else "MISSED"
        if not val["checked"]:
            verdict = ("within" if val["ok"] else "over") + " (reported)"
        rows.append([k, val["ratio"], val["budget"], verdict])
    rows += [[k, val, "-", "reported"] for k, val in r.items() if "floor" in k]
    parts += [table(["ratio", "measured", "budget", ""], rows)]
    return "\n".join(parts)


def main() -> int:
    return run_suite("fabric", measure_with_ratios, lambda m: verdicts(m["ratios"]), render)


def measure_with_ratios(quick: bool) -> dict[str, Any]:
    m = measure(quick)
    m["ratios"] = ratios(m)
    return m


if __name__ == "__main__":
    raise SystemExit(main())
