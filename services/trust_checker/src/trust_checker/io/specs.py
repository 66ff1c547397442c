"""Loading a spec that arrived as text (hot swap from MQTT or the fabric)."""

from __future__ import annotations

from ..errors import SpecError
from ..lang import check_spec, parse_spec
from ..lang.ast import Spec

__all__ = ["load_text"]


def load_text(text: str, path: str = "<swap>") -> Spec:
    """Parse and check spec *text*; ``path`` names it in errors. Unlike
    :func:`trust_checker.lang.load_spec` this never reads a file, whatever the text says:
    a spec from the network must not name files on the checker's disk."""
    spec = parse_spec(text, path)
    problems = check_spec(spec)
    if problems:
        raise SpecError(problems)
    return spec
