"""bench/faults cannot rot: its quick mode runs three cheap scenarios against the real
processes (``rap up --all`` of the lidar model, a FIFO receiver process, a router with
peers killed -9) and reports figures that the harness must have measured, not assumed.

The targets themselves (a plan within 2 s of a restart, no write lost, no event lost, a
router that keeps little of peers gone) are ``make faults``' business; here only that a
figure was measured is checked, except where a miss means the harness itself is broken
(a kill that was never restarted, a probe that wrote nothing) or the config rap up
writes is (shared memory on)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench.faults.__main__ import main

pytestmark = [pytest.mark.zenoh, pytest.mark.slow, pytest.mark.timeout(180)]


def test_the_quick_kill_and_fifo_scenarios_measure_their_figures(tmp_path: Path) -> None:
    out = tmp_path / "faults.json"
    argv = ["--quick", "--only", "kills,fifo", "--backends", "sqlite"]
    argv += ["--kill-targets", "knowledge", "--no-doc", "--out", str(out)]
    argv += ["--work", str(tmp_path / "work")]
    code = main(argv)
    report = json.loads(out.read_text())
    assert code == (0 if report["ok"] else 1)
    kills = report["scenarios"]["kills"]
    assert "error" not in kills, kills
    res = kills["backends"]["sqlite"]
    (kill,) = res["kills"]
    assert kill["target"] == "knowledge"
    assert 0 < kill["restart_after_s"] < 30  # rap up restarted it (after its backoff)
    assert kill["plan_after_restart_s"] is not None  # the loop went on
    assert kill["serving_after_restart_s"] is not None  # its liveliness came back
    writes = res["writes"]
    assert writes["acknowledged"] > 10, writes
    assert writes["writes"] == sum(writes["outcomes"].values())
    assert res["plans"]["plans_sent"] > 0
    assert res["restarts"]["edge/knowledge"] == 1
    fifo = report["scenarios"]["fifo"]
    assert "error" not in fifo, fifo
    assert fifo["sent"] == 10_000
    assert fifo["received"]["distinct"] + fifo["lost"] == fifo["sent"]
    assert len(fifo["windows"]) >= 4
    assert all(w["p50_ms"] is not None for w in fifo["windows"])
    assert fifo["rss"]["start_mib"] > 0
    text = "\n".join(report["table"])
    assert "kill -9" in text
    assert "FIFO 1 kHz" in text


def test_the_quick_memory_scenario_measures_a_router_per_config(tmp_path: Path) -> None:
    out = tmp_path / "faults.json"
    argv = ["--quick", "--only", "memory", "--no-doc", "--out", str(out)]
    code = main([*argv, "--work", str(tmp_path / "work")])
    report = json.loads(out.read_text())
    assert code == (0 if report["ok"] else 1)
    memory = report["scenarios"]["memory"]
    assert "error" not in memory, memory
    assert memory["peers"] == 3
    variants = memory["variants"]
    assert list(variants) == ["zenoh", "limit", "no-shm", "rap"]
    for name, v in variants.items():
        assert len(v["rss_mib"]) == 4, name  # before, and after each peer was gone
        assert all(m > 0 for m in v["rss_mib"]), name
        assert v["end_mib"]["rss"] > 0, name
    # what rap up writes: the model's limit on the links, and no shared memory to map
    rap = variants["rap"]
    assert (rap["message_limit_bytes"], rap["shared_memory"]) == ((4 << 20) + (64 << 10), False)
    assert rap["shmem_mib"] == [0.0] * 4
    text = "\n".join(report["table"])
    assert "killed -9" in text
    assert "rap: rap up / rap generate now" in text
