"""``make eval``: does the loop help? N seeded scenarios, each with the loop and without.

    python -m lidar_occlusion.eval --runs 20 --seed 1 [--duration 120] [--out out/eval]

A scenario (:func:`scenario`) is a 10 x 8 m room with the robot driving a rectangular
route; 2 to 5 obstacles, half of them on the route; one occlusion, its mode taking turns
(``sector``, ``arcs``, ``global``, ``random``, then none at all: the obstacle-only runs,
where every anomaly is a false one), at a random angle, from a random start to 5 s
before the end. Runs whose occlusion covers the robot's front (within 30 degrees of
straight ahead) when it starts are reported apart as well: there an unhandled occlusion
hides what the robot drives into. Each runs
in lockstep, in this process, once with the loop and once without, from the same seed.
Writes ``<out>/lidar_occlusion.json`` (every run and the aggregate) and prints a table.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Annotated, Any

import anyio
import msgspec
import numpy as np
import typer
from rap_sdk.entry import run_cli
from sim_world.occlusion import occlusion_mask
from sim_world.world import WorldSpec

from .scenario import run_in_process

__all__ = ["MODES", "aggregate", "scenario"]

cli = typer.Typer(add_completion=False, help=__doc__)

MODES = ("sector", "arcs", "global", "random", "none")
ROUTE = [(8.5, 1.2), (8.5, 6.8), (1.5, 6.8), (1.2, 1.2)]


def scenario(seed: int, duration: float) -> tuple[str, WorldSpec]:
    """The seeded world of run ``seed``: (occlusion mode, world)."""
    rng = np.random.default_rng(seed)
    mode = MODES[seed % len(MODES)]  # every mode equally often
    obstacles: list[dict[str, Any]] = []
    legs = list(zip([(1.0, 1.0), *ROUTE[:-1]], ROUTE, strict=True))
    n = int(rng.integers(2, 6))
    for i in range(n):
        if i % 2 == 0:  # on the route, not at its ends
            (x0, y0), (x1, y1) = legs[int(rng.integers(len(legs)))]
            f = float(rng.uniform(0.3, 0.7))
            x = x0 + f * (x1 - x0) + float(rng.normal(0, 0.1))
            y = y0 + f * (y1 - y0) + float(rng.normal(0, 0.1))
        else:
            x, y = float(rng.uniform(2.5, 7.5)), float(rng.uniform(2.5, 5.5))
        if rng.random() < 0.7:
            obstacles.append({"kind": "circle", "x": x, "y": y, "r": float(rng.uniform(0.2, 0.4))})
        else:
            w, h = float(rng.uniform(0.3, 0.7)), float(rng.uniform(0.3, 0.7))
            theta = float(rng.uniform(0, math.pi))
            obstacles.append({"kind": "box", "x": x, "y": y, "w": w, "h": h, "theta": theta})
    occlusions: list[dict[str, Any]] = []
    if mode != "none":
        occ: dict[str, Any] = {
            "robot": "tb1",
            "mode": mode,
            "t_start": float(rng.uniform(3.0, 10.0)),
            "t_end": duration - 5.0,
            "start_angle": float(rng.uniform(-math.pi, math.pi)),
        }
        if mode == "sector":
            occ["width"] = float(rng.uniform(0.5, 2.0))
        elif mode == "arcs":
            occ["arcs"] = [
                {"start_angle": float(rng.uniform(-math.pi, math.pi)), "width": float(w)}
                for w in rng.uniform(0.3, 1.0, size=2)
            ]
        elif mode == "random":
            occ["period"] = 6.0
        occlusions.append(occ)
    world = {
        "seed": seed,
        "room": {"width": 10.0, "height": 8.0},
        "obstacles": obstacles,
        "robots": [
            {
                "name": "tb1",
                "start": {"x": 1.0, "y": 1.0, "theta": 0.0},
                "route": [{"x": x, "y": y} for x, y in ROUTE],
            }
        ],
        "lidar": {"noise_std": 0.005},
        "occlusions": occlusions,
    }
    return mode, msgspec.convert(world, WorldSpec)


def covers_front(world: WorldSpec, within: float = math.radians(30)) -> bool:
    """Does the occlusion hide any beam within ``within`` rad of straight ahead when it
    starts?"""
    if not world.occlusions:
        return False
    lidar = world.lidar
    angles = lidar.angle_min + np.arange(lidar.beams, dtype=np.float64) * lidar.angle_increment
    t = world.occlusions[0].t_start
    mask = occlusion_mask(world.occlusions, world.robots[0].name, t, angles, world.seed)
    signed = np.pi - np.mod(np.pi - angles, 2 * np.pi)
    return bool((mask & (np.abs(signed) < within)).any())


def _p(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q, method="inverted_cdf")) if values else None


def aggregate(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The figures of "What working means" over ``runs``."""
    occl = [r for r in runs if r["mode"] != "none"]
    onsets = sum(r["loop"]["occlusion_onsets"] for r in occl)
    detected = sum(r["loop"]["detected_onsets"] for r in occl)
    latencies = [
        float(r["loop"]["detection_latency_scans"]["max"])
        for r in occl
        if r["loop"]["detected_onsets"]
    ]
    to_robot = [
        r["loop"]["anomaly_to_robot_ms"]["p50"]
        for r in runs
        if r["loop"]["anomaly_to_robot_ms"]["p50"] is not None
    ]
    loop_p50 = [
        r["loop"]["loop_latency_ms"]["p50"]
        for r in runs
        if r["loop"]["loop_latency_ms"]["p50"] is not None
    ]

    def side(k: str, rs: list[dict[str, Any]]) -> dict[str, Any]:
        return {
            "collisions": sum(r[k]["collisions"] for r in rs),
            "runs_with_collisions": sum(1 for r in rs if r[k]["collisions"]),
            "routes_completed": sum(1 for r in rs if r[k]["route_completed"]),
            "waypoints_reached": sum(r[k]["waypoints_reached"] for r in rs),
        }

    by_mode = {
        m: {"runs": len(rs), "loop": side("loop", rs), "no_loop": side("no_loop", rs)}
        for m in MODES
        if (rs := [r for r in runs if r["mode"] == m])
    }
    front = [r for r in runs if r["front"]]
    return {
        "runs": len(runs),
        "occlusion_runs": len(occl),
        "front_blind_runs": len(front),
        "occlusion_onsets": onsets,
        "detection_rate": detected / onsets if onsets else None,
        "detection_latency_scans": {"p50": _p(latencies, 50), "max": max(latencies, default=None)},
        "false_anomalies": sum(r["loop"]["false_anomalies"] for r in runs),
        "overreaching_masks": sum(r["loop"]["overreaching_masks"] for r in runs),
        "false_anomalies_obstacle_only": sum(
            r["loop"]["anomalies"] for r in runs if r["mode"] == "none"
        ),
        "anomaly_to_robot_ms_p50": {"p50": _p(to_robot, 50), "max": max(to_robot, default=None)},
        "loop_latency_ms_p50": {"p50": _p(loop_p50, 50), "max": max(loop_p50, default=None)},
        "lockstep_timeouts": sum(r["loop"].get("lockstep_timeouts", 0) for r in runs),
        "loop": side("loop", runs),
        "no_loop": side("no_loop", runs),
        "front_blind": {"loop": side("loop", front), "no_loop": side("no_loop", front)},
        "by_mode": by_mode,
    }


