"""``make eval-ship``: does retraining online help, and does Legitimate keep bad models out?

    python -m ship_motion.eval --runs 5 --seed 1 [--out out/eval] [--rerun]

A scenario (:func:`scenario`) is the ship on its seeded route, calm for ``onset`` s, then a
seeded weather front (wind, current and waves) that ramps in over 60 s. The ship starts with
a data-driven model trained on a calm run of its own (another seed), pinned in the model
store. The whole system runs in one process per scenario (a fresh interpreter each, so no
state crosses runs): the ship simulator and its predictors, knowledge with its model store,
and the generated MAPLE-K nodes, on an in-memory fabric, in lockstep with the simulator.
Plan proposes the planted bad candidates (``--plant``) before each real one: Legitimate
must reject every one of them.

Measured per scenario, from what crossed the fabric and the simulator's ground truth:
the data-driven model's mean path error before the front, during it with the old model,
and after the retrained model is in use; sim seconds from the onset to the anomaly and to
the new model's first path; availability (samples with a path on the display, counting
fallbacks, over samples); candidates approved and rejected, planted ones among them.
Writes ``<out>/ship_motion.json`` and prints a table.
"""

from __future__ import annotations

import json
import logging
import subprocess
import sys
import time
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Annotated, Any

import anyio
import numpy as np
import typer
from rap_schemas import PlanProposal
from rap_sdk import Context, MemoryFabric, Node, NodeRuntime, run_nodes
from rap_sdk.cycles import CycleTracker, Topology
from rap_sdk.entry import run_cli
from rap_sdk.gate import NEW_PLAN
from rap_sdk.knowledge import KnowledgeClient

from . import messages
from .learn import train_onnx
from .loop import MODEL_NAME
from .physics import History, ScenarioSpec, scenario_from_seed, simulate
from .predict import PredictedPath, model_hash, path_error
from .service import ShipService

__all__ = ["PLANTS", "aggregate", "initial_model", "scenario", "table"]

cli = typer.Typer(add_completion=False, help=__doc__)

SYSTEM = "ship_motion"
PLANTS = ("reversed", "unchanged", "corrupt")
"""The bad candidates Plan can plant before a real one (see ship_motion.nodes.plan)."""
RAMP_S = 60.0


def scenario(seed: int, *, onset: float = 600.0, duration: float = 2400.0) -> ScenarioSpec:
    return scenario_from_seed(seed, onset_s=onset, ramp_s=RAMP_S, duration_s=duration)


def initial_model(seed: int) -> bytes:
    """The model the ship starts with: trained on a calm run of another seed."""
    calm = simulate(scenario_from_seed(seed + 10_000, onset_s=1e9, duration_s=900.0))
    return train_onnx(calm.between(0.0, 900.0))


@dataclass
class Observer:
    """The display and the evaluator: what crosses the fabric, with sim times."""

    display: dict[float, messages.PredictedPath] = field(default_factory=dict)
    learned: list[messages.PredictedPath] = field(default_factory=list)
    anomalies: list[float] = field(default_factory=list)
    proposals: list[messages.ModelPlan] = field(default_factory=list)
    verdicts: list[messages.Verdict] = field(default_factory=list)
    executed: list[messages.ActiveModel] = field(default_factory=list)

    def node(self) -> Node:
        node = Node("observer")

        @node.on_event("ship/predicted_path")
        async def path(ctx: Context, p: messages.PredictedPath) -> None:
            if p.fallback or p.predictor == messages.PredictorKind.DATA_DRIVEN:
                self.display.setdefault(p.t0, p)
            if p.predictor == messages.PredictorKind.DATA_DRIVEN:
                self.learned.append(p)

        @node.on_event("anomaly")
        async def anomaly(ctx: Context, a: messages.Anomaly) -> None:
            self.anomalies.append(a.t)

        @node.on_event(NEW_PLAN)
        async def proposal(ctx: Context, p: PlanProposal[messages.ModelPlan]) -> None:
            self.proposals.append(p.plan)

        @node.on_event("model-verdict")
        async def verdict(ctx: Context, v: messages.Verdict) -> None:
            self.verdicts.append(v)

        @node.on_data("ship/model")
        async def model(ctx: Context, m: messages.ActiveModel) -> None:
            self.executed.append(m)

        return node


