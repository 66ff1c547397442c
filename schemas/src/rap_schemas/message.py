"""The base of every typed wire message.

A message is a frozen Struct with a class-level wire name ``TYPE`` (``rap.Name/version``).
Wire messages accept unknown fields so that a newer sender that added a defaulted field
still reaches an older receiver (schema evolution by adding defaulted fields only).
"""

from __future__ import annotations

import re
from typing import Any, ClassVar

import msgspec

__all__ = ["Message"]

_TYPE = re.compile(r"[a-z][a-z0-9_]*(\.[A-Za-z][A-Za-z0-9_]*)+/[1-9][0-9]*")


class Message(msgspec.Struct, frozen=True, kw_only=True):
    TYPE: ClassVar[str] = ""

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        name = cls.__dict__.get("TYPE", "")
        if name and not _TYPE.fullmatch(name):
            raise TypeError(
                f"{cls.__qualname__}.TYPE = {name!r} is not a wire name; "
                "use 'package.Name/<version>', e.g. 'rap.LaserScan/1'"
            )
