"""Read a system model and find everything wrong with it, each finding located.

:func:`check_model_file` reads a RAP model (YAML), validates it against the model's
JSON Schema (every schema error, not only the first), then runs the checks running it
needs (:func:`rap_schemas.plan.plan_findings`) and the model's cross-checks
(:func:`rap_schemas.model.model_findings`).
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jsonschema
from rap_schemas import DeploymentPlan
from rap_schemas.export import PLAN_SCHEMA, render
from rap_schemas.limits import MAX_YAML_BYTES
from rap_schemas.model import model_findings
from rap_schemas.plan import PlanError, plan_findings
from rap_schemas.yamlconf import YamlDocument, YamlError, parse_yaml, read_text_file

from .diagnostics import Diagnostic, sort_diagnostics

__all__ = ["CheckedModel", "check_model_file", "check_model_text"]


@dataclass(slots=True)
class CheckedModel:
    """A model file and what the checks found. ``plan`` is None when the file does not
    fit the schema; ``readable`` is False when it could not be read as YAML at all."""

    source: str
    plan: DeploymentPlan | None = None
    document: YamlDocument | None = None
    diagnostics: list[Diagnostic] = field(default_factory=list)
    readable: bool = True

    @property
    def ok(self) -> bool:
        return self.readable and not any(d.severity == "error" for d in self.diagnostics)


@functools.cache
def _validator() -> jsonschema.Draft202012Validator:
    schema = json.loads(render()[PLAN_SCHEMA])
    return jsonschema.Draft202012Validator(schema)


def check_model_file(path: str | Path) -> CheckedModel:
    """Read and check the model at ``path``."""
    source = str(path)
    try:
        text = read_text_file(path, what="model", error=PlanError, max_bytes=MAX_YAML_BYTES)
    except YamlError as exc:
        return _unreadable(source, exc)
    return check_model_text(text, source)


def check_model_text(text: str, source: str = "<model>") -> CheckedModel:
    """Check a model given as text (``source`` names it in the findings)."""
    try:
        document = parse_yaml(text, source, what="model", error=PlanError)
    except YamlError as exc:
        return _unreadable(source, exc)
    out = CheckedModel(source, document=document)
    if not isinstance(document.data, dict):
        out.diagnostics.append(
            Diagnostic(source, 1, 1, "error", "a model is a mapping - start with 'system: <name>'")
        )
        return out
    schema_errors = sorted(_validator().iter_errors(document.data), key=_error_order)
    for err in schema_errors:
        out.diagnostics.append(_schema_diagnostic(document, err))
    if schema_errors:
        out.diagnostics = sort_diagnostics(out.diagnostics)
        return out
    try:  # what the schema cannot say (a bridge's URL, say): at the field's line
        plan = document.convert(DeploymentPlan)
    except PlanError as exc:
        line, col = exc.line or 1, exc.column or 1
        text = str(exc).removeprefix(f"{source}:{line}:{col}: ")
        out.diagnostics.append(Diagnostic(source, line, col, "error", text))
        return out
    out.plan = plan
    for loc, problem, key in plan_findings(plan):
        line, col = document.position(loc, key=key)
        what, _, fix = problem.partition("; ")
        message = f"{what} - {fix}" if fix else what
        out.diagnostics.append(Diagnostic(source, line, col, "error", message))
    for f in model_findings(plan):
        line, col = document.position(f.loc, key=f.key)
        out.diagnostics.append(Diagnostic(source, line, col, f.severity, f.message))
    out.diagnostics = sort_diagnostics(out.diagnostics)
    return out


def _unreadable(source: str, exc: YamlError) -> CheckedModel:
    message = str(exc)
    prefix = f"{source}:"
    if message.startswith(prefix):  # "source:line:col: problem" -> the problem
        rest = message[len(prefix) :].split(":", 2)
        if len(rest) == 3 and rest[0].isdigit() and rest[1].isdigit():
            message = rest[2].strip()
        else:
            message = message[len(prefix) :].strip()
    diag = Diagnostic(
        source, exc.line, exc.column, "error", f"{message} - fix the file so that it reads"
    )
    return CheckedModel(source, diagnostics=[diag], readable=False)


def _error_order(err: jsonschema.ValidationError) -> tuple[str, ...]:
    return tuple(str(p) for p in err.absolute_path)


def _optional_branch(err: jsonschema.ValidationError) -> jsonschema.ValidationError | None:
    """For a value that fits neither ``null`` nor the one other form of an optional
    field (``bridge: {...}``): the error inside that form, which says what is wrong."""
    options: Any = err.validator_value
    if err.instance is None or not isinstance(options, list) or len(options) != 2:
        return None
    nulls = [i for i, o in enumerate(options) if isinstance(o, dict) and o.get("type") == "null"]
    if len(nulls) != 1:
        return None
    other = 1 - nulls[0]
    inner = [e for e in err.context or () if e.schema_path and e.schema_path[0] == other]
    return jsonschema.exceptions.best_match(inner) if inner else None


def _schema_diagnostic(document: YamlDocument, err: jsonschema.ValidationError) -> Diagnostic:
    if err.validator == "anyOf":
        inner = _optional_branch(err)
        if inner is not None:
            return _schema_diagnostic(document, inner)
    loc = list(err.absolute_path)
    key = False
    message = err.message
    if err.validator == "additionalProperties":
        extra = _extra_keys(err)
        if extra:
            loc.append(extra[0])
            key = True
        allowed = sorted(err.schema.get("properties", {}))  # type: ignore[union-attr]
        message = (
            f"unknown field {', '.join(repr(e) for e in extra)} - the fields here are: "
            f"{', '.join(allowed)}"
        )
    elif err.validator == "required":
        message = f"{err.message} - add it"
    elif err.validator == "enum":
        options = ", ".join(repr(o) for o in err.validator_value)  # type: ignore[union-attr]
        message = f"{err.instance!r} is not one of {options} - use one of them"
    elif err.validator == "pattern":
        message = f"{err.instance!r} does not have the expected form - {_describe(err)}"
    elif err.validator == "type":
        message = f"{err.message} - write a {err.validator_value} here"
    elif err.validator == "anyOf":
        message = f"{err.instance!r} fits none of the allowed forms - {_describe(err)}"
    elif err.validator == "propertyNames":
        message = f"{err.message} - use letters, digits and '_.-~+:@=%,' in names"
    line, col = document.position(tuple(loc), key=key)
    path = "$" + "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in err.absolute_path)
    return Diagnostic(document.source, line, col, "error", f"{path}: {message}")


def _extra_keys(err: jsonschema.ValidationError) -> list[str]:
    allowed = set(err.schema.get("properties", {}))  # type: ignore[union-attr]
    instance: Any = err.instance
    if isinstance(instance, dict):
        return [str(k) for k in instance if k not in allowed]
    return []


def _describe(err: jsonschema.ValidationError) -> str:
    schema: Any = err.schema
    if isinstance(schema, dict):
        text = schema.get("description")
        if not text:
            for option in schema.get("anyOf", []):
                if isinstance(option, dict) and option.get("description"):
                    text = option["description"]
                    break
        examples = schema.get("examples")
        if text:
            return str(text) + (f" e.g. {examples[0]!r}" if examples else "")
    return "see the model reference in docs/toolkit.md"