def _errors(
    paths: list[messages.PredictedPath], truth: History, lo: float, hi: float
) -> float | None:
    values = []
    for p in paths:
        if not lo <= p.t0 < hi:
            continue
        ours = PredictedPath(predictor="data_driven", t0=p.t0, step=p.step, x=p.x, y=p.y, psi=p.psi)
        e = path_error(ours, truth)
        if e is not None:
            values.append(e)
    return round(float(np.mean(values)), 3) if values else None


async def _run(
    seed: int, plant: list[str], onset: float, duration: float, rerun: str | None
) -> dict[str, Any]:
    from knowledge.app import open_service  # the service is wired only where it is run
    from knowledge.config import HistoryRule, KnowledgeConfig

    from .nodes import analysis, execute, legitimate, monitor, plan, predictors

    spec = scenario(seed, onset=onset, duration=duration)
    first = initial_model(seed)
    plan.node.configure({"plant": plant, "seed": seed})
    obs = Observer()
    loop = [m.node for m in (monitor, analysis, plan, legitimate, execute)]
    ship = [predictors.node]
    viz = None
    if rerun is not None:
        from .viz import ShipRerun

        viz = ShipRerun(path=rerun, seed=seed)
    began = time.perf_counter()
    async with MemoryFabric() as fabric:
        kb_config = KnowledgeConfig(
            system=SYSTEM, history=[HistoryRule(pattern="**", max_count=int(duration) + 60)]
        )
        async with open_service(kb_config, fabric=fabric) as _svc:
            async with KnowledgeClient(fabric=fabric, system=SYSTEM, writer="eval") as kb:
                meta = await kb.put_model(MODEL_NAME, first, tags={"trained": "calm"})
                await kb.pin_model(MODEL_NAME, meta.version)
            # every node in lockstep, Plan's retraining too: the simulator waits for it, as
            # a ship in real time would hardly notice a training that takes a fraction of
            # its 1 s sample period (the eval runs hundreds of times faster than that)
            topo = Topology.of([*ship, *loop], system=SYSTEM)
            tracker = CycleTracker(topo)
            service = ShipService(spec, fabric=fabric, system=SYSTEM, sync=tracker)
            async with anyio.create_task_group() as tg:
                await tg.start(partial(tracker.follow, fabric=fabric))
                orun = NodeRuntime(obs.node(), fabric=fabric, system=SYSTEM)
                await tg.start(orun.run)
                async with run_nodes([*ship, *loop], fabric=fabric, system=SYSTEM):
                    await service.run()
                    # let a proposal in flight finish (its training reads history)
                    await anyio.sleep(0.5)
                orun.stop()
                tg.cancel_scope.cancel()
            async with KnowledgeClient(fabric=fabric, system=SYSTEM, writer="eval") as kb:
                versions, _pinned = await kb.list_models(MODEL_NAME)
    planted = {m.version for m in versions if "planted" in m.tags}
    wall = time.perf_counter() - began
    truth = History.from_states(service.states)
    if viz is not None:
        viz.log_run(truth, obs, onset=onset)
        viz.close()
    return _metrics(seed, spec, first, truth, obs, onset, wall, plant, planted, service.lost_cycles)


def _metrics(
    seed: int,
    spec: ScenarioSpec,
    first: bytes,
    truth: History,
    obs: Observer,
    onset: float,
    wall: float,
    plant: list[str],
    planted: set[int],
    lost: int,
) -> dict[str, Any]:
    first_hash = model_hash(first)
    end = spec.duration_s - 30.0  # paths that mature within the run
    old = [p for p in obs.learned if p.model_hash == first_hash]
    # the retrained model: the one in use at the end, from when it first served
    last = obs.learned[-1].model_hash if obs.learned else first_hash
    new = [p for p in obs.learned if p.model_hash == last and last != first_hash]
    switch = min((p.t0 for p in new), default=None)
    verdicts = {v.version: v for v in obs.verdicts}
    samples = [s.t for s in truth]
    shown = sum(1 for t in samples if t in obs.display)
    fallbacks = sum(1 for t in samples if t in obs.display and obs.display[t].fallback)
    anomaly = next((t for t in obs.anomalies if t >= onset), None)
    false_anomalies = sum(1 for t in obs.anomalies if t < onset)
    return {
        "seed": seed,
        "onset_s": onset,
        "duration_s": spec.duration_s,
        "wall_s": round(wall, 1),
        "error_before_m": _errors(old, truth, 60.0, onset),
        "error_during_old_m": _errors(
            old, truth, onset + RAMP_S, switch if switch is not None else end
        ),
        "error_after_new_m": _errors(new, truth, switch, end) if switch is not None else None,
        "onset_to_anomaly_s": None if anomaly is None else round(anomaly - onset, 1),
        "onset_to_new_model_s": None if switch is None else round(switch - onset, 1),
        "false_anomalies": false_anomalies,
        "samples": len(samples),
        "samples_with_display_path": shown,
        "samples_on_fallback": fallbacks,
        "availability": shown / len(samples) if samples else 0.0,
        "proposed": len(obs.proposals),
        "approved": sum(1 for v in obs.verdicts if v.approved),
        "rejected": sum(1 for v in obs.verdicts if not v.approved),
        "planted": len(planted),
        "planted_rejected": sum(1 for v in planted if v in verdicts and not verdicts[v].approved),
        "planted_kinds": plant,
        "executed_versions": [m.version for m in obs.executed],
        "planted_executed": sum(1 for m in obs.executed if m.version in planted),
        "reasons": [verdicts[v].reason for v in sorted(verdicts) if not verdicts[v].approved],
        "lost_cycles": lost,
        "anomalies_at": [round(t, 1) for t in obs.anomalies],
        "models_in_use": _in_use(obs.learned),
    }


