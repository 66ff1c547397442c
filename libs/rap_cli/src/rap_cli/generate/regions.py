"""User regions of generated files: what the user writes there survives regeneration.

    # region user: on_scan
    ...                           # kept as it is when the file is generated again
    # endregion user: on_scan

A region the new file no longer has (its port was removed from the model, say) is not
dropped: it is kept, commented out, at the end of the file, under a heading that says so.
"""

from __future__ import annotations

import re

__all__ = ["REGION", "RegionError", "begin", "end", "merge", "regions"]

_BEGIN = re.compile(r"^(?P<indent>[ \t]*)# region user: (?P<id>[\w.\-]+)[ \t]*$")
_END = re.compile(r"^[ \t]*# endregion user: (?P<id>[\w.\-]+)[ \t]*$")
ORPHANS = "# -- regions of an earlier generation that the model no longer has (kept) --"
REGION = "# region user:"


class RegionError(ValueError):
    """A generated file whose region markers do not pair up (``file:line: ...``)."""


def begin(rid: str, indent: str = "") -> str:
    return f"{indent}# region user: {rid}"


def end(rid: str, indent: str = "") -> str:
    return f"{indent}# endregion user: {rid}"


def regions(text: str, source: str = "<file>") -> dict[str, list[str]]:
    """The body lines of each region of ``text``, by id."""
    out: dict[str, list[str]] = {}
    current: str | None = None
    start = 0
    body: list[str] = []
    for n, line in enumerate(text.splitlines(), 1):
        b, e = _BEGIN.match(line), _END.match(line)
        if b is not None:
            if current is not None:
                raise RegionError(
                    f"{source}:{n}: region {b['id']!r} starts inside region {current!r} "
                    f"(line {start}); close that one first with '{end(current)}'"
                )
            current, start, body = b["id"], n, []
        elif e is not None:
            if current is None or current != e["id"]:
                raise RegionError(
                    f"{source}:{n}: '{line.strip()}' closes no open region of that id; "
                    "restore the region's markers as the generator wrote them"
                )
            if current in out:
                raise RegionError(f"{source}:{n}: region {current!r} appears twice")
            out[current] = body
            current = None
        elif current is not None:
            body.append(line)
    if current is not None:
        raise RegionError(
            f"{source}:{start}: region {current!r} is never closed; add '{end(current)}'"
        )
    return out


def merge(new: str, old: str | None, source: str = "<file>") -> str:
    """``new`` (freshly generated) with the bodies of ``old``'s regions put back."""
    if old is None:
        return new
    kept = regions(old, source)
    used: set[str] = set()
    out: list[str] = []
    skipping = False
    for line in new.splitlines():
        b, e = _BEGIN.match(line), _END.match(line)
        if b is not None and b["id"] in kept:
            out.append(line)
            out.extend(kept[b["id"]])
            used.add(b["id"])
            skipping = True
            continue
        if e is not None and skipping:
            skipping = False
        elif skipping:
            continue
        out.append(line)
    orphans = [rid for rid in kept if rid not in used and any(s.strip() for s in kept[rid])]
    if orphans:
        out += ["", "", ORPHANS]
        for rid in orphans:
            out.append(f"# {begin(rid)}")
            out += [f"# {line}" if line.strip() else "#" for line in kept[rid]]
            out.append(f"# {end(rid)}")
    return "\n".join(out) + "\n"
