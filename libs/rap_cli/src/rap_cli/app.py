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

from .cli import FAILED, OK, USAGE, format_option, usage
from .designs import FORMATS, DesignError, Format, checked_import, detect, import_design, load
from .diagnostics import Diagnostic
from .exporters.aadl import export_aadl, write_aadl
from .model_io import CheckedModel
from .model_yaml import model_to_yaml
from .view import model_view

app = typer.Typer(
    name="rap",
    help="RAP's toolkit: import designs (AADL, AADL-IL, RoboChart), check and show system "
    "models, export them as AADL, generate the package that runs a model (rap new, rap "
    "generate), run it (rap up, rap down, rap health) and operate it while it runs (rap "
    "status, config, pause, resume, restart, swap, snapshot, restore, models, topic, logs, "
    "trace, record, replay, view).",
    no_args_is_help=True,
    rich_markup_mode="markdown",
    pretty_exceptions_enable=False,
    add_completion=False,
)
model_app = typer.Typer(help="Look at a system model.", no_args_is_help=True)
app.add_typer(model_app, name="model")
import_app = typer.Typer(
    help="Import a design into a RAP system model (YAML).", no_args_is_help=True
)
app.add_typer(import_app, name="import")
export_app = typer.Typer(help="Write a system model in another language.", no_args_is_help=True)
app.add_typer(export_app, name="export")


ModelArg = Annotated[
    list[Path],
    typer.Argument(
        help="The model: a RAP model (model.yaml, or a folder holding one) or a design to "
        "import: AADL (.aadl files or their folder), AADL-IL (design.json), RoboChart "
        "(.rct/.rac files or their folder).",
        show_default=False,
        metavar="MODEL...",
    ),
]
FormatOpt = Annotated[
    str | None,
    typer.Option(
        "--format",
        help="The model's format when its file names do not tell: " + ", ".join(FORMATS) + ".",
        show_default=False,
    ),
]
RootOpt = Annotated[
    str | None,
    typer.Option(
        "--root",
        help="AADL: the system implementation to instantiate (default: the one no other contains).",
        show_default=False,
    ),
]


@app.callback()
def _root() -> None:
    """RAP's toolkit: import designs, check, show and export system models, generate
    their packages, run them and operate them while they run."""


def _load(paths: list[Path], fmt: str | None = None, root: str | None = None) -> CheckedModel:
    try:
        return load(paths, format_option(fmt), root=root)
    except DesignError as exc:
        usage(str(exc))


def _counts(diags: list[Diagnostic]) -> str:
    n_err = sum(d.severity == "error" for d in diags)
    n_warn = sum(d.severity == "warning" for d in diags)
    return f"{n_err} error(s), {n_warn} warning(s)"


@app.command()
def check(model: ModelArg, fmt: FormatOpt = None, root: RootOpt = None) -> None:
    """Check a model: its schema, then what running it needs, then the cross-checks
    (inputs nobody produces, outputs nobody consumes, types across connections, names
    that do not exist, knowledge read but never written, an execute stage reachable
    without the Legitimate gate). Each finding names file:line:col."""
    checked = _load(model, fmt, root)
    for d in checked.diagnostics:
        typer.echo(d)
    if not checked.readable:
        raise typer.Exit(USAGE)
    typer.echo(f"{checked.source}: {_counts(checked.diagnostics)}")
    raise typer.Exit(OK if checked.ok else FAILED)


@model_app.command("show")
def show(
    model: ModelArg,
    as_json: Annotated[
        bool, typer.Option("--json", help="The normalized model as JSON (rap.ModelView).")
    ] = False,
    fmt: FormatOpt = None,
    root: RootOpt = None,
) -> None:
    """Print the normalized model: components with their ports, messages, compute
    nodes, bindings, connections and the checks' findings. Exit 0 when there is no
    error, 1 when the model has errors (still printed), 2 when it cannot be read."""
    checked = _load(model, fmt, root)
    view = model_view(checked)
    if as_json:
        typer.echo(json.dumps(view, indent=2))
    else:
        _print_view(view)
    if not checked.readable:
        raise typer.Exit(USAGE)
    raise typer.Exit(OK if checked.ok else FAILED)


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


PathsArg = Annotated[
    list[Path],
    typer.Argument(help="The design's files, or folders holding them.", show_default=False),
]
OutOpt = Annotated[
    Path | None,
    typer.Option(
        "--output",
        "-o",
        help="Where to write the model (default: standard output).",
        show_default=False,
    ),
]


