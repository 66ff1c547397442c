"""``python -m bench.sim [--quick] [--report-only]``: simulator figures in one run,
written to bench/results/sim.json and the sim section of docs/benchmarks.md; exits 1
when a budget is missed."""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
from sim_world.geometry import cast_rays, scene_of
from sim_world.physics import pymunk_ray, static_space
from sim_world.sim import Simulation
from sim_world.world import default_world_path, load_world

from ..report import (
    hardware_line,
    run_suite,
    summary_us,
    table,
)

BUDGETS = {"raycaster_vs_pymunk_scans_per_s": 5.0, "lockstep_realtime_factor": 100.0}


def measure(quick: bool) -> dict[str, Any]:
    world = load_world(default_world_path("default"))
    scene, space = scene_of(world), static_space(world)
    rng = np.random.default_rng(0)
    poses = [
        (rng.uniform(0.5, 9.5), rng.uniform(0.5, 7.5), rng.uniform(-math.pi, math.pi))
        for _ in range(50 if quick else 300)
    ]
    beams = -math.pi + np.arange(360) * (2 * math.pi / 360)
    ours, theirs = [], []
    for x, y, th in poses:  # interleaved: drift hits both alike
        t0 = time.perf_counter_ns()
        cast_rays(x, y, th + beams, scene, 12.0)
        ours.append(time.perf_counter_ns() - t0)
        t0 = time.perf_counter_ns()
        for a in th + beams:
            pymunk_ray(space, x, y, float(a), 12.0)
        theirs.append(time.perf_counter_ns() - t0)
    m: dict[str, Any] = {
        "vectorised scan (360 beams)": summary_us(ours),
        "pymunk segment queries (360 beams)": summary_us(theirs),
    }
    m["scans_per_s"] = {
        "vectorised": round(1e9 / float(np.median(ours))),
        "pymunk": round(1e9 / float(np.median(theirs))),
    }
    sim_seconds = 60.0 if quick else 300.0
    sim = Simulation(world)
    t0 = time.perf_counter()
    sim.run(sim_seconds)
    wall = time.perf_counter() - t0
    m["lockstep"] = {
        "sim_s": sim_seconds,
        "wall_s": round(wall, 3),
        "realtime_factor": round(sim_seconds / wall, 1),
        "lidar_hz": world.lidar.rate_hz,
        "physics_hz": world.physics_hz,
    }
    return m


def verdicts(m: dict[str, Any]) -> dict[str, Any]:
    values = {
        "raycaster_vs_pymunk_scans_per_s": round(
            m["scans_per_s"]["vectorised"] / m["scans_per_s"]["pymunk"], 1
        ),
        "lockstep_realtime_factor": m["lockstep"]["realtime_factor"],
    }
    return {k: {"value": v, "budget": BUDGETS[k], "ok": v >= BUDGETS[k]} for k, v in values.items()}


def render(m: dict[str, Any], v: dict[str, Any], hw: dict[str, Any]) -> str:
    rows = [
        [k, s["p50_us"], s["p99_us"], s["n"]]
        for k, s in m.items()
        if isinstance(s, dict) and "p50_us" in s
    ]
    ls = m["lockstep"]
    return "\n".join(
        [
            "## Simulator (`make bench-sim`)",
            "",
            f"Hardware: {hardware_line(hw)}",
            "",
            "One 360-beam scan of the default world from random poses: the vectorised "
            "raycaster against pymunk's segment query per beam (the same poses, interleaved).",
            "",
            table(["scan", "p50 µs", "p99 µs", "n"], rows),
            "",
            f"Lockstep: {ls['sim_s']} s of the default world ({ls['lidar_hz']} Hz lidar, "
            f"{ls['physics_hz']} Hz physics) in {ls['wall_s']} s: real-time factor "
            f"{ls['realtime_factor']}.",
            "",
            "Budgets (at least):",
            "",
            table(
                ["budget", "measured", "minimum", ""],
                [[k, x["value"], x["budget"], "ok" if x["ok"] else "MISSED"] for k, x in v.items()],
            ),
        ]
    )


def main() -> int:
    return run_suite("sim", measure, verdicts, render)


if __name__ == "__main__":
    raise SystemExit(main())
