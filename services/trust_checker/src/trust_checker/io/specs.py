"""Loading a spec that arrived as text (hot swap from MQTT or the fabric)."""

from __future__ import annotations

from typing import Final

from ..errors import Problem, SpecError
from ..lang import check_spec, parse_spec
from ..lang.ast import Spec

__all__ = ["MAX_SPEC_CHARS", "load_text"]

MAX_SPEC_CHARS: Final = 256 << 10
"""The longest spec text taken over the network (a spec is a few KiB; parsing a
megabyte of expression takes seconds and hundreds of MiB)."""


def load_text(text: str, path: str = "<swap>") -> Spec:
    """Parse and check spec *text*; ``path`` names it in errors. Unlike
    :func:`trust_checker.lang.load_spec` this never reads a file, whatever the text says:
    a spec from the network must not name files on the checker's disk."""
    if len(text) > MAX_SPEC_CHARS:
        raise SpecError(
            [
                Problem(
                    path,
                    1,
                    1,
                    f"the spec is {len(text)} characters, over the limit of {MAX_SPEC_CHARS}",
                    hint="a spec is a few KiB; split what is not one spec",
                )
            ]
        )
    spec = parse_spec(text, path)
    problems = check_spec(spec)
    if problems:
        raise SpecError(problems)
    return spec
