"""A recorded run of the lidar-occlusion loop, replayed into a fresh loop, makes the same
decisions, cycle by cycle (issue 16: ``rap record`` / ``rap replay``).

1. ``rap up --all`` runs the loop's processes (a copy of examples/lidar_occlusion/model.yaml
   on a free port, its simulator's ``run:`` taken out) and ``rap record`` records the
   whole system while the simulator (``python -m sim_world``, a client of the robot's
   router, in real time) drives it through a world of two occlusions: the first gets
   a plan that is approved and sent to the robot, the second is too wide for the
   planner's period (``config: {period: 4.0}``), so its plans are rejected.
2. A fresh ``rap up --all`` of the same model (no simulator: nothing but the loop and
   knowledge) gets ``rap replay`` of the recorded managed-system data only (``--only
   'data/**' --exclude data/tb1/spin_config``: the scans, odometry and clock, not the
   plans the first loop sent), while ``rap record`` records it again.
3. The decisions of both recordings are compared per cycle (the envelope's ``cycle``: the
   uid of the scan that started it, which the replay keeps): the anomalies raised (their
   masks), the verdicts (approved or rejected, and why), the plans given up on, and the
   plans sent to the robot (their commands).

What can make the runs differ is the loop itself, not the replay: the analysis reads the
knowledge key ``laser_scan`` at least at the version its ``new-data`` event names, so
when its handler runs late (a loaded machine), after the monitor has written the next
scan, it judges that next scan in the earlier cycle (and its mask window holds that scan
twice). Its decision then lands one cycle early in one run and not in the other. The
failure message says so per cycle ("the analysis read scan N's laser_scan"), from the
runs' own trace records. Scans 200 ms apart (the simulator in real time) leave the loop
ample time on an idle machine; under heavy load the test can still fail that way.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import AsyncIterator, Sequence
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import anyio
import msgspec
import pytest
from rap_cli.recording import read_recording
from rap_cli.testing import model_copy, rap_command, rap_up
from rap_schemas import Envelope, LidarMask, SpinPlan, StageTrace, Verdict, keys
from rap_sdk.fabric import CONFIG_ENV
from rap_sdk.testing import OutputLines, stop_process

pytestmark = [pytest.mark.anyio, pytest.mark.zenoh, pytest.mark.slow, pytest.mark.timeout(120)]

REPO = Path(__file__).resolve().parents[1]
MODEL = REPO / "examples/lidar_occlusion/model.yaml"
DEFAULT_WORLD = REPO / "services/sim_world/src/sim_world/worlds/default.yaml"
SYSTEM = "demo"
SIM_RUN = (
    '    run: ["{python}", "-m", "sim_world", "--system", "{system}", "--world", "default", '
    '"--name", "robot"]\n'
)
SIM_SECONDS = 6.6
SIM_SPEED = 1.0

# two occlusions of the robot's lidar: a narrow one (its plan takes 3 s: approved) and
# a wide one (its plan would take over 4 s, the planner's period: rejected)
OCCLUSIONS = """\
occlusions:
  - {robot: tb1, mode: sector, start_angle: -0.9, width: 1.5, t_start: 1.0, t_end: 2.6}
  - {robot: tb1, mode: sector, start_angle: -1.6, width: 2.8, t_start: 3.4, t_end: 6.0}
