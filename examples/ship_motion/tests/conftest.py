"""Runs shared by the ship-motion tests: simulated once per session."""

from __future__ import annotations

from functools import cache

import pytest
from ship_motion.physics import History, scenario_from_seed, simulate

ONSET = 900.0
"""When the weather front sets in (it ramps up over the next 60 s); test_learn.py relies on it."""
SEEDS = (0, 1, 2)


@cache
def disturbed_run(seed: int) -> History:
    """The ship on its route: calm for 900 s, then the seed's wind, current and waves."""
    return simulate(scenario_from_seed(seed, onset_s=ONSET, ramp_s=60.0, duration_s=1900.0))


@pytest.fixture(scope="session")
def runs() -> dict[int, History]:
    return {seed: disturbed_run(seed) for seed in SEEDS}
