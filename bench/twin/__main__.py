"""``python -m bench.twin [--quick] [--report-only]``: the digital twin's figures in one
run, written to bench/results/twin.json and the twin section of docs/benchmarks.md;
exits 1 when a budget is missed.

The default world runs in the simulator (lockstep); the robot's belief is built as the
loop would build it (``lidar_occlusion.belief.update`` on every scan and odometry pose,
the analysis's mask). Every 8 s of sim time, from the belief of that moment, the twin
rolls out three plans over one period (8 s): nominal navigation (an empty plan), the
reference planner's plan for the current mask, and a full turn; each is timed
``reps`` times, interleaved with the baselines of the same moment:

- the simulator itself over the same 8 s (``Simulation.step`` x 400, scans included:
  what the twin replaces), timed as the run goes on;
- the twin on an empty map from the same pose (what the rollout costs with nothing to
  raycast against: the floor);
- the twin without its trust spec.

Accuracy: the nominal rollout's end pose against where the simulator's robot is 8 s
later when no plan was sent (the simulator continues on nominal navigation).

Budget (checked): the twin at least 2x faster than the simulator over the same 8 s
(median rollout against median simulator 8 s). Ratios only; no absolute timing is
asserted.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
from lidar_occlusion.analysis import AnalysisConfig, MaskWindow, analyse_scan, to_message
from lidar_occlusion.belief import MapConfig, ObstacleMap, belief_of, update
from lidar_occlusion.planning import PlanConfig, plan_for
from lidar_occlusion.twin import LidarTwin, TwinConfig
from rap_schemas import SpinCommand, SpinPlan
from sim_world.sim import Simulation
from sim_world.world import default_world_path, load_world

from ..report import hardware_line, run_suite, summary_us, table

BUDGETS = {"simulator_8s_over_twin_rollout": 2.0}
PERIOD = 8.0
PLANS = ("nominal", "reference", "full turn")


def measure(quick: bool) -> dict[str, Any]:
    world = load_world(default_world_path("default"))
    sim = Simulation(world)
    robot = world.robots[0]
    route = [(p.x, p.y) for p in robot.route]
    reps = 5 if quick else 15
    windows = 6 if quick else 20
    twin, bare = LidarTwin(), LidarTwin(TwinConfig(trust=False))
    full_turn = SpinPlan(commands=[SpinCommand(omega=1.0, duration=2 * math.pi)], period=PERIOD)
    cfg, acfg = MapConfig(), AnalysisConfig()
    window = MaskWindow(acfg.window)
    m: ObstacleMap | None = None
    sim_ns: list[int] = []
    update_ns: list[int] = []
    rollout: dict[str, list[int]] = {p: [] for p in PLANS}
    empty_ns: list[int] = []
    no_spec_ns: list[int] = []
    errors: list[float] = []
    cells: list[int] = []
    sizes: list[int] = []
    steps = round(PERIOD / sim.dt)
    pending: tuple[float, float] | None = None
    for _ in range(windows):
        spent = 0
        events = []
        for _ in range(steps):
            t0 = time.perf_counter_ns()
            new = sim.step()
            spent += time.perf_counter_ns() - t0
            for ev in new:  # the odometry pose of the step that took the scan
                t0 = time.perf_counter_ns()
                m = update(m, ev.scan, sim.odometry(robot.name).pose, ev.t, cfg)
                update_ns.append(time.perf_counter_ns() - t0)
                occluded = analyse_scan(ev.scan, window, acfg)
            events += new
        sim_ns.append(spent)
        here = sim.robots[robot.name].pose
        if pending is not None:
            errors.append(math.hypot(pending[0] - here.x, pending[1] - here.y))
        assert m is not None
        last = events[-1].scan
        mask = to_message(occluded, last)
        b = belief_of(
            robot.name,
            sim.odometry(robot.name),
            last,
            m,
            mask,
            route,
            waypoint=sim.robots[robot.name].nav.index,
            loop_route=robot.loop_route,
        )
        cells.append(m.size)
        sizes.append(len(m.cells) + 2 * len(m.seen_age) + len(m.looked) + len(m.looked_age))
        plans = {
            "nominal": SpinPlan(commands=[], period=PERIOD),
            "reference": plan_for(occluded, last.angle_min, last.angle_increment, PlanConfig()),
            "full turn": full_turn,
        }
        empty = b.__class__(**{**_fields(b), "map": ObstacleMap()})
        for _ in range(reps):  # interleaved: drift hits all alike
            for name, plan in plans.items():
                t0 = time.perf_counter_ns()
                twin.rollout(plan, b)
                rollout[name].append(time.perf_counter_ns() - t0)
            t0 = time.perf_counter_ns()
            twin.rollout(plans["nominal"], empty)
            empty_ns.append(time.perf_counter_ns() - t0)
            t0 = time.perf_counter_ns()
            bare.rollout(plans["nominal"], b)
            no_spec_ns.append(time.perf_counter_ns() - t0)
        report = twin.rollout(plans["nominal"], b)
        pending = (report.metrics["end_x_m"], report.metrics["end_y_m"])
    all_rollouts = [x for p in PLANS for x in rollout[p]]
    m_out: dict[str, Any] = {
        f"twin rollout, {name} (8 s)": summary_us(rollout[name]) for name in PLANS
    }
    m_out["twin rollout, all plans (8 s)"] = summary_us(all_rollouts)
    m_out["twin rollout, empty map (8 s)"] = summary_us(empty_ns)
    m_out["twin rollout, nominal, no trust spec (8 s)"] = summary_us(no_spec_ns)
    m_out["simulator, 8 s in lockstep"] = summary_us(sim_ns)
    m_out["map update, per scan"] = summary_us(update_ns)
    m_out["map"] = {
        "obstacle_cells_p50": int(np.median(cells)),
        "obstacle_cells_max": int(max(cells)),
        "bytes_p50": int(np.median(sizes)),
        "bytes_max": int(max(sizes)),
    }
    m_out["prediction_error_m"] = {
        "p50": round(float(np.median(errors)), 3),
        "max": round(float(max(errors)), 3),
        "n": len(errors),
    }
    m_out["setup"] = {
        "world": "default",
        "windows": windows,
        "reps": reps,
        "twin_beams": TwinConfig().beams,
        "twin_step_s": TwinConfig().step,
        "twin_scan_hz": TwinConfig().scan_hz,
    }
    return m_out


def _fields(b: Any) -> dict[str, Any]:
    return {f: getattr(b, f) for f in b.__struct_fields__}


def verdicts(m: dict[str, Any]) -> dict[str, Any]:
    twin = m["twin rollout, all plans (8 s)"]["p50_us"]
    sim = m["simulator, 8 s in lockstep"]["p50_us"]
    empty = m["twin rollout, empty map (8 s)"]["p50_us"]
    out = {
        "simulator_8s_over_twin_rollout": {
            "value": round(sim / twin, 1),
            "budget": BUDGETS["simulator_8s_over_twin_rollout"],
            "ok": sim / twin >= BUDGETS["simulator_8s_over_twin_rollout"],
        },
        "twin_rollout_over_empty_map": {
            "value": round(twin / empty, 2),
            "budget": "-",
            "ok": True,
            "checked": False,
        },
    }
    return out


def render(m: dict[str, Any], v: dict[str, Any], hw: dict[str, Any]) -> str:
    rows = [
        [k, s["p50_us"], s["p99_us"], s["n"]]
        for k, s in m.items()
        if isinstance(s, dict) and "p50_us" in s
    ]
    mp, err, st = m["map"], m["prediction_error_m"], m["setup"]
    return "\n".join(
        [
            "## Digital twin of the lidar case (`make bench-twin`)",
            "",
            f"Hardware: {hardware_line(hw)}",
            "",
            f"The default world in lockstep; every 8 s of sim time ({st['windows']} times) "
            "the robot's belief of that moment (the map built from every scan and "
            "odometry pose, the analysis's mask) is rolled out over one plan period "
            f"(8 s; the twin: {st['twin_beams']} beams, {st['twin_scan_hz']} Hz scans, "
            f"{st['twin_step_s']} s steps) for three plans, {st['reps']} times each, "
            "interleaved with the baselines: the simulator over the same 8 s (400 physics "
            "steps, 40 scans of 360 beams: what the twin stands in for) and the twin on "
            "an empty map from the same pose.",
            "",
            table(["what", "p50 µs", "p99 µs", "n"], rows),
            "",
            f"The map: {mp['obstacle_cells_p50']} obstacle cells at the median "
            f"({mp['obstacle_cells_max']} at most), {mp['bytes_p50']} bytes of cells and "
            f"ages ({mp['bytes_max']} at most). Prediction: the nominal rollout's end "
            "pose lies "
            f"{err['p50']} m (median; {err['max']} m at most, n = {err['n']}) from where "
            "the simulator's robot is 8 s later (occlusion in force part of the time).",
            "",
            "Ratios (the budget is checked, the floor only reported):",
            "",
            table(
                ["ratio", "measured", "minimum", ""],
                [
                    [
                        k,
                        x["value"],
                        x["budget"],
                        ("ok" if x["ok"] else "MISSED") if x.get("checked", True) else "reported",
                    ]
                    for k, x in v.items()
                ],
            ),
        ]
    )


def main() -> int:
    return run_suite("twin", measure, verdicts, render)


if __name__ == "__main__":
    raise SystemExit(main())
