"""``make eval``: does the loop help, and which planner costs least? N seeded scenarios,
each run in five configurations.

    python -m lidar_occlusion.eval --runs 20 --seed 1 [--duration 200] [--out out/eval]
        [--configurations no_loop,reference,...] [--jobs 2]

A scenario (:func:`scenario`) is a 10 x 8 m room with the robot driving a rectangular
route; 2 to 5 obstacles, half of them on the route; one occlusion, its mode taking turns
(``sector``, ``arcs``, ``global``, ``random``, then none at all: the obstacle-only runs,
where every anomaly is a false one), at a random angle, from a random start to 5 s
before the end. Runs whose occlusion covers the robot's front (within 30 degrees of
straight ahead) when it starts are reported apart as well: there an unhandled occlusion
hides what the robot drives into.

Each scenario runs, from the same seed, in lockstep, in every configuration
(:data:`CONFIGURATIONS`): no loop; the reference planner; the reference planner with the
twin-backed Legitimate stage; the lookahead planner; the lookahead planner with the twin.
The loop's nodes come from :func:`lidar_occlusion.nodes.build` with the settings of
:func:`configuration`. ``--jobs`` worker processes (``python -m lidar_occlusion.eval
--worker SEEDS``, one JSON line per scenario on stdout) share the scenarios; the figures
do not depend on it.

Writes ``<out>/lidar_occlusion.json`` - the aggregate (its ``loop`` and ``no_loop``
figures are the reference planner's and the no-loop run's; ``configurations`` has every
configuration's) and every run - and prints a side-by-side table.
"""

from __future__ import annotations

import json
import logging
import math
import sys
import time
from pathlib import Path
from typing import Annotated, Any

import anyio
import msgspec
import numpy as np
import typer
from rap_sdk import Node
from rap_sdk.entry import EntryError, run_cli
from sim_world.occlusion import occlusion_mask
from sim_world.world import WorldSpec

from .nodes import MonitorConfig, build
from .planning import LegitimacyConfig, PlanConfig
from .scenario import run_in_process

__all__ = [
    "CONFIGURATIONS",
    "MODES",
    "TWIN_CODES",
    "aggregate",
    "configuration",
    "run_scenario",
    "scenario",
    "twin_rejections",
]

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


CONFIGURATIONS: dict[str, tuple[str | None, bool]] = {
    "no_loop": (None, False),
    "reference": ("reference", False),
    "reference_twin": ("reference", True),
    "lookahead": ("lookahead", False),
    "lookahead_twin": ("lookahead", True),
}
"""Name -> (planner, or None for no loop at all; the twin-backed Legitimate stage?)."""
LABELS = {
    "no_loop": "no loop",
    "reference": "reference",
    "reference_twin": "ref + twin",
    "lookahead": "lookahead",
    "lookahead_twin": "look + twin",
}
TWIN_CODES = ("belief", "limits", "collision", "clearance", "pose-mismatch")
"""The reject codes of the twin (:mod:`lidar_occlusion.twin`); ``spec:<output>`` too."""
GOAL_ROUTES = 0.95
"""The goal: no collision, and routes completed within 5 % of the no-loop run."""


def configuration(name: str) -> tuple[PlanConfig, LegitimacyConfig]:
    """The loop's settings in configuration ``name`` (one of :data:`CONFIGURATIONS`
    but ``no_loop``), for the scenarios' route: ``build(robot, planning=...,
    legitimacy=...)`` makes its nodes."""
    if name not in CONFIGURATIONS or CONFIGURATIONS[name][0] is None:
        loops = ", ".join(n for n, (p, _) in CONFIGURATIONS.items() if p is not None)
        raise ValueError(f"no loop configuration {name!r}: choose from {loops}")
    planner, twin = CONFIGURATIONS[name]
    route = {"route": ROUTE, "loop_route": False}  # every scenario's robot drives ROUTE once
    planning = msgspec.convert({"planner": planner, **route}, PlanConfig)
    if not twin:
        return planning, LegitimacyConfig()
    return planning, msgspec.convert({"twin": True, **route}, LegitimacyConfig)


def _nodes(name: str, robot: str) -> list[Node]:
    planning, legitimacy = configuration(name)
    monitoring = MonitorConfig(belief=legitimacy.twin)  # the twin reads the obstacle map
    return build(robot, monitoring=monitoring, planning=planning, legitimacy=legitimacy).nodes


