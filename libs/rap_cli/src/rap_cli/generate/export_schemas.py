"""``python -m rap_cli.generate.export_schemas ROOT PACKAGE TARGET``: write the JSON Schema
of each message of a generated package to ``TARGET/<Class>.schema.json`` (one process per
generation, so that importing the package registers its types nowhere else). Prints the
files it changed, relative to ROOT."""

from __future__ import annotations

import importlib
import json
import sys
from pathlib import Path


def main(argv: list[str]) -> int:
    root, package, target = Path(argv[0]), argv[1], Path(argv[2])
    sys.path.insert(0, str(root))
    module = importlib.import_module(f"{package}.messages")
    target.mkdir(parents=True, exist_ok=True)
    wanted = set()
    for cls in module.MESSAGES:
        schema = module.msgspec.json.schema(cls)
        path = target / f"{cls.__name__}.schema.json"
        wanted.add(path.name)
        text = json.dumps({"$id": cls.TYPE, **schema}, indent=2, sort_keys=True) + "\n"
        if not path.exists() or path.read_text(encoding="utf-8") != text:
            path.write_text(text, encoding="utf-8")
            sys.stdout.write(path.relative_to(root).as_posix() + "\n")
    for stale in target.glob("*.schema.json"):
        if stale.name not in wanted:
            stale.unlink()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
