"""The trust checker: runtime verification of MAPLE-K loops in the LOLA/DSRV stream
language (both syntax eras of the RoboSAPIENS checker), on trace files, MQTT and the
Zenoh fabric. See docs/trust_checker.md.

The core is here: :func:`load_spec` (parse and check), :class:`SpecRunner` (run it one
tick at a time), :class:`Explainer` (why a verdict), the errors. The service (a spec on
MQTT or the fabric) is :func:`trust_checker.service.open_service`, configured with
:mod:`trust_checker.config`.
"""

from trust_checker.engine import Fired, Output, SpecRunner
from trust_checker.errors import (
    EvalError,
    InputError,
    Problem,
    SpecError,
    TextFileError,
    TrustError,
)
from trust_checker.explain import Explainer
from trust_checker.lang import load_spec

__all__ = [
    "EvalError",
    "Explainer",
    "Fired",
    "InputError",
    "Output",
    "Problem",
    "SpecError",
    "SpecRunner",
    "TextFileError",
    "TrustError",
    "load_spec",
]
