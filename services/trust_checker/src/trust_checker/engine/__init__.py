"""The evaluator: a checked spec compiled to closures and run one tick at a time.

:class:`SpecRunner` is the entry point (:mod:`.runner`); the layout of a compiled spec
is in :mod:`.plan`, the compiled nodes in :mod:`.nodes`, :mod:`.lifted`,
:mod:`.stateful` and :mod:`.dynamic`, the compiler in :mod:`.compiler`.
"""

from __future__ import annotations

from trust_checker.engine.runner import Fired, Output, SpecRunner

__all__ = ["Fired", "Output", "SpecRunner"]
