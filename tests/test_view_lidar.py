"""``rap view`` on the lidar case as ``rap up examples/lidar_occlusion/model.yaml --all``
runs it (both compute nodes' routers, knowledge, the two runners, the simulator in real
time): ``rap view -m MODEL --run-dir RUN --save view.rrd`` finds the routers from the run
dir, as a user's ``rap view`` in the model's folder does, and the recording, read back
with rerun-sdk's own reader, holds the world, the scans, the robot's pose and a cycle
followed from its scan to the plan at the robot.
"""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import anyio
import pytest
from rap_cli.testing import model_copy, rap_up
from rap_schemas import Verdict, keys
from rap_sdk.fabric import CONFIG_ENV
from rap_sdk.testing import Harness, OutputLines, Record, stop_process

pytestmark = [pytest.mark.anyio, pytest.mark.zenoh, pytest.mark.slow, pytest.mark.timeout(150)]

REPO = Path(__file__).resolve().parents[1]
MODEL = REPO / "examples/lidar_occlusion/model.yaml"
SYSTEM = "demo"
PLAN_TOPIC = "tb1/spin_config"

RrdReader = pytest.importorskip("rerun.chunk").RrdReader


def _bin(name: str) -> str:
    exe = Path(sys.executable).with_name(name)
    assert exe.exists(), f"{exe}: {name} is not installed next to {sys.executable}"
    return str(exe)


def _approved(r: Record) -> bool:
    return r.kind is keys.Kind.EVENT and r.name == "verdict" and r.decode(Verdict[Any]).approved


def _rows(path: Path) -> dict[str, list[dict[str, Any]]]:
    """Every row of every entity, as {column: values} (timestamp columns left out)."""
    out: dict[str, list[dict[str, Any]]] = {}
    for chunk in RrdReader(path).stream().to_chunks():
        rb = chunk.to_record_batch()
        cols = {
            n: rb.column(i).to_pylist()
            for i, n in enumerate(rb.schema.names)
            if n not in ("time", "log_time") and not n.startswith("rerun.")
        }
        rows = out.setdefault(chunk.entity_path, [])
        rows += [{n: v[r] for n, v in cols.items()} for r in range(rb.num_rows)]
    return out


def _one(value: Any) -> Any:
    assert isinstance(value, list), value
    assert len(value) == 1, value
    return value[0]


async def test_rap_view_records_the_case_under_rap_up(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    run, out = tmp_path / "run", tmp_path / "view.rrd"
    copy = model_copy(MODEL, tmp_path)
    monkeypatch.setenv("RERUN_ANALYTICS", "0")
    monkeypatch.delenv(CONFIG_ENV, raising=False)
    rap = _bin("rap")
    async with rap_up(copy, run), anyio.create_task_group() as tg:
        view = await anyio.open_process(
            [rap, "view", "-m", str(copy), "--run-dir", str(run), "--save", str(out)],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
        )
        try:
            lines = OutputLines(view)
            tg.start_soon(lines.pump)
            await lines.line("viewing system demo through the routers of rap up")
            monkeypatch.setenv(CONFIG_ENV, str(run / "robot" / "zenoh-client.json5"))
            async with Harness(system=SYSTEM, fabric="zenoh", timeout=40) as h:
                # the default world covers the lidar from 6 s on: a cycle closes
                verdict = await h.wait_for(_approved)
                await h.expect_data(PLAN_TOPIC, after=h.records.index(verdict))
            view.send_signal(signal.SIGINT)  # it takes what is in flight, then closes
            with anyio.fail_after(30):
                code = await view.wait()
        finally:
            await stop_process(view)
        tg.cancel_scope.cancel()
    said = "\n".join(lines.lines)
    assert code == 0, said
    assert f"wrote {out}" in said, said

    rows = _rows(out)
    assert "/world/room" in rows, sorted(rows)  # the world of the model's simulator
    scans = rows["/world/tb1/scan"]
    assert len(scans) >= 20, len(scans)  # 5 Hz for more than 6 s
    assert any(len(r["Points2D:positions"]) > 100 for r in scans)
    assert all(_one(r["pose_known"]) for r in scans[1:])
    assert len(rows["/world/tb1/pose"]) >= 20
    # a cycle, scan -> anomaly -> new-plan -> verdict -> plan at the robot
    by_uid = {_one(r["uid"]): r for r in scans}
    planned = {_one(r["cycle_id"]) for r in rows["/world/tb1/plans"]}
    anomaly = next(
        r
        for r in rows["/maplek/events/anomaly"]
        if _one(r["cycle_id"]) in by_uid and _one(r["cycle_id"]) in planned
    )
    cycle_id, number = _one(anomaly["cycle_id"]), anomaly["cycle"]
    assert by_uid[cycle_id]["cycle"] == number
    for entity in ("/maplek/events/new-plan", "/maplek/events/verdict", "/world/tb1/plans"):
        hits = [r for r in rows[entity] if _one(r["cycle_id"]) == cycle_id]
        assert hits, (entity, cycle_id)
        assert all(r["cycle"] == number for r in hits)
