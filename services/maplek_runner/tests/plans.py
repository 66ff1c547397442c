"""Plans for the runner's tests, naming the Nodes of ``sample_nodes``.

Plans name modules the way a deployment does, by their import path from the repository
root (pytest puts the root on sys.path; the CLI test runs there). pytest
(``--import-mode=importlib``) imports test files under a package name of its own
(``tests.*``, which several test directories share), so the tests import these helpers
by absolute name, ``from services.maplek_runner.tests import sample_nodes``: the same
module objects that the plans' module specs import."""

from __future__ import annotations

from pathlib import Path

SAMPLE = "services.maplek_runner.tests.sample_nodes"
BROKEN = "services.maplek_runner.tests.broken_nodes"
REPO = Path(__file__).resolve().parents[3]
"""The repository root: the working directory from which ``SAMPLE`` imports."""

PLAN = f"""\
system: demo
compute_nodes:
  laptop: {{}}
  robot: {{}}
components:
  echo:
    module: {SAMPLE}:echo
    stage: monitor
    node: laptop
  relay:
    module: {SAMPLE}:relay
    stage: analyse
    node: laptop
    config: {{reply: tack}}
  silent:
    module: {SAMPLE}:silent
    stage: plan
    node: robot
"""