def twin_rejections(codes: dict[str, int]) -> int:
    """Rejections whose reason starts with a twin finding code (``collision: ...``)."""
    return sum(n for c, n in codes.items() if c in TWIN_CODES or c.startswith("spec:"))


async def run_scenario(seed: int, duration: float, names: list[str]) -> dict[str, Any]:
    """Scenario ``seed`` in each configuration of ``names``: one entry of ``results``."""
    mode, world = scenario(seed, duration)
    robot = world.robots[0].name
    runs: dict[str, dict[str, Any]] = {}
    for name in names:
        if CONFIGURATIONS[name][0] is None:
            runs[name] = await run_in_process(world, loop=False, duration=duration)
        else:
            runs[name] = await run_in_process(world, duration=duration, nodes=_nodes(name, robot))
    entry: dict[str, Any] = {"seed": seed, "mode": mode, "front": covers_front(world)}
    if "reference" in runs:
        entry["loop"] = runs["reference"]
    if "no_loop" in runs:
        entry["no_loop"] = runs["no_loop"]
    entry["configurations"] = runs
    return entry


def _side(k: str, rs: list[dict[str, Any]]) -> dict[str, Any]:
    return {
        "collisions": sum(r[k]["collisions"] for r in rs),
        "runs_with_collisions": sum(1 for r in rs if r[k]["collisions"]),
        "routes_completed": sum(1 for r in rs if r[k]["route_completed"]),
        "waypoints_reached": sum(r[k]["waypoints_reached"] for r in rs),
    }


def _configuration(name: str, runs: list[dict[str, Any]]) -> dict[str, Any]:
    ms = [r["configurations"][name] for r in runs]
    front = [r["configurations"][name] for r in runs if r["front"]]
    codes: dict[str, int] = {}
    for m in ms:
        for c, n in m.get("rejections", {}).items():
            codes[c] = codes.get(c, 0) + n
    return {
        "collisions": sum(m["collisions"] for m in ms),
        "runs_with_collisions": sum(1 for m in ms if m["collisions"]),
        "routes_completed": sum(1 for m in ms if m["route_completed"]),
        "waypoints_reached": sum(m["waypoints_reached"] for m in ms),
        "spin_s": round(sum(m.get("spin_s", 0.0) for m in ms), 1),
        "plans_proposed": sum(m["plans_proposed"] for m in ms),
        "plans_rejected": sum(m["plans_rejected"] for m in ms),
        "plans_rejected_twin": twin_rejections(codes),
        "rejections": codes,
        "front_blind_collisions": sum(m["collisions"] for m in front),
        "by_mode": {
            mode: {
                "collisions": sum(r["configurations"][name]["collisions"] for r in rs),
                "routes_completed": sum(
                    1 for r in rs if r["configurations"][name]["route_completed"]
                ),
            }
            for mode in MODES
            if (rs := [r for r in runs if r["mode"] == mode])
        },
    }