def _import(fmt: Format, paths: list[Path], output: Path | None, root: str | None) -> None:
    try:
        _, files = detect(paths, fmt)
        imported = import_design(fmt, files, root=root)
    except DesignError as exc:
        usage(str(exc))
    checked = checked_import(imported, ", ".join(map(str, paths)))
    for d in checked.diagnostics:
        typer.echo(d, err=True)
    plan = checked.plan
    if plan is None or not checked.readable:
        typer.echo(f"rap: nothing imported: {_counts(checked.diagnostics)}", err=True)
        raise typer.Exit(USAGE)
    header = (
        f"Imported by `rap import {fmt}` from {len(files)} file(s): "
        + " ".join(f.name for f in files[:8])
        + (" ..." if len(files) > 8 else "")
        + "\nCheck it with `rap check`; "
        + ("the design has errors (see `rap check`)." if not checked.ok else "it checked clean.")
    )
    text = model_to_yaml(plan, header)
    if output is None:
        typer.echo(text, nl=False)
    else:
        try:
            output.parent.mkdir(parents=True, exist_ok=True)
            output.write_text(text, encoding="utf-8")
        except OSError as exc:
            usage(f"{output}: cannot write the model ({exc.strerror}) - choose another path")
    where = output if output is not None else "standard output"
    typer.echo(
        f"{where}: {len(plan.components)} component(s), {len(plan.messages)} message(s), "
        f"{len(plan.compute_nodes)} compute node(s), {len(plan.connections)} "
        f"connection(s); {_counts(checked.diagnostics)}",
        err=True,
    )
    raise typer.Exit(OK if checked.ok else FAILED)


@import_app.command("aadl")
def import_aadl_cmd(paths: PathsArg, output: OutOpt = None, root: RootOpt = None) -> None:
    """An AADL v2 design: its components are the processes of the root system's
    instance tree, its compute nodes the processors, its bindings
    Actual_Processor_Binding; messages from data types (the Data_Model annex). Exit 0
    when the design has no error, 1 when it has (the model is still written), 2 when
    nothing could be read."""
    _import("aadl", paths, output, root)


@import_app.command("aadl-il")
def import_aadl_il_cmd(paths: PathsArg, output: OutOpt = None) -> None:
    """RPIO's AADL-IL (design.json): its processes, ports, messages, compute nodes and
    bindings, with the file's defects reported."""
    _import("aadl-il", paths, output, None)


@import_app.command("robochart")
def import_robochart_cmd(paths: PathsArg, output: OutOpt = None) -> None:
    """A RoboChart design (.rct, with RoboArch .rac where given): each state machine
    a component, each connection endpoint a port, each record a message."""
    _import("robochart", paths, output, None)


@export_app.command("aadl")
def export_aadl_cmd(
    model: ModelArg,
    output: Annotated[
        Path, typer.Option("--output", "-o", help="The folder to write the AADL files into.")
    ],
    fmt: FormatOpt = None,
    root: RootOpt = None,
) -> None:
    """Write the model as AADL v2: the RAP property set, the messages (Data_Model
    types), the logical architecture (processes, ports, threads, modes, connections),
    the physical one (processors, buses) and the root system with the bindings.
    `rap import aadl` reads the folder back to the same model. Exit 1 (and nothing
    written) when the model has errors."""
    checked = _load(model, fmt, root)
    for d in checked.diagnostics:
        typer.echo(d, err=True)
    if not checked.readable:
        raise typer.Exit(USAGE)
    if checked.plan is None or not checked.ok:
        typer.echo(f"rap: not exported: {_counts(checked.diagnostics)}", err=True)
        raise typer.Exit(FAILED)
    try:
        written = write_aadl(checked.plan, output)
    except OSError as exc:
        usage(f"{output}: cannot write there ({exc.strerror}) - choose another folder")
    root_impl = export_aadl(checked.plan).root
    typer.echo(f"wrote {len(written)} files to {output} (root system {root_impl})")
    raise typer.Exit(OK)


def _register_commands() -> None:
    """Commands that live in modules of their own (each has ``register(app)``)."""
    from . import (
        admin_cli,
        certs_cli,
        generate_cli,
        logs_cli,
        models_cli,
        topic_cli,
        trace_cli,
        up,
        view_cli,
    )

    generate_cli.register(app)
    up.register(app)
    admin_cli.register(app)
    view_cli.register(app)
    topic_cli.register(app)
    logs_cli.register(app)
    trace_cli.register(app)
    certs_cli.register(app)
    models_cli.register(app)


_register_commands()


def main() -> None:
    app()


if __name__ == "__main__":
    main()
