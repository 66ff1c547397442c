"""The example's commands report mistakes as one 'error:' line with exit code 2."""

from __future__ import annotations

import subprocess
import sys

import pytest


@pytest.mark.parametrize(
    ("module", "args", "says"),
    [
        ("demo", ["--duration", "-1"], "--duration -1.0"),
        ("demo", ["--world", "corrid"], "'corrid' is not a shipped world"),
        ("demo", ["--plan", "/nonexistent/plan.yaml"], "cannot read the deployment plan"),
        ("demo", ["--log-level", "LOUD"], "'LOUD' is not a logging level"),
        ("eval", ["--runs", "0"], "Invalid value for '--runs'"),
    ],
)
def test_mistakes_are_one_line_and_exit_2(module: str, args: list[str], says: str) -> None:
    done = subprocess.run(
        [sys.executable, "-m", f"lidar_occlusion.{module}", *args],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 2, done.stderr
    assert done.stderr.startswith("error: "), done.stderr
    assert done.stderr.count("\n") == 1, done.stderr
    assert says in done.stderr
