"""``rap new`` and ``rap generate``: from a model (or a design) to a package that runs."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated

import typer
from rap_schemas import PlanDocument, PlanError

from .cli import USAGE, format_option, usage
from .designs import DesignError, load
from .generate.names import package_name
from .generate.package import (
    Generated,
    GenerateError,
    generate_package,
    package_dir,
    write_model,
)
from .model_io import CheckedModel

__all__ = ["STARTER", "register"]

STARTER = """\
# The system model of {name}: what runs where, and how the parts talk.
# `rap check model.yaml` checks it; `rap generate model.yaml` regenerates the package
# after you change it (your code in the nodes' user regions is kept).
system: {name}
doc: A MAPLE-K loop that watches a sensor and adapts an actuator.

compute_nodes:
  laptop:
    doc: One machine runs everything while you develop.

knowledge:
  backend: memory
  node: laptop

messages:
  Reading:
    doc: A sensor reading.
    fields:
      value: {{type: float, doc: The measured value.}}
  Setpoint:
    doc: What the actuator should do.
    fields:
      target: {{type: float, ge: -10, le: 10, doc: The new set point.}}

components:
  robot:
    role: managed
    external: true
    node: laptop
    doc: The managed system (its drivers or a simulator); RAP does not start it.
    ports:
      reading: {{direction: out, kind: data, type: Reading, topic: robot/reading}}
      setpoint: {{direction: in, kind: data, type: Setpoint, topic: robot/setpoint}}
  monitor:
    stage: monitor
    node: laptop
    ports:
      reading: {{direction: in, kind: data, type: Reading, topic: robot/reading}}
      observed: {{direction: out, type: Reading, topic: observed}}
    writes: [last_reading]
  analyse:
    stage: analyse
    node: laptop
    ports:
      observed: {{direction: in, type: Reading, topic: observed}}
      deviation: {{direction: out, type: Reading, topic: deviation}}
    reads: [last_reading]
  plan:
    stage: plan
    node: laptop
    ports:
      deviation: {{direction: in, type: Reading, topic: deviation}}
      proposal: {{direction: out, type: Setpoint, topic: new-plan}}
  # plan -> legitimate -> execute: the plan is proposed on the Legitimate gate's event
  # new-plan (as a rap.PlanProposal/1 holding the Setpoint) and approved on its event
  # verdict; execute acts only on approved set points.
  legitimate:
    stage: legitimate
    node: laptop
    doc: Checks each proposed set point before it may run.
    ports:
      proposal: {{direction: in, type: Setpoint, topic: new-plan}}
      approved: {{direction: out, type: Setpoint, topic: verdict}}
  execute:
    stage: execute
    node: laptop
    doc: Acts only on set points the legitimate stage approved (the gate).
    ports:
      approved: {{direction: in, type: Setpoint, topic: verdict}}
      setpoint: {{direction: out, kind: data, type: Setpoint, topic: robot/setpoint}}