def aggregate(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The figures of "What working means" over ``runs``: detection from the reference
    planner's runs (``loop``), ``loop`` / ``no_loop`` as before, and ``configurations``
    side by side with whether each meets the goal."""
    names = [n for n in CONFIGURATIONS if runs and all(n in r["configurations"] for r in runs)]
    configs = {n: _configuration(n, runs) for n in names}
    if "no_loop" in configs:
        floor = GOAL_ROUTES * configs["no_loop"]["routes_completed"]
        for c in configs.values():
            c["meets_goal"] = c["collisions"] == 0 and c["routes_completed"] >= floor - 1e-9
    out: dict[str, Any] = {
        "runs": len(runs),
        "occlusion_runs": sum(1 for r in runs if r["mode"] != "none"),
        "front_blind_runs": sum(1 for r in runs if r["front"]),
        "goal": "0 collisions and routes completed >= 95 % of the no-loop run's",
    }
    if runs and all("loop" in r for r in runs):
        out.update(_detection(runs))
    legacy = [k for k in ("loop", "no_loop") if runs and all(k in r for r in runs)]
    for k in legacy:
        out[k] = _side(k, runs)
    front = [r for r in runs if r["front"]]
    out["front_blind"] = {k: _side(k, front) for k in legacy}
    out["by_mode"] = {
        m: {"runs": len(rs), **{k: _side(k, rs) for k in legacy}}
        for m in MODES
        if (rs := [r for r in runs if r["mode"] == m])
    }
    out["configurations"] = configs
    return out


def _detection(runs: list[dict[str, Any]]) -> dict[str, Any]:
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
    return {
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
    }


def table(agg: dict[str, Any]) -> str:
    """The aggregate for a person: detection, then the configurations side by side."""
    lines = [
        "",
        f"lidar-occlusion evaluation: {agg['runs']} runs "
        f"({agg['occlusion_runs']} with occlusion, {agg['front_blind_runs']} front-blind)",
    ]
    if "detection_rate" in agg:
        rate = agg["detection_rate"]
        lines += [
            f"  detection rate          {'-' if rate is None else f'{rate:.1%}'} of "
            f"{agg['occlusion_onsets']} onsets; latency p50 "
            f"{agg['detection_latency_scans']['p50']} scans, "
            f"max {agg['detection_latency_scans']['max']}",
            f"  false anomalies         {agg['false_anomalies']} "
            f"({agg['false_anomalies_obstacle_only']} in obstacle-only runs); "
            f"{agg['overreaching_masks']} masks claimed > pi/48 beyond a real occlusion",
            f"  anomaly -> plan at robot p50 of run p50s "
            f"{agg['anomaly_to_robot_ms_p50']['p50']} ms",
        ]
    configs: dict[str, dict[str, Any]] = agg["configurations"]
    names = list(configs)
    w = 13
    lines += ["", f"  {'':26}" + "".join(f"{LABELS[n]:>{w}}" for n in names)]
    rows = [
        ("collisions", "collisions"),
        ("runs with a collision", "runs_with_collisions"),
        ("routes completed", "routes_completed"),
        ("waypoints reached", "waypoints_reached"),
        ("time spinning (s)", "spin_s"),
        ("plans proposed", "plans_proposed"),
        ("plans rejected", "plans_rejected"),
        ("  by the twin", "plans_rejected_twin"),
        ("front-blind collisions", "front_blind_collisions"),
    ]
    for label, key in rows:
        cells = "".join(f"{configs[n][key]!s:>{w}}" for n in names)
        lines.append(f"  {label:26}{cells}")
    if all("meets_goal" in configs[n] for n in names):
        cells = "".join(f"{'yes' if configs[n]['meets_goal'] else 'no':>{w}}" for n in names)
        lines.append(f"  {'meets the goal (*)':26}{cells}")
        lines.append(f"  (*) {agg['goal']}")
    lines += ["", f"  {'collisions / routes':26}" + "".join(f"{LABELS[n]:>{w}}" for n in names)]
    for mode in MODES:
        if mode not in agg["by_mode"]:
            continue
        cells = "".join(
            f"{configs[n]['by_mode'][mode]['collisions']:>{w - 5}} / "
            f"{configs[n]['by_mode'][mode]['routes_completed']:<2}"
            for n in names
        )
        lines.append(f"  {mode + ' (' + str(agg['by_mode'][mode]['runs']) + ')':26}{cells}")
    return "\n".join(lines)


def _progress(entry: dict[str, Any], done: int, runs: int, t0: float) -> None:
    cells = "  ".join(
        f"{LABELS[n]} {m['collisions']}c {m['waypoints_reached']}wp {m.get('spin_s', 0.0):.0f}s"
        for n, m in entry["configurations"].items()
    )
    print(
        f"[{time.perf_counter() - t0:6.1f} s] run {done}/{runs} seed {entry['seed']} "
        f"{entry['mode']:7}{' front' if entry['front'] else '      '}  {cells}",
        flush=True,
    )


async def _in_process(seeds: list[int], duration: float, names: list[str]) -> list[dict[str, Any]]:
    out: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    for s in seeds:
        out.append(await run_scenario(s, duration, names))
        _progress(out[-1], len(out), len(seeds), t0)
    return out


async def _workers(
    seeds: list[int], duration: float, names: list[str], jobs: int
) -> list[dict[str, Any]]:
    """The scenarios shared among ``jobs`` worker processes (every ``jobs``-th each)."""
    got: dict[int, dict[str, Any]] = {}
    failed: list[str] = []
    t0 = time.perf_counter()

    async def work(part: list[int]) -> None:
        cmd = [
            sys.executable,
            "-m",
            "lidar_occlusion.eval",
            "--worker",
            ",".join(map(str, part)),
            "--duration",
            repr(duration),
            "--configurations",
            ",".join(names),
        ]
        async with await anyio.open_process(cmd, stdin=None, stderr=None) as proc:
            assert proc.stdout is not None
            buf = b""
            async for chunk in proc.stdout:
                *lines, buf = (buf + chunk).split(b"\n")
                for line in lines:
                    if line.startswith(b"{"):
                        entry = json.loads(line)
                        got[entry["seed"]] = entry
                        _progress(entry, len(got), len(seeds), t0)
            code = await proc.wait()
        if code != 0:
            failed.append(f"the worker for seeds {part[0]}.. exited with {code}")

    async with anyio.create_task_group() as tg:
        for i in range(jobs):
            tg.start_soon(work, seeds[i::jobs])
    missing = [s for s in seeds if s not in got]
    if failed or missing:
        raise EntryError(
            f"{'; '.join(failed) or 'a worker stopped early'} (seeds without a result: "
            f"{missing}); its log is above - run with --jobs 1 to see it in this process",
            1,
        )
    return [got[s] for s in seeds]


def _names(text: str) -> list[str]:
    names = [n.strip() for n in text.split(",") if n.strip()]
    bad = [n for n in names if n not in CONFIGURATIONS]
    if bad or not names:
        raise typer.BadParameter(
            f"{bad or 'none given'}: choose from {', '.join(CONFIGURATIONS)}",
            param_hint="--configurations",
        )
    return [n for n in CONFIGURATIONS if n in names]  # in the table's order


@cli.command()
def main(
    runs: Annotated[int, typer.Option(help="Scenarios.", min=1)] = 20,
    seed: Annotated[int, typer.Option(help="Seed of the first scenario.")] = 1,
    duration: Annotated[float, typer.Option(help="Sim seconds per run.", min=20)] = 200.0,
    out: Annotated[Path, typer.Option(help="Output directory.")] = Path("out/eval"),
    configurations: Annotated[
        str,
        typer.Option(help=f"Comma-separated, of: {', '.join(CONFIGURATIONS)}."),
    ] = ",".join(CONFIGURATIONS),
    jobs: Annotated[
        int, typer.Option(help="Worker processes sharing the scenarios (1: this one).", min=1)
    ] = 2,
    worker: Annotated[
        str, typer.Option(hidden=True, help="Run these seeds here; JSON lines on stdout.")
    ] = "",
) -> None:
    """Run the evaluation and write <out>/lidar_occlusion.json."""
    if not math.isfinite(duration):
        raise typer.BadParameter(f"{duration}: give a number of seconds", param_hint="--duration")
    names = _names(configurations)
    # the stages' own lines (a plan rejected by the twin, given up on) are counted in the
    # figures; only what goes wrong is printed
    logging.basicConfig(level=logging.ERROR, format="%(levelname)s %(name)s: %(message)s")
    if worker:
        for entry_seed in (int(s) for s in worker.split(",")):
            entry = anyio.run(run_scenario, entry_seed, duration, names)
            sys.stdout.write(json.dumps(entry) + "\n")
            sys.stdout.flush()
        return
    seeds = list(range(seed, seed + runs))
    began = time.perf_counter()
    if min(jobs, runs) > 1:
        results = anyio.run(_workers, seeds, duration, names, min(jobs, runs))
    else:
        results = anyio.run(_in_process, seeds, duration, names)
    wall = time.perf_counter() - began
    agg = aggregate(results)
    out.mkdir(parents=True, exist_ok=True)
    doc = {
        "runs": runs,
        "seed": seed,
        "duration": duration,
        "configurations": names,
        "jobs": min(jobs, runs),
        "wall_s": round(wall, 1),
        "aggregate": agg,
        "results": results,
    }
    (out / "lidar_occlusion.json").write_text(json.dumps(doc, indent=2) + "\n")
    print(table(agg), flush=True)
    print(
        f"\n  {wall:.0f} s with {min(jobs, runs)} job(s); written {out / 'lidar_occlusion.json'}",
        flush=True,
    )


if __name__ == "__main__":
    run_cli(cli)
