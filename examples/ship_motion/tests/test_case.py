"""The whole case on the fabric: the ship, its predictors, knowledge with the model store and
the generated MAPLE-K nodes, in lockstep (one scenario of ``make eval-ship``, shortened)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest


def _scenario(tmp_path: Path, seed: int, *extra: str) -> dict[str, object]:
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "ship_motion.eval",
            "--one",
            "--seed",
            str(seed),
            "--onset",
            "300",
            "--duration",
            "1400",
            "--out",
            str(tmp_path),
            *extra,
        ],
        capture_output=True,
        text=True,
        check=False,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-4000:]
    result: dict[str, object] = json.loads(done.stdout.strip().splitlines()[-1])
    return result


@pytest.mark.parametrize("seed", [4])
def test_the_loop_retrains_and_legitimate_keeps_planted_models_out(
    tmp_path: Path, seed: int
) -> None:
    r = _scenario(tmp_path, seed, "--rerun")
    assert r["false_anomalies"] == 0, r
    assert isinstance(r["onset_to_anomaly_s"], float), r
    assert 0 < r["onset_to_anomaly_s"] < 200, r
    before, during, after = r["error_before_m"], r["error_during_old_m"], r["error_after_new_m"]
    assert isinstance(before, float), r
    assert isinstance(during, float), r
    assert isinstance(after, float), r
    assert during > 3 * before, r  # the front makes the old model drift ...
    assert after < during / 3, r  # ... and the retrained one predicts well again
    assert r["availability"] == 1.0, r  # a path on the display at every sample
    assert r["samples_on_fallback"] > 0, r  # the physics fallback covered the retraining
    assert (r["planted"], r["planted_rejected"], r["planted_executed"]) == (3, 3, 0), r
    assert r["approved"] >= 1, r
    assert r["lost_cycles"] == 0, r
    rrd = tmp_path / f"ship_motion_{seed}.rrd"
    assert rrd.stat().st_size > 10_000