"""


def _model(tmp_path: Path) -> Path:
    """The lidar model without its simulator (the test runs it, or the replay stands for
    it), its planner's period long enough that a wide occlusion's plans are rejected."""
    model = model_copy(MODEL, tmp_path, drop=[SIM_RUN])
    text = model.read_text()
    assert text.count("    stage: plan\n") == 1
    model.write_text(
        text.replace("    stage: plan\n", "    stage: plan\n    config: {period: 4.0}\n")
    )
    return model


QUIET = ("--log-level", "WARNING")


def _world(tmp_path: Path) -> Path:
    text = DEFAULT_WORLD.read_text()
    head, sep, _ = text.partition("occlusions:")
    assert sep, "the default world has no occlusions: section: update this test"
    world = tmp_path / "world.yaml"
    world.write_text(head + OCCLUSIONS)
    return world


@asynccontextmanager
async def rap_record(model: Path, run: Path, out: Path) -> AsyncIterator[OutputLines]:
    """``rap record`` of the whole system; stopped with SIGINT (as Ctrl-C) on the way
    out, which must finish the file."""
    argv = [rap_command(), "record", "-o", str(out), "-m", str(model), "--run-dir", str(run)]
    async with (
        await anyio.open_process(argv, stderr=subprocess.STDOUT) as rec,
        anyio.create_task_group() as tg,
    ):
        lines = OutputLines(rec)
        tg.start_soon(lines.pump)
        try:
            await lines.line("recording", keys.system_pattern(SYSTEM))
            yield lines
            rec.send_signal(signal.SIGINT)
            with anyio.fail_after(15):
                assert await rec.wait() == 0, str(lines)
            await lines.line("stopped (SIGINT); wrote")
        finally:
            await stop_process(rec)


class Run:
    """What a recording shows of the loop: per cycle (hex uid of the scan that started
    it), the decisions in the order recorded, each as one comparable line; the scans in
    order; and, to explain a difference, what the monitor and the analysis did."""

    def __init__(self, path: Path) -> None:
        self.decisions: dict[str, list[str]] = {}
        self.scans: list[str] = []
        self.new_data: set[str] = set()
        self.wrote: dict[str, int] = {}
        """The monitor's write of laser_scan, per cycle."""
        self.read: dict[str, int] = {}
        """The analysis's read of laser_scan, per cycle (when its trace was recorded)."""
        k = {
            "anomaly": keys.event(SYSTEM, "anomaly"),
            "verdict": keys.event(SYSTEM, "verdict"),
            "plan-rejected": keys.event(SYSTEM, "plan-rejected"),
            "spin": keys.data(SYSTEM, "tb1/spin_config"),
            "scan": keys.data(SYSTEM, "tb1/scan"),
            "new-data": keys.event(SYSTEM, "new-data"),
        }
        for key, _, data in read_recording(path):
            env = msgspec.msgpack.decode(data, type=Envelope)
            if key == k["scan"]:
                self.scans.append(env.uid.hex())
                continue
            if env.type == StageTrace.TYPE:
                self._trace(msgspec.msgpack.decode(env.body, type=StageTrace))
                continue
            if key == k["new-data"] and env.cycle is not None:
                self.new_data.add(env.cycle.hex())
            if key not in (k["anomaly"], k["verdict"], k["plan-rejected"], k["spin"]):
                continue
            assert env.cycle is not None, f"a decision without a cycle on {key}"
            if key == k["anomaly"]:
                mask = msgspec.msgpack.decode(env.body, type=LidarMask)
                line = f"anomaly: beams {_runs(mask.flags())} occluded"
            elif key == k["spin"]:
                plan = msgspec.msgpack.decode(env.body, type=SpinPlan)
                cmds = ", ".join(
                    f"{c.omega:+.3f} rad/s x {c.duration:.6f} s" for c in plan.commands
                )
                line = f"plan sent to the robot: [{cmds}] every {plan.period:g} s"
            else:
                v = msgspec.msgpack.decode(env.body, type=Verdict[Any])
                what = "approved" if v.approved else f"rejected ({v.reason})"
                line = f"{'verdict' if key == k['verdict'] else 'plan-rejected'}: {what}"
            self.decisions.setdefault(env.cycle.hex(), []).append(line)

    def _trace(self, st: StageTrace) -> None:
        for a in st.access:
            if a.key != "laser_scan":
                continue
            if st.node == "monitor" and a.op == "write":
                self.wrote[st.cycle.hex()] = a.version
            elif st.node == "analysis" and a.op == "read":
                self.read[st.cycle.hex()] = a.version

    def evidence(self, cycle: str) -> str:
        """What the monitor and the analysis did in ``cycle``."""
        if cycle not in self.new_data:
            return "the monitor sent no new-data for this scan"
        read, wrote = self.read.get(cycle), self.wrote.get(cycle)
        if read is None or wrote is None:
            return "new-data sent; the analysis's trace of it was not recorded"
        if read == wrote:
            return "new-data sent; the analysis read this scan"
        which = next((c for c, v in self.wrote.items() if v == read), None)
        where = f"scan {self.scans.index(which)}'s" if which in self.scans else "another"
        return (
            f"new-data sent; the analysis read {where} laser_scan (version {read}), not "
            f"this one's ({wrote})"
        )