def _in_use(paths: list[messages.PredictedPath]) -> list[dict[str, Any]]:
    """When each model version first served a path (sim time)."""
    seen: dict[int, float] = {}
    for p in paths:
        seen.setdefault(p.model_version, p.t0)
    return [{"version": v, "from_t": t} for v, t in seen.items()]


def _mean(values: list[float | None]) -> float | None:
    got = [v for v in values if v is not None]
    return round(float(np.mean(got)), 3) if got else None


def aggregate(runs: list[dict[str, Any]]) -> dict[str, Any]:
    def col(k: str) -> list[Any]:
        return [r[k] for r in runs]

    return {
        "runs": len(runs),
        "error_before_m": _mean(col("error_before_m")),
        "error_during_old_m": _mean(col("error_during_old_m")),
        "error_after_new_m": _mean(col("error_after_new_m")),
        "runs_retrained_better": sum(
            1
            for r in runs
            if r["error_after_new_m"] is not None
            and r["error_during_old_m"] is not None
            and r["error_after_new_m"] < r["error_during_old_m"]
        ),
        "onset_to_anomaly_s": _mean(col("onset_to_anomaly_s")),
        "onset_to_new_model_s": _mean(col("onset_to_new_model_s")),
        "false_anomalies": sum(col("false_anomalies")),
        "availability": min(col("availability")) if runs else 0.0,
        "samples_on_fallback": sum(col("samples_on_fallback")),
        "proposed": sum(col("proposed")),
        "approved": sum(col("approved")),
        "rejected": sum(col("rejected")),
        "planted": sum(col("planted")),
        "planted_rejected": sum(col("planted_rejected")),
        "planted_executed": sum(col("planted_executed")),
        "lost_cycles": sum(col("lost_cycles")),
    }


def _fmt(v: Any, unit: str = "") -> str:
    return "-" if v is None else f"{v:g}{unit}" if isinstance(v, float) else f"{v}{unit}"


def _row(r: dict[str, Any]) -> str:
    errors = (
        f"{_fmt(r['error_before_m'], ' m'):>9}{_fmt(r['error_during_old_m'], ' m'):>15}"
        f"{_fmt(r['error_after_new_m'], ' m'):>11}"
    )
    times = f"{_fmt(r['onset_to_anomaly_s'], ' s'):>9}{_fmt(r['onset_to_new_model_s'], ' s'):>11}"
    rest = (
        f"{r['availability']:>8.1%}{r['samples_on_fallback']:>10}"
        f"{r['planted_rejected']:>8} / {r['planted']:<4}"
    )
    return f"  {r['seed']:>5}{errors}{times}{rest}"


