"""Any model the ``rap`` command takes: a RAP model, or a design it imports.

:func:`detect` tells the format from what is given (a file, a directory, several
paths) or takes it from ``--format``; :func:`load` reads it and runs every check: a RAP
model through :func:`rap_cli.model_io.check_model_file`, a design through its importer
and then the same checks as a model (:func:`rap_schemas.plan.plan_findings`,
:func:`rap_schemas.model.model_findings`), their findings located in the design's files
through :meth:`rap_cli.importers.Imported.locate`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Literal, get_args

from rap_schemas.model import model_findings
from rap_schemas.plan import plan_findings

from .diagnostics import Diagnostic, Severity, sort_diagnostics
from .importers import Imported
from .model_io import CheckedModel, check_model_file

__all__ = ["FORMATS", "DesignError", "Format", "detect", "import_design", "load"]

Format = Literal["rap", "aadl", "aadl-il", "robochart"]
FORMATS: tuple[Format, ...] = get_args(Format)
DESIGN_FORMATS: tuple[Format, ...] = ("aadl", "aadl-il", "robochart")

_SUFFIXES: dict[str, Format] = {
    ".yaml": "rap",
    ".yml": "rap",
    ".aadl": "aadl",
    ".rct": "robochart",
    ".rac": "robochart",
}
_MAX_FILES = 2000
"""A directory with more design files than this is not a design (a home folder, say)."""


class DesignError(Exception):
    """What is given cannot be read as a model (exit 2): the message says what and how
    to fix it."""


def _format_of(path: Path) -> Format | None:
    if path.name == "design.json":
        return "aadl-il"
    return _SUFFIXES.get(path.suffix.lower())


def _files_of(directory: Path, fmt: Format | None) -> list[Path]:
    found: list[Path] = []
    for path in sorted(directory.rglob("*")):
        if not path.is_file() or any(part.startswith(".") for part in path.parts[-2:]):
            continue
        kind = _format_of(path)
        if kind is None or kind == "rap" or (fmt is not None and kind != fmt):
            continue
        found.append(path)
        if len(found) > _MAX_FILES:
            raise DesignError(
                f"{directory}: more than {_MAX_FILES} design files - name the design's own folder"
            )
    return found


def detect(paths: Sequence[Path], fmt: Format | None = None) -> tuple[Format, list[Path]]:
    """The format of the model given as ``paths`` and the files to read.

    A directory holding ``model.yaml`` is that RAP model; otherwise its design files
    (``.aadl``; ``.rct``/``.rac``; ``design.json``), searched recursively. Raises
    :class:`DesignError` when nothing, or several formats, are found."""
    if not paths:
        raise DesignError("no model given - name a model file or a design's folder")
    files: list[Path] = []
    for path in paths:
        if path.is_dir():
            model = path / "model.yaml"
            if fmt in (None, "rap") and model.is_file():
                files.append(model)
                continue
            inside = _files_of(path, fmt)
            if not inside:
                want = f"{fmt} files" if fmt else "a model.yaml or design files"
                raise DesignError(
                    f"{path}: a directory with no {want} (.aadl, .rct, .rac, design.json) "
                    "- name the model file, or check --format"
                )
            files += inside
        elif path.is_file():
            files.append(path)
        else:
            raise DesignError(f"{path}: no such file or directory - check the path")
    kinds = {_format_of(f) for f in files}
    if fmt is not None:
        return fmt, files
    if None in kinds:
        odd = next(f for f in files if _format_of(f) is None)
        raise DesignError(
            f"{odd}: cannot tell the format from the name - give --format ({', '.join(FORMATS)})"
        )
    if len(kinds) > 1:
        raise DesignError(
            f"the paths mix formats ({', '.join(sorted(str(k) for k in kinds))}) - import "
            "one design at a time, or give --format"
        )
    kind = kinds.pop()
    assert kind is not None
    if kind == "rap" and len(files) > 1:
        raise DesignError("several RAP models given - check one model at a time")
    if kind == "aadl-il" and len(files) > 1:
        raise DesignError("several design.json files given - import one at a time")
    return kind, files


def import_design(fmt: Format, files: Sequence[Path], *, root: str | None = None) -> Imported:
    """Run the importer of ``fmt`` on ``files``."""
    if fmt == "aadl":
        from .importers.aadl import import_aadl

        return import_aadl(files, root=root)
    if root is not None:
        raise DesignError(f"--root is for AADL designs, not {fmt} - leave it out")
    if fmt == "aadl-il":
        from .importers.aadl_il import import_aadl_il

        return import_aadl_il(files[0])
    if fmt == "robochart":
        from .importers.robochart import import_robochart

        return import_robochart(files)
    raise DesignError(f"{fmt!r} is not a design format - use one of {', '.join(DESIGN_FORMATS)}")


def load(
    paths: Sequence[Path], fmt: Format | None = None, *, root: str | None = None
) -> CheckedModel:
    """Read the model given as ``paths`` and check it (see the module's docstring)."""
    kind, files = detect(paths, fmt)
    if kind == "rap":
        if root is not None:
            raise DesignError("--root is for AADL designs, not RAP models - leave it out")
        return check_model_file(files[0])
    return checked_import(import_design(kind, files, root=root), ", ".join(map(str, paths)))


def checked_import(imported: Imported, source: str) -> CheckedModel:
    """An import with the model's own checks added, located in the design."""
    out = CheckedModel(source, plan=imported.plan, readable=imported.readable)
    out.diagnostics = list(imported.diagnostics)
    plan = imported.plan
    if plan is not None:
        fallback = imported.sources[0] if imported.sources else source
        for loc, problem, _key in plan_findings(plan):
            what, _, fix = problem.partition("; ")
            message = f"{what} - {fix}" if fix else what
            out.diagnostics.append(_located(imported, loc, "error", message, fallback))
        for f in model_findings(plan):
            out.diagnostics.append(_located(imported, f.loc, f.severity, f.message, fallback))
    out.diagnostics = sort_diagnostics(_unique(out.diagnostics))
    return out


def _located(
    imported: Imported, loc: Sequence[object], severity: Severity, message: str, fallback: str
) -> Diagnostic:
    where = imported.locate(tuple(loc))
    if where is None:
        return Diagnostic(fallback, 0, 0, severity, message)
    return Diagnostic(where.file, where.line, where.column, severity, message)


def _unique(diagnostics: list[Diagnostic]) -> list[Diagnostic]:
    seen: set[Diagnostic] = set()
    out: list[Diagnostic] = []
    for d in diagnostics:
        if d not in seen:
            seen.add(d)
            out.append(d)
    return out
