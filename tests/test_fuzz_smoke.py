"""bench/fuzz cannot rot: its mutations are reproducible and each one yields bytes, and a
small run against the real processes sends every target its samples, reads the
rejections and measures every process.

The small run checks the harness, not the loop: what it finds (crashes, a loop that does
not close) is the full run's business (``make fuzz``), so it is only reported here."""

from __future__ import annotations

import json
import math
from pathlib import Path

import anyio
import msgspec
import pytest
from lidar_occlusion.demo import default_plan_path
from lidar_occlusion.scans import occluded_scan

from bench.fuzz.__main__ import render
from bench.fuzz.mutate import MUTATIONS, Mutator
from bench.fuzz.run import Options, run
from bench.fuzz.samples import plain

SYSTEM = "demo"


NOW = 1_700_000_000_000_000_000


def _batch(seed: int) -> list[tuple[str, bytes, bytes]]:
    """(mutation, the valid sample, the mutated one) for every mutation, three times."""
    m = Mutator(
        "data/tb1/scan",
        seed,
        sources=["fuzzer", "monitor"],
        ctx_keys=["laser_scan"],
        clock=lambda: NOW,
    )
    body = plain(occluded_scan(-0.4, 0.8))
    out = []
    for name in MUTATIONS * 3:
        valid = m.envelope("rap/demo/data/tb1/scan", "rap.LaserScan/1", body)
        valid["uid"] = bytes(16)  # uids follow the clock's sub-ms counter: pinned here
        out.append((name, msgspec.msgpack.encode(valid), m.mutate(name, valid)))
    return out


def test_mutations_are_reproducible_and_each_one_changes_the_sample() -> None:
    a = _batch(7)
    assert a == _batch(7)
    assert a != _batch(8)
    assert {name for name, _, _ in a} == set(MUTATIONS)
    for name, valid, payload in a:
        assert isinstance(payload, bytes), name
        assert payload != valid, name


def test_nonfinite_floats_reach_the_wire() -> None:
    m = Mutator("t", 3)
    valid = m.envelope("k", "rap.LaserScan/1", plain(occluded_scan()))
    seen = set()
    for _ in range(20):
        env = msgspec.msgpack.decode(m.mutate("nonfinite", valid))
        body = env["body"]
        values = [body[k] for k in ("angle_min", "angle_increment", "range_min", "range_max")]
        values += body["ranges"] if isinstance(body.get("ranges"), list) else []
        seen |= {repr(v) for v in values if isinstance(v, float) and not math.isfinite(v)}
    assert {"nan", "inf", "-inf"} <= seen


@pytest.mark.slow
@pytest.mark.zenoh
@pytest.mark.timeout(180)
def test_a_small_fuzz_run_reaches_every_target_and_measures_every_process(
    tmp_path: Path,
) -> None:
    opts = Options(
        plan=default_plan_path("demo"),
        seconds=8.0,
        samples=1500,
        seed=1,
        specs=["stage_order"],
        logs=tmp_path / "logs",
        close_timeout=20.0,
    )
    report = anyio.run(run, opts)
    json.dumps(report, default=str)  # what __main__ writes
    assert report["system"] == SYSTEM
    assert report["warm_up"]["closed"]
    assert report["warm_up"]["checkers_heard"] == ["trust_stage_order"]
    targets = report["targets"]
    names = set(targets)
    # derived from the nodes' routes and the warm-up cycle's knowledge accesses
    assert {
        "data/tb1/scan",
        "event/new-data",
        "event/anomaly",
        "event/new-plan",
        "event/verdict",
        "event/plan-rejected",
        "kb/laser_scan",
        "kb/lidar_mask",
        "kb/planned_lidar_mask",
        "kb/handling_anomaly",
        "kb/fuzz/other",
        "trace/*",
        "kb/** (queries)",
        "admin/trust_stage_order/swap (queries)",
    } <= names
    assert all(t["sent"] >= 1500 for t in targets.values()), targets
    assert report["target_reached"]
    assert report["samples_total"] >= 1500 * len(targets)
    queries = targets["kb/** (queries)"]["replies"]
    assert sum(queries.values()) == targets["kb/** (queries)"]["sent"]
    assert report["rejections"]["records"] > 0
    assert report["rejections"]["by_reason"]
    assert set(report["processes"]) == {"knowledge", "runner-laptop", "trust_stage_order"}
    for name, p in report["processes"].items():
        assert p["rss_before_kib"] > 0, name
        assert p["exit_code"] is not None, name
    assert isinstance(report["crashes"], list)
    assert isinstance(report["loop_closed_after"], bool)
    text = render(report, {"cpu": "x", "cores": 1, "mem_gib": 1, "python": "3", "os": "x",
                           "packages": {}, "date": "now"})  # fmt: skip
    assert "rejections by reason" in text
    assert "loop closed after the flood" in text
