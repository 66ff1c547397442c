"""``make eval``: the configurations, the figures, the table, the worker processes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import anyio
import pytest
from lidar_occlusion.eval import (
    CONFIGURATIONS,
    ROUTE,
    aggregate,
    configuration,
    run_scenario,
    table,
    twin_rejections,
)
from lidar_occlusion.planning import LegitimacyConfig
from lidar_occlusion.scenario import rejection_codes, spin_seconds
from rap_schemas import SpinCommand, SpinPlan


def test_each_loop_configuration_selects_its_planner_and_twin() -> None:
    assert configuration("reference")[0].planner == "reference"
    assert configuration("lookahead")[0].planner == "lookahead"
    assert configuration("lookahead")[1] == LegitimacyConfig()
    assert configuration("lookahead")[0].route == ROUTE  # the lookahead needs the route
    with pytest.raises(ValueError, match="no loop configuration 'no_loop'"):
        configuration("no_loop")
    for name in ("reference_twin", "lookahead_twin"):
        planning, legitimacy = configuration(name)
        assert legitimacy.twin is True
        assert legitimacy.route == ROUTE  # the twin navigates the scenarios' route
        assert planning.planner == CONFIGURATIONS[name][0]


def test_spin_time_counts_each_period_until_the_next_plan() -> None:
    spin = SpinPlan(commands=[SpinCommand(omega=1.0, duration=1.5)], period=8.0)
    empty = SpinPlan(commands=[], period=8.0)
    assert spin_seconds([], 100.0) == 0.0
    assert spin_seconds([(10.0, spin)], 100.0) == pytest.approx(12 * 1.5)  # 90 s: 11.25 periods
    assert spin_seconds([(10.0, spin), (17.0, empty)], 100.0) == pytest.approx(1.5)
    assert spin_seconds([(10.0, spin), (10.5, spin)], 11.0) == pytest.approx(0.5 + 0.5)


def test_rejections_are_counted_by_code_and_the_twins_apart() -> None:
    codes = rejection_codes(
        [
            "collision: the robot meets a believed obstacle at 2.1 s",
            "clearance: 0.03 m",
            "spec:robot_ok: clearance_ok turned false",
            "plan is stale: 0.300 s old, limit 0.2 s",
            "commands take 9.000 s, not within the period of 8.0 s",
        ]
    )
    assert codes == {"collision": 1, "clearance": 1, "spec:robot_ok": 1, "check": 2}
    assert twin_rejections(codes) == 3


def _metrics(collisions: int, completed: bool, spin: float = 0.0) -> dict[str, Any]:
    return {
        "collisions": collisions,
        "route_completed": completed,
        "waypoints_reached": 4 if completed else 2,
        "spin_s": spin,
        "plans_proposed": 3,
        "plans_rejected": 1,
        "rejections": {"collision": 1},
        "occlusion_onsets": 1,
        "detected_onsets": 1,
        "detection_latency_scans": {"p50": 0, "max": 0},
        "anomaly_to_robot_ms": {"p50": 0.5, "p99": 0.5},
        "loop_latency_ms": {"p50": 1.0, "p99": 1.0},
        "false_anomalies": 0,
        "overreaching_masks": 0,
        "anomalies": 1,
    }


def _run(seed: int, **by_config: dict[str, Any]) -> dict[str, Any]:
    return {
        "seed": seed,
        "mode": "sector",
        "front": True,
        "loop": by_config["reference"],
        "no_loop": by_config["no_loop"],
        "configurations": by_config,
    }


def test_the_aggregate_keeps_its_keys_and_judges_each_configuration_by_the_goal() -> None:
    runs = [
        _run(
            s,
            no_loop=_metrics(2 if s == 0 else 0, True),
            reference=_metrics(0, s >= 5, 40.0),
            lookahead=_metrics(0, s != 0, 5.0),
        )
        for s in range(20)
    ]
    agg = aggregate(runs)
    for key in ("loop", "no_loop", "front_blind", "by_mode", "detection_rate", "false_anomalies"):
        assert key in agg
    assert agg["loop"]["routes_completed"] == 15
    configs = agg["configurations"]
    assert list(configs) == ["no_loop", "reference", "lookahead"]
    assert configs["no_loop"]["collisions"] == 2
    assert configs["no_loop"]["meets_goal"] is False  # it collides
    assert configs["reference"]["meets_goal"] is False  # 15 of 20 routes: beyond 5 % fewer
    assert configs["lookahead"]["routes_completed"] == 19
    assert configs["lookahead"]["meets_goal"] is True  # 19 >= 0.95 * 20
    assert configs["lookahead"]["spin_s"] == 100.0
    assert configs["lookahead"]["plans_rejected_twin"] == 20
    text = table(agg)
    assert "time spinning (s)" in text
    header = next(line for line in text.splitlines() if "lookahead" in line and "no loop" in line)
    assert header.index("no loop") < header.index("reference") < header.index("lookahead")


def test_a_scenario_runs_in_each_configuration_asked_for() -> None:
    entry = anyio.run(run_scenario, 4, 20.0, ["no_loop", "lookahead"])
    assert entry["seed"] == 4
    assert entry["mode"] == "none"  # seed 4: obstacles only
    assert set(entry["configurations"]) == {"no_loop", "lookahead"}
    assert "loop" not in entry  # the reference did not run
    assert entry["no_loop"] is entry["configurations"]["no_loop"]
    for m in entry["configurations"].values():
        assert m["sim_seconds"] == pytest.approx(20.0)
        assert m["spin_s"] == 0.0  # nothing occluded: no spin
        assert m["plans_proposed"] == 0


def test_workers_give_the_same_figures_as_one_process(tmp_path: Path) -> None:
    def run(jobs: int) -> dict[str, Any]:
        out = tmp_path / f"jobs{jobs}"
        done = subprocess.run(
            [
                sys.executable,
                "-m",
                "lidar_occlusion.eval",
                "--runs",
                "2",
                "--seed",
                "2",
                "--duration",
                "25",
                "--configurations",
                "reference,no_loop",
                "--jobs",
                str(jobs),
                "--out",
                str(out),
            ],
            capture_output=True,
            text=True,
            timeout=300,
            check=False,
        )
        assert done.returncode == 0, done.stderr
        assert "routes completed" in done.stdout
        doc: dict[str, Any] = json.loads((out / "lidar_occlusion.json").read_text())
        return doc

    one, two = run(1), run(2)
    assert two["jobs"] == 2
    assert one["configurations"] == two["configurations"] == ["no_loop", "reference"]
    assert [r["seed"] for r in two["results"]] == [2, 3]
    keep = ("collisions", "waypoints_reached", "spin_s", "plans_proposed", "anomalies")
    for a, b in zip(one["results"], two["results"], strict=True):
        for name in ("no_loop", "reference"):
            assert {k: a["configurations"][name][k] for k in keep} == {
                k: b["configurations"][name][k] for k in keep
            }
    assert one["aggregate"]["configurations"] == two["aggregate"]["configurations"]


def test_an_unknown_configuration_is_one_error_line() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "lidar_occlusion.eval", "--configurations", "reference,fast"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 2, done.stderr
    assert done.stderr.startswith("error: ")
    assert done.stderr.count("\n") == 1
    assert "['fast']: choose from no_loop, reference" in done.stderr
