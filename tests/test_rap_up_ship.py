"""``rap up examples/ship_motion/model.yaml --all`` runs the ship-motion case across its two
compute nodes (the vessel: predictors, monitor, execute; the shore: knowledge with the model
store, analysis, plan, legitimate), with the ship simulator as a client of the vessel's
router: the weather front makes the loop retrain, and the ship serves the new model; an
operator's ``rap models rollback`` brings the previous one back to the ship.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import anyio
import pytest
from rap_cli.testing import model_copy, rap_command, rap_up
from rap_sdk.fabric import CONFIG_ENV
from rap_sdk.testing import Harness, Record
from ship_motion import messages

pytestmark = [pytest.mark.anyio, pytest.mark.zenoh, pytest.mark.slow, pytest.mark.timeout(180)]

REPO = Path(__file__).resolve().parents[1]
MODEL = REPO / "examples/ship_motion/model.yaml"
SIMULATOR = "    run: ['{python}', -m, ship_motion, --system, '{system}', --speed, '20']\n"


def _served(version: int) -> Callable[[Record], bool]:
    def match(r: Record) -> bool:
        if r.name != "ship/predicted_path" or r.envelope is None:
            return False
        p = r.decode(messages.PredictedPath)
        return p.predictor == messages.PredictorKind.DATA_DRIVEN and p.model_version == version

    return match


async def _ship(run: Path, *args: str) -> subprocess.CompletedProcess[bytes]:
    env = {**os.environ, CONFIG_ENV: str(run / "vessel" / "zenoh-client.json5")}
    argv = [sys.executable, "-m", "ship_motion", "--speed", "100", *args]
    with anyio.fail_after(90):
        return await anyio.run_process(argv, env=env, check=False)


async def test_the_ship_retrains_across_two_nodes_and_follows_a_rollback(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    run = tmp_path / "run"
    # the shipped model, the shore's port free, the simulator started here (faster)
    model = model_copy(MODEL, tmp_path, endpoint="tcp/shore:7447", drop=[SIMULATOR])
    async with rap_up(model, run, nodes=("vessel", "shore")):
        monkeypatch.setenv(CONFIG_ENV, str(run / "vessel" / "zenoh-client.json5"))
        async with Harness(system="ship_motion", fabric="zenoh", timeout=60) as h:
            ship = await _ship(run, "--onset", "300", "--duration", "1300")
            assert ship.returncode == 0, ship.stderr.decode()[-3000:]
            first = await h.wait_for(_served(1))
            second = await h.wait_for(_served(2), after=h.records.index(first))
            anomaly = await h.expect_event("anomaly")
            assert h.records.index(anomaly) < h.records.index(second)
            rap = rap_command()
            listed = await anyio.run_process(
                [rap, "models", "list", str(model), "ship_motion", "--run-dir", str(run)],
                check=False,
            )
            assert listed.returncode == 0, listed.stderr.decode()
            assert "in force: version 2 (pinned)" in listed.stdout.decode()
            back = await anyio.run_process(
                [rap, "models", "rollback", str(model), "ship_motion", "--run-dir", str(run)],
                check=False,
            )
            assert back.returncode == 0, back.stderr.decode()
            mark = len(h.records)
            ship = await _ship(run, "--onset", "3000", "--duration", "60")
            assert ship.returncode == 0, ship.stderr.decode()[-3000:]
            await h.wait_for(_served(1), after=mark)