"""


def _checked(paths: list[Path], fmt: str | None, root: str | None) -> CheckedModel:
    try:
        checked = load(paths, format_option(fmt), root=root)
    except DesignError as exc:
        usage(str(exc))
    for d in checked.diagnostics:
        typer.echo(d, err=True)
    if not checked.readable or checked.plan is None:
        raise typer.Exit(USAGE)
    errors = sum(d.severity == "error" for d in checked.diagnostics)
    if errors:
        typer.echo(
            f"rap: the model has {errors} error(s) (above; 'rap check' lists them again): "
            "generating it as it stands - the generated code does what the model says, "
            "defects included",
            err=True,
        )
    return checked


def _document(checked: CheckedModel) -> PlanDocument:
    assert checked.plan is not None
    try:
        return PlanDocument.from_plan(checked.plan, checked.source)
    except PlanError as exc:
        usage(f"{exc} - fix the model, then generate again")


def _generate(doc: PlanDocument, out: Path, package: str, deploy_only: bool = False) -> Generated:
    try:
        return generate_package(doc, out, package=package, deploy_only=deploy_only)
    except GenerateError as exc:
        usage(str(exc))
    except OSError as exc:
        usage(f"{out}: cannot write there ({exc.strerror or exc}) - choose another folder")


def _report(result: Generated) -> None:
    for w in result.warnings:
        typer.echo(f"rap: warning: {w}", err=True)
    kept = f"; kept as you have them: {', '.join(result.kept)}" if result.kept else ""
    typer.echo(f"wrote {len(result.written)} file(s) in {result.root}{kept}")


def register(app: typer.Typer) -> None:
    """Add ``new`` and ``generate`` to ``app``."""

    @app.command("new")
    def new(
        name: Annotated[str, typer.Argument(help="The package's folder (and Python name).")],
        source: Annotated[
            list[Path] | None,
            typer.Option(
                "--from",
                help="A design to start from: AADL (.aadl files or their folder), AADL-IL "
                "(design.json) or RoboChart (.rct/.rac files or their folder).",
                show_default=False,
            ),
        ] = None,
        fmt: Annotated[
            str | None,
            typer.Option("--format", help="The design's format, when names do not tell."),
        ] = None,
        root: Annotated[
            str | None, typer.Option("--root", help="AADL: the system implementation to use.")
        ] = None,
    ) -> None:
        """Create a package in ./NAME: `model.yaml` at its root, a node module per
        component in `nodes/`, the messages module, tests, deploy files and a README.
        With `--from`, the model is imported from a design first."""
        out = Path(name)
        package = package_name(out.name)
        if out.exists() and any(out.iterdir()):
            hint = (
                f", or run 'rap generate {out}/model.yaml' to regenerate the package there"
                if (out / "model.yaml").is_file()
                else ""
            )
            usage(f"{out} exists and is not empty - choose a new name{hint}")
        taken = _taken(package, out)
        if taken is not None:
            usage(
                f"{name}: its Python package would be {package!r}, but that name is taken "
                f"by {taken}; importing the package would find that instead - choose "
                "another name"
            )
        if source:
            checked = _checked(list(source), fmt, root)
            doc = _document(checked)
            origin = f"imported from {', '.join(_relative(s, out) for s in source)} by rap new"
        else:
            text = STARTER.format(name=package)
            from .model_io import check_model_text

            checked = check_model_text(text, str(out / "model.yaml"))
            doc = _document(checked)
            origin = "written by rap new as a starting point"
        out.mkdir(parents=True, exist_ok=True)
        result = _generate(doc, out, package)
        header = (
            f"# The system model of {doc.plan.system}, {origin}.\n"
            "# rap check model.yaml checks it; rap generate model.yaml regenerates the\n"
            "# package after a change (your code in the user regions is kept).\n"
        )
        if source:
            write_model(result.plan, out / "model.yaml", header)
        else:
            (out / "model.yaml").write_text(_with_modules(text, result), encoding="utf-8")
        _report(result)
        typer.echo(f"\nnext:\n  cd {out}\n  python -m pytest\n  rap up model.yaml --all")

    @app.command("generate")
    def generate(
        model: Annotated[
            list[Path],
            typer.Argument(help="The model (model.yaml, or a design).", show_default=False),
        ],
        output: Annotated[
            Path | None,
            typer.Option("-o", "--output", help="Folder of the package (default: the model's)."),
        ] = None,
        package: Annotated[
            str | None,
            typer.Option("--package", help="Python package name (default: the folder's name)."),
        ] = None,
        fmt: Annotated[str | None, typer.Option("--format", help="The model's format.")] = None,
        root: Annotated[str | None, typer.Option("--root", help="AADL root system.")] = None,
        deploy_only: Annotated[
            bool,
            typer.Option(
                "--deploy-only",
                help="Only deploy/ (per compute node: plan slice, Zenoh configs, "
                "compose.yaml; the Dockerfile and lock), for a model whose components "
                "all name their modules, e.g. the lidar example.",
            ),
        ] = False,
    ) -> None:
        """Generate the package of a model: messages (msgspec Structs and JSON Schema), a
        node per component (user code in marked regions survives regeneration), tests,
        and per compute node the runner's plan, Zenoh configs, compose.yaml and a
        Dockerfile (`deploy/`)."""
        checked = _checked(list(model), fmt, root)
        doc = _document(checked)
        first = model[0]
        out = output or (first.parent if first.is_file() else first)
        pkg = package or _existing_package(doc, out) or package_name(out.resolve().name)
        result = _generate(doc, out, pkg, deploy_only)
        target = out / "model.yaml"
        same = first.is_file() and target.exists() and target.resolve() == first.resolve()
        if result.plan != doc.plan or not same:
            if same:
                typer.echo(
                    f"rap: {target}: filled in module: of the generated components (the "
                    "file is rewritten: its comments are not kept)",
                    err=True,
                )
            write_model(
                result.plan,
                target,
                f"# The system model of {doc.plan.system} (rap generate "
                f"{', '.join(_relative(m, out) for m in model)}).\n",
            )
            result.written.append("model.yaml")
        _report(result)


def _existing_package(doc: PlanDocument, out: Path) -> str | None:
    """The package an earlier generation wrote into ``out`` (its components' modules
    name ``<package>.nodes.<module>:node`` and that folder is there, in ``out`` or in
    ``out/src``): the folder's name may have changed since (a clone, a copy)."""
    for comp in doc.plan.components.values():
        if comp.module is None:
            continue
        head, sep, _ = comp.module.partition(".nodes.")
        if sep and head.isidentifier() and (out / package_dir(out, head) / "nodes").is_dir():
            return head
    return None


def _relative(path: Path, out: Path) -> str:
    """``path`` relative to the folder ``out`` the model is written in (POSIX), so that
    the model's header records no machine's path."""
    try:
        return Path(os.path.relpath(path.resolve(), out.resolve())).as_posix()
    except ValueError:  # another drive (Windows): its name alone
        return path.name


def _taken(package: str, out: Path) -> str | None:
    """What already answers to ``package`` on import (a module of the standard library,
    of RAP, of an installed distribution), or None; the package of the folder ``out``
    itself (``out/<package>``, ``out/src/<package>``: an install of that very project)
    does not count."""
    import importlib.util

    try:
        spec = importlib.util.find_spec(package)
    except (ImportError, ValueError):
        return None
    if spec is None:
        return None
    where = spec.origin or (list(spec.submodule_search_locations or []) or ["a namespace"])[0]
    own = [(out / package).resolve(), (out / "src" / package).resolve()]
    found = Path(where).resolve()
    if any(found == d or d in found.parents for d in own):
        return None
    return where


def _with_modules(text: str, result: Generated) -> str:
    """The starter model's text with ``module:`` lines under each generated component
    (keeping its comments)."""
    lines = text.splitlines()
    out: list[str] = []
    for line in lines:
        out.append(line)
        stripped = line.strip()
        if line.startswith("  ") and not line.startswith("   ") and stripped.endswith(":"):
            comp = result.plan.components.get(stripped[:-1])
            if comp is not None and comp.module is not None:
                out.append(f"    module: {comp.module}")
    return "\n".join(out) + "\n"
