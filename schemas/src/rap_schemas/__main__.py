"""``python -m rap_schemas export DIR``: write the JSON Schema export.
``python -m rap_schemas reference DOC``: write the model reference into DOC (between its
markers)."""

from __future__ import annotations

import sys
from pathlib import Path

from .export import write

__all__ = ["main"]


def main(argv: list[str]) -> int:
    if len(argv) == 2 and argv[0] == "reference":
        from .reference import update_doc

        changed = update_doc(Path(argv[1]))
        print(f"{argv[1]}: model reference {'updated' if changed else 'unchanged'}")
        return 0
    if len(argv) != 2 or argv[0] != "export":
        print("usage: python -m rap_schemas export DIR | reference DOC", file=sys.stderr)
        return 2
    paths = write(Path(argv[1]))
    print(f"wrote {len(paths)} schemas to {argv[1]}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