def _table(agg: dict[str, Any]) -> str:
    lo, no = agg["loop"], agg["no_loop"]
    rate = agg["detection_rate"]
    lines = [
        "",
        f"lidar-occlusion evaluation: {agg['runs']} runs ({agg['occlusion_runs']} with occlusion)",
        f"  detection rate          {'-' if rate is None else f'{rate:.1%}'} of "
        f"{agg['occlusion_onsets']} onsets; latency p50 "
        f"{agg['detection_latency_scans']['p50']} scans, "
        f"max {agg['detection_latency_scans']['max']}",
        f"  false anomalies         {agg['false_anomalies']} "
        f"({agg['false_anomalies_obstacle_only']} in obstacle-only runs); "
        f"{agg['overreaching_masks']} masks claimed > pi/48 beyond a real occlusion",
        f"  anomaly -> plan at robot p50 of run p50s {agg['anomaly_to_robot_ms_p50']['p50']} ms",
        "",
        f"  {'':24}{'with loop':>12}{'without':>12}",
        f"  {'collisions':24}{lo['collisions']:>12}{no['collisions']:>12}",
        f"  {'runs with a collision':24}{lo['runs_with_collisions']:>12}"
        f"{no['runs_with_collisions']:>12}",
        f"  {'routes completed':24}{lo['routes_completed']:>12}{no['routes_completed']:>12}",
        f"  {'waypoints reached':24}{lo['waypoints_reached']:>12}{no['waypoints_reached']:>12}",
        f"  {'front-blind runs':24}{agg['front_blind_runs']:>12}",
        f"  {'  collisions':24}{agg['front_blind']['loop']['collisions']:>12}"
        f"{agg['front_blind']['no_loop']['collisions']:>12}",
        "",
        f"  {'mode':10}{'runs':>6}{'collisions loop/no':>22}{'completed loop/no':>20}",
    ]
    for m, d in agg["by_mode"].items():
        lines.append(
            f"  {m:10}{d['runs']:>6}"
            f"{d['loop']['collisions']:>14} / {d['no_loop']['collisions']:<5}"
            f"{d['loop']['routes_completed']:>12} / {d['no_loop']['routes_completed']:<5}"
        )
    return "\n".join(lines)


async def _run(runs: int, seed: int, duration: float) -> list[dict[str, Any]]:
    out: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    for i in range(runs):
        s = seed + i
        mode, world = scenario(s, duration)
        with_loop = await run_in_process(world, loop=True, duration=duration)
        without = await run_in_process(world, loop=False, duration=duration)
        front = covers_front(world)
        out.append({"seed": s, "mode": mode, "front": front, "loop": with_loop, "no_loop": without})
        print(
            f"[{time.perf_counter() - t0:6.1f} s] run {i + 1}/{runs} seed {s} {mode:7}"
            f"{' front' if front else '      '} "
            f"anomalies {with_loop['anomalies']:3}  collisions {with_loop['collisions']} "
            f"with loop, {without['collisions']} without  waypoints "
            f"{with_loop['waypoints_reached']} / {without['waypoints_reached']}",
            flush=True,
        )
    return out


@cli.command()
def main(
    runs: Annotated[int, typer.Option(help="Scenarios.", min=1)] = 20,
    seed: Annotated[int, typer.Option(help="Seed of the first scenario.")] = 1,
    duration: Annotated[float, typer.Option(help="Sim seconds per run.", min=20)] = 200.0,
    out: Annotated[Path, typer.Option(help="Output directory.")] = Path("out/eval"),
) -> None:
    """Run the evaluation and write <out>/lidar_occlusion.json."""
    results = anyio.run(_run, runs, seed, duration)
    agg = aggregate(results)
    out.mkdir(parents=True, exist_ok=True)
    doc = {"runs": runs, "seed": seed, "duration": duration, "aggregate": agg, "results": results}
    (out / "lidar_occlusion.json").write_text(json.dumps(doc, indent=2) + "\n")
    print(_table(agg), flush=True)
    print(f"\n  written {out / 'lidar_occlusion.json'}", flush=True)


if __name__ == "__main__":
    run_cli(cli)
