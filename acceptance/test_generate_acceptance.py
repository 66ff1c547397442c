"""From a third-party design to a running system: ``rap new --from`` the ship-motion AADL
makes a package that passes its own generated tests unedited and runs with
``rap up --all`` (every Node of every compute node alive on the fabric), then stops with
``rap down``."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

RAP = [sys.executable, "-m", "rap_cli.app"]


def _env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "RAP_ZENOH_CONFIG")}


def _run(args: list[str], cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        args, cwd=cwd, capture_output=True, text=True, timeout=timeout, env=_env(), check=False
    )


@pytest.mark.timeout(300)
@pytest.mark.parametrize("design", ["rpio-ntnu-ship", "rpio-ntnu-ship-docs"])
def test_the_ship_design_becomes_a_package_that_tests_and_runs(
    design_models: Path, tmp_path: Path, design: str
) -> None:
    source = design_models / "aadl" / design
    new = _run([*RAP, "new", "shipmotion", "--from", str(source)], tmp_path)
    assert new.returncode == 0, new.stdout + new.stderr
    pkg = tmp_path / "shipmotion"
    # its own generated tests, unedited, with the Python environment RAP is installed in
    tests = _run([sys.executable, "-m", "pytest", "-q"], pkg)
    assert tests.returncode == 0, tests.stdout + tests.stderr
    assert " passed" in tests.stdout
    # every compute node's share on this machine
    run_dir = tmp_path / "run"
    log = (tmp_path / "up.log").open("w")
    up = subprocess.Popen(
        [*RAP, "up", "model.yaml", "--all", "--run-dir", str(run_dir)],
        cwd=pkg,
        stdout=log,
        stderr=subprocess.STDOUT,
        env=_env(),
    )
    try:
        import yaml

        model = yaml.safe_load((pkg / "model.yaml").read_text())
        nodes = sorted({c["node"] for c in model["components"].values() if c.get("module")})
        assert nodes, "the generated model runs no component"
        deadline = time.monotonic() + 90
        healthy: set[str] = set()
        while time.monotonic() < deadline and healthy != set(nodes):
            assert up.poll() is None, (tmp_path / "up.log").read_text()
            for node in nodes:
                if node in healthy:
                    continue
                check = _run(
                    [
                        *RAP,
                        "health",
                        "model.yaml",
                        "--node",
                        node,
                        "--run-dir",
                        str(run_dir),
                        "--timeout",
                        "5",
                    ],
                    pkg,
                    timeout=60,
                )
                if check.returncode == 0:
                    healthy.add(node)
        assert healthy == set(nodes), (tmp_path / "up.log").read_text()[-4000:]
        down = _run([*RAP, "down", "model.yaml", "--run-dir", str(run_dir)], pkg, timeout=90)
        assert down.returncode == 0, down.stdout + down.stderr
        assert up.wait(timeout=60) == 0, (tmp_path / "up.log").read_text()[-4000:]
    finally:
        if up.poll() is None:
            up.send_signal(signal.SIGTERM)
            try:
                up.wait(timeout=30)
            except subprocess.TimeoutExpired:
                up.kill()
        log.close()
