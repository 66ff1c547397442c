"""The acceptance suite's one input: the folder of third-party design models, named by
the ``DESIGN_MODELS`` environment variable (``make acceptance`` sets it)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def design_models() -> Path:
    """The design-model folder (it holds ``aadl/``, ``aadl-il/`` and ``robochart/``);
    a missing or wrong one fails the test, it never skips it."""
    value = os.environ.get("DESIGN_MODELS")
    if not value:
        pytest.fail(
            "DESIGN_MODELS is not set - set it to the shared design-model folder "
            "(the one holding aadl/, aadl-il/ and robochart/)"
        )
    root = Path(value)
    missing = [d for d in ("aadl", "aadl-il", "robochart") if not (root / d).is_dir()]
    if missing:
        pytest.fail(
            f"{root} lacks {', '.join(missing)} - DESIGN_MODELS={value} must name the "
            "shared design-model folder"
        )
    return root
