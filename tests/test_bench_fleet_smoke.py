"""`make bench-fleet` in miniature: a few robots' loops in real processes, every cycle
closed, the figures and the budget check computed from them."""

from __future__ import annotations

from pathlib import Path

import anyio

from bench.fleet.__main__ import budgets, summarise
from bench.fleet.run import Options, measure


def test_a_small_fleet_closes_every_cycle_and_reports_each_process(tmp_path: Path) -> None:
    opts = Options(robots=3, rate=5.0, seconds=3.0, warmup=2.0, runners=2, out=tmp_path)
    raw = anyio.run(measure, opts, print, backend_options={"use_uvloop": True})
    s = summarise(opts, raw)
    checks = {c["what"]: c for c in budgets(s)}
    assert checks["lost cycles"]["value"] == 0, s
    assert s["latency"]["n"] >= 3 * 5 * 2  # about 3 s of 3 robots at 5 Hz
    rows = s["resources"]["processes"]
    names = {r["process"] for r in rows}
    assert any(n.startswith("runner") for n in names), names
    assert any("knowledge" in n for n in names), names
    for r in rows:
        assert r["rss_mib"] > 0
