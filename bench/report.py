"""Shared by the benchmarks: percentiles, the hardware line, JSON results and the
sections of docs/benchmarks.md (each benchmark owns the text between its markers)."""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import re
import sys
import time
from collections.abc import Callable, Sequence
from importlib import metadata
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
DOC = ROOT / "docs" / "benchmarks.md"


def pct(values: Sequence[float], q: float) -> float:
    """The q-quantile (0..1) by nearest rank: the smallest value with at least a
    fraction q of the samples at or below it."""
    if not values:
        raise ValueError("no samples")
    s = sorted(values)
    return s[max(0, math.ceil(q * len(s)) - 1)]


def summary_us(ns: Sequence[int]) -> dict[str, float]:
    return {
        "p50_us": round(pct(ns, 0.50) / 1000, 2),
        "p90_us": round(pct(ns, 0.90) / 1000, 2),
        "p99_us": round(pct(ns, 0.99) / 1000, 2),
        "n": len(ns),
    }


def hardware() -> dict[str, Any]:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem_gib = 0.0
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                mem_gib = round(int(line.split()[1]) / 2**20, 1)
    except OSError:
        pass
    versions = {}
    for pkg in ("eclipse-zenoh", "msgspec", "anyio", "uvloop"):
        try:
            versions[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            versions[pkg] = "-"
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "mem_gib": mem_gib,
        "python": sys.version.split()[0],
        "os": platform.platform(terse=True),
        "packages": versions,
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
    }


def hardware_line(hw: dict[str, Any]) -> str:
    pk = ", ".join(f"{k} {v}" for k, v in hw["packages"].items())
    return (
        f"{hw['cpu']}, {hw['cores']} cores, {hw['mem_gib']} GiB, Python {hw['python']}, "
        f"{hw['os']}; {pk}; {hw['date']}"
    )


def write_json(name: str, data: dict[str, Any]) -> Path:
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(data, indent=2, sort_keys=True) + "\n", encoding="utf-8")
    return path


def write_section(name: str, markdown: str) -> None:
    """Replace this benchmark's section of docs/benchmarks.md (created if missing)."""
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    text = DOC.read_text(encoding="utf-8") if DOC.exists() else "# Benchmarks\n"
    block = f"{begin}\n{markdown.rstrip()}\n{end}"
    pattern = re.compile(re.escape(begin) + r".*?" + re.escape(end), re.S)
    text = (
        pattern.sub(lambda _: block, text)
        if pattern.search(text)
        else (text.rstrip() + "\n\n" + block + "\n")
    )
    DOC.parent.mkdir(parents=True, exist_ok=True)
    DOC.write_text(text, encoding="utf-8")


def table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    out = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(out)


def run_suite(
    name: str,
    measure: Callable[[bool], dict[str, Any]],
    verdicts: Callable[[dict[str, Any]], dict[str, Any]],
    render: Callable[[dict[str, Any], dict[str, Any], dict[str, Any]], str],
) -> int:
    """The command line of a benchmark suite: ``--quick`` (a smoke run written to
    ``<name>.quick.json``, the page left alone) and ``--report-only`` (exit 0 even when a
    budget is missed). Writes the results and the suite's section of the page."""
    ap = argparse.ArgumentParser(prog=f"python -m bench.{name}")
    ap.add_argument("--quick", action="store_true", help="fewer iterations (smoke run)")
    ap.add_argument("--report-only", action="store_true", help="exit 0 even if over budget")
    args = ap.parse_args()
    hw = hardware()
    print(f"bench/{name} on {hardware_line(hw)}", file=sys.stderr)
    m = measure(args.quick)
    v = verdicts(m)
    write_json(
        f"{name}.quick" if args.quick else name,
        {"hardware": hw, "quick": args.quick, "measurements": m, "budgets": v},
    )
    text = render(m, v, hw)
    if not args.quick:
        write_section(name, text)
    print(text)
    # a verdict with checked=False is reported beside the budget, not enforced
    missed = [k for k, x in v.items() if x.get("checked", True) and not x["ok"]]
    if missed and not args.report_only:
        print(f"budget missed: {', '.join(missed)}", file=sys.stderr)
        return 1
    return 0