def _runs(flags: Sequence[bool]) -> str:
    """The occluded beams as index ranges: ``187-266``, ``0-3,350-359``."""
    runs: list[str] = []
    start = None
    for i, f in enumerate([*flags, False]):
        if f and start is None:
            start = i
        elif not f and start is not None:
            runs.append(f"{start}-{i - 1}")
            start = None
    return ",".join(runs) or "none"


def _table(first: Run, second: Run) -> str:
    """Every scan that decided something in either run, in scan order, with both runs'
    decisions; for a scan where they differ, and the two before it, what the monitor
    and the analysis did."""
    rows = []
    order = first.scans
    differ = {
        i for i, c in enumerate(order) if first.decisions.get(c, []) != second.decisions.get(c, [])
    }
    explain = {j for i in differ for j in (i - 2, i - 1, i) if j >= 0}
    for i, cycle in enumerate(order):
        a, b = first.decisions.get(cycle, []), second.decisions.get(cycle, [])
        if not a and not b and i not in explain:
            continue
        rows.append(f"scan {i} (cycle {cycle}): {'DIFFERENT' if i in differ else 'same'}")
        rows += [f"    recorded: {line}" for line in a] or ["    recorded: (nothing)"]
        rows += [f"    replayed: {line}" for line in b] or ["    replayed: (nothing)"]
        if i in explain:
            rows.append(f"    recorded run: {first.evidence(cycle)}")
            rows.append(f"    replayed run: {second.evidence(cycle)}")
    stray = sorted(set(second.decisions) - set(order))
    rows += [f"cycle {c} (not a recorded scan): replayed: {second.decisions[c]}" for c in stray]
    return "\n".join(rows)


async def test_a_recorded_run_replayed_into_a_fresh_loop_makes_the_same_decisions(
    tmp_path: Path,
) -> None:
    model, world = _model(tmp_path), _world(tmp_path)
    first, second = tmp_path / "recorded.mcap", tmp_path / "replayed.mcap"

    # 1. the loop with the simulator, recorded
    run1 = tmp_path / "run1"
    async with rap_up(model, run1, args=QUIET), rap_record(model, run1, first):
        sim = await anyio.run_process(
            [
                sys.executable,
                "-m",
                "sim_world",
                "--system",
                SYSTEM,
                "--world",
                str(world),
                "--speed",
                str(SIM_SPEED),
                "--duration",
                str(SIM_SECONDS),
                "--log-level",
                "WARNING",
            ],
            env={**os.environ, CONFIG_ENV: str(run1 / "robot" / "zenoh-client.json5")},
            check=False,
        )
        assert sim.returncode == 0, sim.stdout.decode() + sim.stderr.decode()
        await anyio.sleep(1.0)  # the last cycle's decisions reach the recorder

    # 2. a fresh loop (no simulator), fed the recorded managed-system data, recorded
    run2 = tmp_path / "run2"
    async with rap_up(model, run2, args=QUIET), rap_record(model, run2, second):
        replay = await anyio.run_process(
            [
                rap_command(),
                "replay",
                str(first),
                "--only",
                "data/**",
                "--exclude",
                "data/tb1/spin_config",
                "-m",
                str(model),
                "--run-dir",
                str(run2),
            ],
            check=False,
        )
        said = replay.stdout.decode() + replay.stderr.decode()
        assert replay.returncode == 0, said
        await anyio.sleep(1.0)

    # 3. the same decisions, cycle by cycle
    recorded, replayed = Run(first), Run(second)
    table = _table(recorded, replayed)
    # the run was worth comparing: it decided both ways and acted
    lines = [line for ls in recorded.decisions.values() for line in ls]
    assert len(recorded.scans) >= SIM_SECONDS * 5 - 2, f"{len(recorded.scans)} scans\n{table}"
    assert any(line.startswith("anomaly") for line in lines), table
    assert any(line == "verdict: approved" for line in lines), table
    assert any(line.startswith("verdict: rejected") for line in lines), table
    assert any(line.startswith("plan sent") for line in lines), table
    assert replayed.scans == recorded.scans, f"the replay sent other scans\n{table}"
    assert replayed.decisions == recorded.decisions, (
        "the replayed loop decided otherwise:\n" + table
    )