def table(agg: dict[str, Any], runs: list[dict[str, Any]]) -> str:
    lines = [
        "",
        f"ship-motion evaluation: {agg['runs']} seeded scenarios",
        f"  {'seed':>5}{'before':>9}{'old, in front':>15}{'retrained':>11}"
        f"{'anomaly':>9}{'new model':>11}{'avail.':>8}{'fallback':>10}{'planted rej.':>14}",
    ]
    lines += [_row(r) for r in runs]
    lines += [
        "",
        f"  mean path error (30 s ahead): before the front {_fmt(agg['error_before_m'], ' m')}, "
        f"in it with the old model {_fmt(agg['error_during_old_m'], ' m')}, "
        f"with the retrained one {_fmt(agg['error_after_new_m'], ' m')} "
        f"(better in {agg['runs_retrained_better']} of {agg['runs']} runs)",
        f"  onset -> anomaly {_fmt(agg['onset_to_anomaly_s'], ' s')}, -> new model in use "
        f"{_fmt(agg['onset_to_new_model_s'], ' s')} (sim time, means); "
        f"{agg['false_anomalies']} anomalies before any front",
        f"  availability {agg['availability']:.1%} (lowest run; fallbacks count), "
        f"{agg['samples_on_fallback']} samples on the physics fallback",
        f"  candidates: {agg['proposed']} proposed, {agg['approved']} approved, "
        f"{agg['rejected']} rejected; planted {agg['planted']}, rejected "
        f"{agg['planted_rejected']}, executed {agg['planted_executed']}",
    ]
    return "\n".join(lines)


@cli.command()
def main(
    runs: Annotated[int, typer.Option(help="Scenarios.", min=1)] = 5,
    seed: Annotated[int, typer.Option(help="Seed of the first scenario.")] = 1,
    onset: Annotated[
        float, typer.Option(help="Sim seconds of calm before the front.", min=120)
    ] = 600.0,
    duration: Annotated[float, typer.Option(help="Sim seconds per run.", min=600)] = 2400.0,
    plant: Annotated[
        str,
        typer.Option(
            help="Bad candidates planted before each real one: comma-separated of "
            f"{', '.join(PLANTS)}, or empty."
        ),
    ] = ",".join(PLANTS),
    out: Annotated[Path, typer.Option(help="Output directory.")] = Path("out/eval"),
    rerun: Annotated[
        bool, typer.Option(help="Write <out>/ship_motion_<seed>.rrd per run (Rerun).")
    ] = False,
    verbose: Annotated[bool, typer.Option(help="Log the stages' decisions.")] = False,
    one: Annotated[
        bool, typer.Option(hidden=True, help="Run one scenario here; JSON on stdout.")
    ] = False,
) -> None:
    """Run the evaluation and write <out>/ship_motion.json."""
    kinds = [k for k in plant.split(",") if k]
    bad = [k for k in kinds if k not in PLANTS]
    if bad:
        raise typer.BadParameter(
            f"unknown plant {bad}: choose from {', '.join(PLANTS)}", param_hint="--plant"
        )
    if one:
        logging.basicConfig(
            level=logging.INFO if verbose else logging.WARNING,
            format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        )
        if rerun:
            out.mkdir(parents=True, exist_ok=True)
        rrd = str(out / f"ship_motion_{seed}.rrd") if rerun else None
        result = anyio.run(_run, seed, kinds, onset, duration, rrd)
        sys.stdout.write(json.dumps(result) + "\n")
        return
    out.mkdir(parents=True, exist_ok=True)
    results = []
    t0 = time.perf_counter()
    for i in range(runs):
        s = seed + i
        cmd = [
            sys.executable,
            "-m",
            "ship_motion.eval",
            "--one",
            "--seed",
            str(s),
            "--onset",
            str(onset),
            "--duration",
            str(duration),
            "--plant",
            ",".join(kinds),
            "--out",
            str(out),
        ]
        if rerun:
            cmd.append("--rerun")
        done = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if done.returncode != 0:
            sys.stderr.write(done.stderr)
            sys.stderr.write(
                f"error: scenario seed {s} failed (exit {done.returncode}); its log is above\n"
            )
            raise typer.Exit(1)
        r = json.loads(done.stdout.strip().splitlines()[-1])
        results.append(r)
        print(
            f"[{time.perf_counter() - t0:6.1f} s] run {i + 1}/{runs} seed {s}: error "
            f"{_fmt(r['error_during_old_m'], ' m')} -> {_fmt(r['error_after_new_m'], ' m')}, "
            f"availability {r['availability']:.1%}, planted rejected "
            f"{r['planted_rejected']}/{r['planted']}",
            flush=True,
        )
    agg = aggregate(results)
    doc = {
        "runs": runs,
        "seed": seed,
        "onset_s": onset,
        "duration_s": duration,
        "plant": kinds,
        "aggregate": agg,
        "results": results,
    }
    path = out / "ship_motion.json"
    path.write_text(json.dumps(doc, indent=2) + "\n")
    print(table(agg, results), flush=True)
    print(f"\n  written {path}", flush=True)


if __name__ == "__main__":
    run_cli(cli)
