"""``make demo``: the lidar-occlusion loop end to end, on embedded defaults.

Three kinds of processes on loopback Zenoh: this one (sim_world in lockstep with the
loop, the observer, Rerun logging), the knowledge service (memory backend) and one
``maplek_runner`` per compute node of the plan (by default the case's system model,
``examples/lidar_occlusion/model.yaml``: the five MAPLE-K nodes in one runner). Prints
a summary and writes ``<out>/summary.json`` and ``<out>/demo.rrd``; exits 1 when the
loop did not close (no anomaly, or no plan reached the robot), 2 on bad input.
"""

from __future__ import annotations

import json
import logging
import time
from functools import partial
from importlib import resources
from pathlib import Path
from typing import Annotated, Any

import anyio
import typer
from rap_schemas import PlanError, load_plan
from rap_sdk import ZenohConfig, ZenohFabric
from rap_sdk.cycles import CycleTracker, Topology
from rap_sdk.entry import fail, run_cli, setup_logging
from rap_sdk.fabric import free_port
from sim_world.service import SimService
from sim_world.sim import Simulation
from sim_world.viz import RerunLog
from sim_world.world import WorldError, WorldSpec, default_world_path, find_world, load_world

from .deploy import local_deployment, plan_nodes
from .scenario import Observer, metrics

__all__ = ["default_plan_path", "main", "run_demo"]

log = logging.getLogger("lidar_occlusion.demo")
cli = typer.Typer(add_completion=False, help=__doc__)


MODEL = Path(__file__).resolve().parents[2] / "model.yaml"
"""The case's system model, ``examples/lidar_occlusion/model.yaml``: what the demo runs."""


def default_plan_path(name: str = "demo") -> Path:
    """The plan the demo runs by default (``demo``: the case's model) or a shipped plan
    (``five_processes``)."""
    if name == "demo":
        return MODEL
    return Path(str(resources.files("lidar_occlusion") / "plans" / f"{name}.yaml"))


def _say(msg: str, t0: float) -> None:
    print(f"[{time.perf_counter() - t0:6.2f} s] {msg}", flush=True)


async def run_demo(
    world: WorldSpec, plan: Path, out: Path, duration: float, rerun: bool = True
) -> dict[str, Any]:
    t0 = time.perf_counter()
    doc = load_plan(plan)
    system = doc.plan.system
    loop_nodes = plan_nodes(doc)
    viz = RerunLog(world, path=str(out / "demo.rrd"), application_id="rap_demo") if rerun else None
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    sim = Simulation(world)
    robot = world.robots[0].name
    obs = Observer(system, robot, rerun=viz)
    try:
        async with ZenohFabric(ZenohConfig(listen=[endpoint])) as fabric:
            _say(f"starting the knowledge service and {len(doc.plan.compute_nodes)} runner(s)", t0)
            async with local_deployment(plan, fabric=fabric, endpoint=endpoint, logs=out / "logs"):
                names = ", ".join(n.name for n in loop_nodes)
                _say(f"{len(loop_nodes)} MAPLE-K nodes alive: {names}", t0)
                service = SimService(
                    sim,
                    fabric=fabric,
                    system=system,
                    on_scan=obs.on_scan,
                    on_plan=obs.on_plan,
                    rerun=viz,
                )
                tracker = CycleTracker(Topology.of([*loop_nodes, service.node], system=system))
                service.sync = tracker
                async with anyio.create_task_group() as tg:
                    await tg.start(partial(tracker.follow, fabric=fabric))
                    await tg.start(partial(obs.follow, fabric=fabric))
                    _say(f"simulating {duration:g} s of sim time in lockstep with the loop", t0)
                    await service.run(duration)
                    tg.cancel_scope.cancel()
                _say(f"simulated; {len(obs.scans)} scans, stopping the processes", t0)
    finally:
        if viz is not None:
            viz.close()
    summary = metrics(obs, sim, tracker=tracker)
    summary["loop_closed"] = summary["anomalies"] > 0 and summary["plans_executed"] > 0
    summary["wall_seconds"] = round(time.perf_counter() - t0, 2)
    return summary


def _report(s: dict[str, Any], out: Path) -> str:
    def ms(d: dict[str, Any]) -> str:
        return "-" if d["p50"] is None else f"p50 {d['p50']:.2f} ms, p99 {d['p99']:.2f} ms"

    det = s["detection_latency_scans"]
    lines = [
        "",
        "lidar-occlusion demo",
        f"  scans                {s['scans']} ({s['sim_seconds']:g} s of sim time, "
        f"{s['wall_seconds']:g} s wall)",
        f"  occlusion onsets     {s['occlusion_onsets']}, detected {s['detected_onsets']}"
        + ("" if det["p50"] is None else f" after {det['p50']:g} scans (max {det['max']:g})"),
        f"  anomalies            {s['anomalies']} ({s['false_anomalies']} false)",
        f"  plans                {s['plans_proposed']} proposed, {s['plans_approved']} approved, "
        f"{s['plans_rejected']} rejected, {s['plans_executed']} executed",
        f"  loop latency         {ms(s['loop_latency_ms'])} (scan published -> plan at robot)",
        f"  collisions           {s['collisions']}",
        f"  route                {s['waypoints_reached']} waypoints reached, "
        f"{'completed' if s['route_completed'] else 'not completed'}",
        f"  loop closed          {'yes' if s['loop_closed'] else 'NO'}",
        f"  written              {out / 'summary.json'}, {out / 'demo.rrd'}",
    ]
    return "\n".join(lines)


@cli.command()
def main(
    out: Annotated[Path, typer.Option(help="Output directory.")] = Path("out/demo"),
    duration: Annotated[float, typer.Option(help="Seconds of sim time.")] = 60.0,
    plan: Annotated[
        Path | None,
        typer.Option(help="System model or plan (default: examples/lidar_occlusion/model.yaml)."),
    ] = None,
    world: Annotated[
        str | None, typer.Option(help="A shipped world's name or a world file (default: default).")
    ] = None,
    rerun: Annotated[bool, typer.Option(help="Write <out>/demo.rrd.")] = True,
    log_level: Annotated[str, typer.Option(help="Logging level.")] = "WARNING",
) -> None:
    """Run the lidar-occlusion loop end to end and summarise it."""
    setup_logging(log_level)
    if not 0 < duration <= 86_400:
        raise fail(f"--duration {duration}: give the seconds of sim time, 0 < s <= 86400")
    plan_path = plan or default_plan_path()
    try:
        spec = load_world(find_world(world) if world else default_world_path())
        load_plan(plan_path)
        out.mkdir(parents=True, exist_ok=True)
    except (WorldError, PlanError) as exc:
        raise fail(str(exc)) from None
    except OSError as exc:
        raise fail(f"--out {out}: cannot create it: {exc.strerror or exc}") from None
    summary = anyio.run(run_demo, spec, plan_path, out, duration, rerun)
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(_report(summary, out), flush=True)
    if not summary["loop_closed"]:
        raise typer.Exit(1)


if __name__ == "__main__":
    run_cli(cli)
