"""RoboChart (``.rct``) and RoboArch (``.rac``) designs: the parser and its located syntax
model. :func:`parse_robochart_files` reads a design's files; :mod:`.syntax` documents
what comes back."""

from .parse import (
    MAX_BYTES,
    MAX_NESTING,
    parse_roboarch,
    parse_robochart,
    parse_robochart_files,
)

__all__ = [
    "MAX_BYTES",
    "MAX_NESTING",
    "parse_roboarch",
    "parse_robochart",
    "parse_robochart_files",
]
