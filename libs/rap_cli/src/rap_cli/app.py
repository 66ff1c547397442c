"""The ``rap`` command line (typer).

Exit codes: 0 ok, 1 the checked thing is wrong, 2 bad usage or unreadable input.
Findings read ``file:line:col: severity: what - how to fix``, several per run, never a
traceback.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from .diagnostics import Diagnostic
from .model_io import CheckedModel, check_model_file
from .view import model_view

app = typer.Typer(
    name="rap",
    help="RAP's toolkit: check and show system models.",
    no_args_is_help=True,
    rich_markup_mode="rich",
    pretty_exceptions_enable=False,
    add_completion=False,
)
model_app = typer.Typer(help="Look at a system model.", no_args_is_help=True)
app.add_typer(model_app, name="model")

OK, WRONG, UNUSABLE = 0, 1, 2

ModelArg = Annotated[
    Path,
    typer.Argument(
        help="The model: a RAP model file (model.yaml).", show_default=False, metavar="MODEL"
    ),
]


@app.callback()
def _root() -> None:
    """RAP's toolkit: check and show system models."""


def _load(path: Path) -> CheckedModel:
    if path.is_dir():
        candidate = path / "model.yaml"
        if not candidate.is_file():
            _usage(f"{path}: a directory with no model.yaml - name the model file")
        path = candidate
    elif not path.exists():
        _usage(f"{path}: no such file - check the path")
    elif path.suffix.lower() not in (".yaml", ".yml"):
        _usage(
            f"{path}: not a RAP model (.yaml) - the importers of AADL (.aadl), AADL-IL "
            "(design.json) and RoboChart (.rct) designs are not part of this version"
        )
    return check_model_file(path)


def _usage(message: str) -> None:
    typer.echo(f"rap: error: {message}", err=True)
    raise typer.Exit(UNUSABLE)


def _counts(diags: list[Diagnostic]) -> str:
    n_err = sum(d.severity == "error" for d in diags)
    n_warn = sum(d.severity == "warning" for d in diags)
    return f"{n_err} error(s), {n_warn} warning(s)"


@app.command()
def check(model: ModelArg) -> None:
    """Check a model: its schema, then what running it needs, then the cross-checks
    (inputs nobody produces, outputs nobody consumes, types across connections, names
    that do not exist, knowledge read but never written, an execute stage reachable
    without the Legitimate gate). Each finding names file:line:col."""
    checked = _load(model)
    for d in checked.diagnostics:
        typer.echo(d)
    if not checked.readable:
        raise typer.Exit(UNUSABLE)
    typer.echo(f"{checked.source}: {_counts(checked.diagnostics)}")
    raise typer.Exit(OK if checked.ok else WRONG)


@model_app.command("show")
def show(
    model: ModelArg,
    as_json: Annotated[
        bool, typer.Option("--json", help="The normalized model as JSON (rap.ModelView).")
    ] = False,
) -> None:
    """Print the normalized model: components with their ports, messages, compute
    nodes, bindings, connections and the checks' findings. Exit 0 when there is no
    error, 1 when the model has errors (still printed), 2 when it cannot be read."""
    checked = _load(model)
    view = model_view(checked)
    if as_json:
        typer.echo(json.dumps(view, indent=2))
    else:
        _print_view(view)
    if not checked.readable:
        raise typer.Exit(UNUSABLE)
    raise typer.Exit(OK if checked.ok else WRONG)


def _print_view(view: dict[str, object]) -> None:
    comps = view["components"]
    assert isinstance(comps, list)
    bindings = view["bindings"]
    assert isinstance(bindings, dict)
    typer.echo(f"components ({len(comps)}):")
    for c in comps:
        role = c["stage"] or c.get("role") or "-"
        typer.echo(f"  {c['name']:<20} {role:<11} on {bindings.get(c['name']) or '(unbound)'}")
        for p in c["ports"]:
            typer.echo(f"      {p['direction']:<6} {p['kind']:<10} {p['name']}: {p['type'] or '-'}")
    for section in ("messages", "nodes", "connections", "diagnostics"):
        items = view[section]
        assert isinstance(items, list)
        typer.echo(f"{section} ({len(items)}):")
        for item in items:
            if section == "messages":
                fields = ", ".join(f"{f['name']}: {f['type']}" for f in item["fields"])
                typer.echo(f"  {item['name']} {{{fields}}}")
            elif section == "nodes":
                typer.echo(f"  {item['name']} {item['address'] or ''}".rstrip())
            elif section == "connections":
                typer.echo(f"  {item['from']} -> {item['to']}")
            else:
                typer.echo(
                    f"  {item['file']}:{item['line']}: {item['severity']}: {item['message']}"
                )


def main() -> None:
    app()
